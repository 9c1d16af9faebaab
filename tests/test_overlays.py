"""Overlays (``--set KEY=VALUE``, ``--scenario-text YAML``) on scenario and run files:
applied to the file's data before it is checked, so overlaid values meet the file's
checks and a run's key and ``run.yaml`` are those of the file they make."""

import json

import pytest

from reachwatch.pipeline import cli
from reachwatch.pipeline.commands import scenario_from_args
from reachwatch.pipeline.overlays import key_parts

#: A controller factory whose module leaves a file behind when it is imported (as any
#: code of a shared scenario file could), steering by a parameter it requires.
FACTORY = """\
from pathlib import Path
Path(__file__).with_name("imported.txt").write_text("the factory's module ran")

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U


class Constant(LeafSystem):
    def __init__(self, *, steering):
        super().__init__()
        self.steering = steering
        self.DeclareAbstractInputPort("color_image", AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, self._steer)

    def _steer(self, context, output):
        output.SetAtIndex(0, self.steering)


def make(config):
    return Constant(**config.parameters)
"""


def _factory(tmp_path):
    folder = tmp_path / "controller"
    folder.mkdir(exist_ok=True)
    (folder / "constant.py").write_text(FACTORY)
    return folder / "imported.txt", f"{folder / 'constant.py'}:make"


def _scenario(argv):
    return scenario_from_args(cli.build_parser().parse_args(argv))


def _one_line_error(capsys, argv) -> str:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_keys_are_dotted_paths_with_list_indices():
    assert key_parts("guard.check_starts") == ["guard", "check_starts"]
    assert key_parts("train[0].hour") == key_parts("train.0.hour") == ["train", 0, "hour"]
    for bad in ("", ".grid", "grid.", "a..b", "0.hour", "train[x]", "a b"):
        with pytest.raises(ValueError, match="is not a dotted key"):
            key_parts(bad)


def test_set_and_text_overlays_change_the_scenario_in_the_order_given(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("controller: {speed: 4.0, parameters: {a: 1.0}}\ncamera: {width: 64}\n")
    scenario = _scenario(["render", "--scenario", str(path), "--out", "o",
                          "--set", "controller.parameters.b=2",
                          "--scenario_text", "{controller: {speed: 3.0}, camera: {height: 36}}",
                          "--set", "controller.speed=2.5", "--set", "initial_state.px=1.0e-1"])
    assert scenario.controller.speed == 2.5                 # the last one given wins
    assert scenario.controller.parameters == {"a": 1.0, "b": 2.0}      # mappings merged
    assert (scenario.camera.width, scenario.camera.height) == (64, 36)
    assert scenario.initial_state.px == 0.1
    # without a file: the built-in defaults, overlaid
    assert _scenario(["render", "--out", "o", "--set", "duration=2"]).duration == 2.0
    with pytest.raises(ValueError, match="expected a YAML mapping"):
        _scenario(["render", "--out", "o", "--scenario-text", "[1, 2]"])


@pytest.mark.parametrize("argv, message", [
    (["--set", "controller.sped=3"], "--set controller.sped=3: scenario.controller.sped: "
                                     "unknown field of ControllerConfig; known fields: factory"),
    (["--scenario-text", "{camera: {widht: 64}}"], "--scenario-text: scenario.camera.widht: "
                                                   "unknown field of CameraConfig"),
    (["--set", "duration.x=1"], "--set duration.x=1: scenario.duration is a float, not a "
                                "mapping or a list"),
    # overlaid values meet the checks a value in the file meets
    (["--set", "controller.speed=-3"], "controller.speed must be"),
    (["--set", "controller.speed=fast"], "scenario.controller.speed: expected float, got str"),
    (["--set", "duration=.nan"], "duration must be"),
])
def test_a_bad_overlay_is_one_line_with_rc_2(tmp_path, capsys, argv, message):
    err = _one_line_error(capsys, ["render", "--out", str(tmp_path / "o")] + argv)
    assert message in err
    assert not (tmp_path / "o").exists()


def test_set_refuses_what_is_not_key_value(capsys):
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["render", "--out", "o", "--set", "grid"])
    assert "'grid' is not KEY=VALUE" in capsys.readouterr().err


def test_run_file_overlays_reach_the_keys_and_a_repeat_is_cached(tmp_path, capsys):
    _, factory = _factory(tmp_path)
    path = tmp_path / "run.yaml"
    path.write_text(f"name: overlaid\n"
                    f"scenario:\n  camera: {{width: 64, height: 36}}\n"
                    f"  controller: {{factory: '{factory}', parameters: {{steering: 0.0}}}}\n"
                    f"train: [{{runway: KMWH, hour: 9.0, sky: clear}}]\n"
                    f"test: [{{runway: KSFO, hour: 17.0, sky: clear}}]\n"
                    f"grid: [5, 3, 5]\nhorizon: 2.0\nincremental: {{enabled: false}}\n")
    argv = ["run", "--scenario", str(path), "--out", str(tmp_path / "out"), "--executor",
            "inline", "--until", "sweep", "--set", "grid=[3,3,3]",
            "--run-text", "{test: [{runway: KMWH, hour: 17.0, sky: clear}]}"]
    assert cli.main(argv) == 0
    recorded = (tmp_path / "out" / "run.yaml").read_text()
    assert "grid: [3, 3, 3]" in recorded and "KSFO" not in recorded
    records = sorted((tmp_path / "out" / "stages").glob("sweep_*.json"))
    assert [p.stem for p in records] == ["sweep_KMWH_17h_clear", "sweep_KMWH_9h_clear"]
    first = {p.stem: json.loads(p.read_text()) for p in records}
    assert all("_3x3x3_" in r["key"] and r["outputs"]["states"] == 27 for r in first.values())
    capsys.readouterr()
    assert cli.main(argv) == 0                      # the same overlays: nothing re-run
    assert capsys.readouterr().out.count("up to date") == 2
    assert {p.stem: json.loads(p.read_text()) for p in records} == first
    # an overlay that changes a swept input changes the key (and runs again)
    assert cli.main(argv + ["--set", "scenario.controller.parameters.steering=0.1"]) == 0
    again = json.loads(records[0].read_text())
    assert again["key"] != first[records[0].stem]["key"] and again["outputs"]["rendered"] == 27
