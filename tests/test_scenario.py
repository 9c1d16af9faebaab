import pytest

from reachwatch.diagrams import Scenario, ScenarioError, dump_scenario, load_scenario
from reachwatch.systems import RunwaySpec


def test_defaults_and_round_trip():
    s = load_scenario(data="environment: {runway: KATL, hour: 17.0, sky: overcast}\n")
    assert s.environment.runway == "KATL" and s.environment.sky == "overcast"
    assert s.camera.width == 360 and s.camera.height == 200    # untouched defaults
    again = load_scenario(data=dump_scenario(s))
    assert again == s


def test_custom_runway_from_yaml():
    text = """
environment:
  runway: MINE
  runway_spec:
    name: MINE
    half_width: 14.0
    surface: {kind: concrete, tone: [0.5, 0.5, 0.5]}
    taxiway_lines: [{start: 90.0, side: -1}]
"""
    s = load_scenario(data=text)
    spec = s.environment.spec()
    assert isinstance(spec, RunwaySpec) and spec.half_width == 14.0
    assert spec.taxiway_lines[0].side == -1
    assert s.environment.half_width == 14.0


@pytest.mark.parametrize("text, where", [
    ("camera: {heigth: 200}", "scenario.camera.heigth"),
    ("camera: {height: tall}", "scenario.camera.height"),
    ("camera: {height: 200.0}", "scenario.camera.height"),
    ("seed: 1.5", "scenario.seed"),
    ("environment: {runway: [a, b]}", "scenario.environment.runway"),
    ("camera: 5", "scenario.camera"),
    ("environment: {runway_spec: {lights: {spacing: x}}}",
     "scenario.environment.runway_spec.lights.spacing"),
    ("environment: {runway_spec: {taxiway_lines: {start: 1.0}}}",
     "scenario.environment.runway_spec.taxiway_lines"),
    ("environment: {runway_spec: {taxiway_lines: [{strat: 1.0}]}}",
     "scenario.environment.runway_spec.taxiway_lines[0].strat"),
])
def test_schema_errors_name_the_field(text, where):
    with pytest.raises(ScenarioError) as info:
        load_scenario(data=text)
    assert where in str(info.value)


@pytest.mark.parametrize("text, word", [
    ("environment: {runway: EGLL}", "EGLL"),
    ("environment: {hour: 25.0}", "hour"),
    ("environment: {sky: foggy}", "sky"),
    ("camera: {width: 4}", "width"),
    ("duration: -1.0", "duration"),
    ("environment: {runway_spec: {surface: {kind: gravel}}}", "surface.kind"),
])
def test_value_errors_name_the_field(text, word):
    with pytest.raises(ScenarioError, match=word):
        load_scenario(data=text)


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")


def test_file_and_empty(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("initial_state: {px: 2.0, theta_deg: -5.0}\n")
    s = load_scenario(path)
    assert s.initial_state.px == 2.0 and s.initial_state.theta_deg == -5.0
    path.write_text("")                      # an empty file is a mistake, not "all defaults"
    with pytest.raises(ScenarioError, match="is empty; write '{}' for all defaults"):
        load_scenario(path)
    path.write_text("{}\n")
    assert load_scenario(path) == Scenario()
    assert load_scenario(data="") == Scenario()      # an empty string still means defaults


def test_malformed_yaml():
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(data="camera: {width: 64\n")


@pytest.mark.parametrize("path", sorted(
    __import__("pathlib").Path(__file__).parents[1].glob("scenarios/*.yaml")))
def test_shipped_scenarios_load(path):
    """Scenario files and run files (those naming training environments) both load."""
    from pydrake.common.yaml import yaml_load_data
    if {"train", "train_random"} & set(yaml_load_data(path.read_text()) or {}):
        from reachwatch.pipeline.spec import load_run_spec
        assert load_run_spec(path).validate()
    else:
        assert load_scenario(path).validate()
