"""Overlays (``--set KEY=VALUE``, ``--scenario-text YAML``) on scenario and run files:
applied to the file's data before it is checked, so overlaid values meet the file's
checks and a run's key and ``run.yaml`` are those of the file they make; and a scenario
naming a controller factory is loaded without running the factory's code."""

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
    path.write_text("controller: {speed: 4.0, factory: 'mine.steer:make', parameters: {a: 1.0}}"
                    "\ncamera: {width: 64}\n")
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


def test_an_overlays_error_names_it_once(tmp_path, capsys):
    """The overlay's own label leads its error, after the file's name, not twice."""
    err = _one_line_error(capsys, ["render", "--out", str(tmp_path / "o"), "--set",
                                   "controller.sped=3"])
    assert err.count("--set controller.sped=3") == 1, err


def test_a_text_overlays_error_names_the_flag_it_was_given_as(tmp_path, capsys):
    path = tmp_path / "run.yaml"
    path.write_text("train: [{runway: KMWH, hour: 9.0, sky: clear}]\n")
    for flag in ("--run-text", "--run_text", "--scenario-text"):
        err = _one_line_error(capsys, ["run", "--scenario", str(path), "--out",
                                       str(tmp_path / "o"), flag, "{grid2: [3, 3, 3]}"])
        canonical = flag.replace("_", "-")
        assert f"{canonical}: run.grid2: unknown field of RunSpec" in err
        assert ("--run-text" in err) == (canonical == "--run-text")


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


def test_loading_a_scenario_runs_no_factory_code(tmp_path, capsys):
    """A scenario file naming a factory is data until a command builds the controller:
    loading it, rendering and exporting the open-loop world import nothing of it; the
    graph of the closed loop builds the controller, so it imports and runs it."""
    marker, factory = _factory(tmp_path)
    path = tmp_path / "s.yaml"
    path.write_text(f"camera: {{width: 64, height: 36}}\nduration: 0.1\n"
                    f"controller: {{factory: '{factory}', parameters: {{steering: 0.02}}}}\n")
    scenario = _scenario(["render", "--scenario", str(path), "--out", "o"])
    assert scenario.controller.factory == factory
    assert cli.main(["render", "--scenario", str(path), "--out", str(tmp_path / "r")]) == 0
    assert cli.main(["graph", "--loop", "world", "--scenario", str(path), "--out",
                     str(tmp_path / "g")]) == 0
    assert not marker.exists()
    assert cli.main(["graph", "--scenario", str(path), "--out", str(tmp_path / "g")]) == 0
    assert marker.exists() and "name=controller" in (tmp_path / "g" / "closed_loop.dot").read_text()
    # a command that needs the controller imports it, and it runs
    assert cli.main(["simulate", "--scenario", str(path), "--out", str(tmp_path / "sim"),
                     "--no-meshcat"]) == 0
    assert marker.exists() and list((tmp_path / "sim").glob("*_trajectory.csv"))


def test_a_bad_factory_name_is_one_line_when_loaded_its_code_when_needed(tmp_path, capsys):
    path = tmp_path / "s.yaml"
    for factory, message in (("nowhere.py:make", "controller.factory: file not found: nowhere.py"),
                             ("constant.make", "controller.factory must be 'package.module:"
                                               "function' or 'path/to/file.py:function'")):
        path.write_text(f"controller: {{factory: '{factory}'}}\n")
        assert message in _one_line_error(
            capsys, ["render", "--scenario", str(path), "--out", str(tmp_path / "o")])
    # code that fails on import: not run to render; one line where it is first needed
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "f.py").write_text("raise RuntimeError('boom')\n")
    path.write_text(f"camera: {{width: 64, height: 36}}\ncontroller: {{factory: "
                    f"'{folder / 'f.py'}:make'}}\n")
    assert cli.main(["render", "--scenario", str(path), "--out", str(tmp_path / "r")]) == 0
    err = _one_line_error(capsys, ["simulate", "--scenario", str(path), "--out",
                                   str(tmp_path / "sim"), "--no-meshcat"])
    assert "importing it failed: RuntimeError: boom" in err
    # sys.exit() at import: was an exit with that code and not a word
    (folder / "e.py").write_text("import sys\nsys.exit(3)\n")
    path.write_text(f"camera: {{width: 64, height: 36}}\ncontroller: {{factory: "
                    f"'{folder / 'e.py'}:make'}}\n")
    err = _one_line_error(capsys, ["simulate", "--scenario", str(path), "--out",
                                   str(tmp_path / "sim"), "--no-meshcat"])
    assert f"importing it failed: SystemExit: it called sys.exit(3) at {folder / 'e.py'}:2" in err
    # code that fails when called: one line naming the factory and the line that raised
    (folder / "g.py").write_text("def make(config):\n    raise RuntimeError('bang')\n")
    path.write_text(f"camera: {{width: 64, height: 36}}\ncontroller: {{factory: "
                    f"'{folder / 'g.py'}:make'}}\n")
    err = _one_line_error(capsys, ["simulate", "--scenario", str(path), "--out",
                                   str(tmp_path / "sim"), "--no-meshcat"])
    assert f"'{folder / 'g.py'}:make': calling it failed: RuntimeError: bang at " \
           f"{folder / 'g.py'}:2" in err


def test_an_application_that_raises_when_built_is_one_line(tmp_path):
    from reachwatch.reach.application import load_application
    path = tmp_path / "app.py"
    path.write_text("from reachwatch.taxi.application import TaxiApplication\n\n\n"
                    "class App(TaxiApplication):\n    def __init__(self):\n"
                    "        raise RuntimeError('boom in app')\n")
    with pytest.raises(ValueError, match=rf"^application '{path}:App': calling it failed: "
                                         rf"RuntimeError: boom in app at {path}:6$"):
        load_application(f"{path}:App")


@pytest.mark.parametrize("parameters, message", [
    ("{steering: 0.0, gain: 2.0}", "controller.parameters.gain is not a parameter it takes"),
    ("{}", "controller.parameters lacks steering, which it needs"),
])
def test_a_factorys_bad_parameters_are_one_line_naming_them(tmp_path, capsys, parameters,
                                                            message):
    _, factory = _factory(tmp_path)
    err = _one_line_error(capsys, [
        "simulate", "--out", str(tmp_path / "sim"), "--no-meshcat",
        "--scenario-text", f"{{camera: {{width: 64, height: 36}}, duration: 0.1, controller: "
                           f"{{factory: '{factory}', parameters: {parameters}}}}}"])
    assert f"controller.factory '{factory}': {message} (TypeError: " in err


def test_a_path_the_system_refuses_is_one_line(tmp_path, capsys):
    """An OSError the cases above do not name (here a name too long; a full or
    read-only disk alike): one line with the path and the system's reason, exit 1."""
    out = tmp_path / ("a" * 300)
    assert cli.main(["graph", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("reachwatch graph: error: ") and "File name too long" in err
