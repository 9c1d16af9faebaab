import os
import re
import shutil

import cv2
import pytest

from reachwatch.diagrams import (GraphvizMissing, Scenario, export_graph, load_scenario,
                                 make_guarded_diagram, make_world_diagram)
from reachwatch.pipeline.cli import main

TINY = "camera: {width: 64, height: 32}\n"


@pytest.fixture
def world():
    return make_world_diagram(Scenario())


def test_world_diagram_ports(world):
    names = [world.get_input_port(i).get_name() for i in range(world.num_input_ports())]
    assert names == ["steering_angle", "speed"]
    outs = [world.get_output_port(i).get_name() for i in range(world.num_output_ports())]
    assert outs == ["state", "color_image"]


def test_export_dot(world, tmp_path):
    paths = export_graph(world, tmp_path / "g", formats=("dot",))
    text = paths[0].read_text()
    assert paths[0].suffix == ".dot" and "taxi_plant" in text and "wing_camera" in text


def test_export_svg_png_with_graphviz(world, tmp_path):
    if shutil.which("dot") is None:
        if os.environ.get("CI"):
            pytest.fail("CI must install graphviz (see .ci/run)")
        pytest.skip("graphviz's dot is not installed")
    paths = export_graph(world, tmp_path / "g")
    svg = tmp_path / "g.svg"
    assert svg in paths and "<svg" in svg.read_text()
    assert cv2.imread(str(tmp_path / "g.png")) is not None


def test_missing_graphviz_is_explained(world, tmp_path, monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.warns(UserWarning, match="apt-get install graphviz"):
        paths = export_graph(world, tmp_path / "g")
    assert [p.suffix for p in paths] == [".dot"]
    with pytest.raises(GraphvizMissing):
        export_graph(world, tmp_path / "g", strict=True)


def test_cli_render_and_graph(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text(TINY + "environment: {runway: KEWR, hour: 21.0}\n")
    assert main(["render", "--scenario", str(scenario), "--out", str(tmp_path)]) == 0
    image = cv2.imread(str(tmp_path / "KEWR_21h_clear.png"))
    assert image.shape == (32, 64, 3)
    assert main(["graph", "--loop", "world", "--scenario", str(scenario), "--out",
                 str(tmp_path)]) == 0
    world = (tmp_path / "world.dot").read_text()
    assert "name=world_KEWR_21h_clear" in world and "name=controller" not in world


def _names(dot_text):
    """The names of the systems in a Graphviz text of a diagram."""
    return set(re.findall(r"name=(\w+)", dot_text))


def _graph(tmp_path, *argv):
    out = tmp_path / "graph"
    assert main(["graph", "--out", str(out), *argv]) == 0
    (written,) = out.glob("*.dot")
    text = written.read_text()
    written.unlink()
    return written.stem, _names(text)


def test_graph_exports_the_closed_loop_or_the_guarded_one_the_scenario_names(
        tmp_path, detector_path):
    """Without --loop: the closed loop, guarded when the scenario names a detector; the
    guarded graph is the diagram the pipeline builds and runs (make_guarded_diagram)."""
    scenario = tmp_path / "s.yaml"
    scenario.write_text(TINY)
    loop, names = _graph(tmp_path, "--scenario", str(scenario))
    assert loop == "closed_loop" and {"controller", "taxi_plant", "steering_hold"} <= names
    assert not names & {"anomaly_detector", "fallback_switch"}
    # the detector given by an overlay: guarded, with the monitor and the switch
    loop, names = _graph(tmp_path, "--scenario", str(scenario), "--set",
                         f"monitor.detector={detector_path}", "--set",
                         "monitor.steering=dead_reckoning")
    assert loop == "guarded_loop"
    assert {"controller", "anomaly_detector", "fallback_switch", "dead_reckoning"} <= names
    built = make_guarded_diagram(load_scenario(data=TINY + f"monitor: {{detector: "
                                               f"{detector_path}, steering: dead_reckoning}}\n"))
    assert names == _names(built.GetGraphvizString(max_depth=2))
    # --loop closed leaves the monitor out though the scenario names one
    loop, names = _graph(tmp_path, "--loop", "closed", "--scenario", str(scenario),
                         "--scenario-text", f"{{monitor: {{detector: {detector_path}}}}}")
    assert loop == "closed_loop" and "controller" in names and "fallback_switch" not in names


def test_graph_reads_a_run_file_in_one_of_its_environments(tmp_path, detector_path):
    run = tmp_path / "run.yaml"
    run.write_text("name: g\nscenario: {camera: {width: 64, height: 32}}\n"
                   "train: [{runway: KMWH, hour: 9.0, sky: clear}]\n"
                   "test: [{runway: KSFO, hour: 17.0, sky: clear}]\n")
    # --run, or a run file given as --scenario (as 'reachwatch run' takes it)
    for flag in ("--run", "--scenario"):
        loop, names = _graph(tmp_path, "--loop", "world", flag, str(run))
        assert loop == "world" and "world_KSFO_17h_clear" in names     # the first held out
    loop, names = _graph(tmp_path, "--loop", "world", "--run", str(run), "--env",
                         "KMWH_9h_clear")
    assert "world_KMWH_9h_clear" in names
    loop, names = _graph(tmp_path, "--scenario", str(run), "--run-text",
                         f"{{scenario: {{monitor: {{detector: {detector_path}}}}}}}")
    assert loop == "guarded_loop" and {"controller", "anomaly_detector",
                                       "fallback_switch"} <= names


#: A user application (a file beside a helper it imports) whose loop is the taxi's,
#: named by the helper.
APPLICATION = """
import helper
from reachwatch.taxi.application import TaxiApplication


class Named(TaxiApplication):
    def loop_diagram(self, scenario, *, guarded=False):
        diagram = super().loop_diagram(scenario, guarded=guarded)
        diagram.set_name(helper.NAME + ("_guarded" if guarded else ""))
        return diagram
"""


def test_graph_of_a_run_file_is_its_applications_loop(tmp_path, detector_path, capsys):
    folder = tmp_path / "app"
    folder.mkdir()
    (folder / "loop.py").write_text(APPLICATION)
    (folder / "helper.py").write_text("NAME = 'cart_on_a_track'\n")
    run = tmp_path / "run.yaml"
    run.write_text(f"application: '{folder / 'loop.py'}:Named'\n"
                   f"scenario: {{camera: {{width: 64, height: 32}}}}\n"
                   f"train: [{{runway: KMWH, hour: 9.0, sky: clear}}]\n"
                   f"test: [{{runway: KSFO, hour: 17.0, sky: clear}}]\n"
                   # a loop of its own has none of the taxi's showcase and noise runs
                   f"guard: {{candidates: 0, noise_starts: 0}}\n")
    loop, names = _graph(tmp_path, "--run", str(run))
    assert loop == "closed_loop" and {"cart_on_a_track", "controller"} <= names
    loop, names = _graph(tmp_path, "--run", str(run), "--set",
                         f"scenario.monitor.detector={detector_path}")
    assert loop == "guarded_loop" and {"cart_on_a_track_guarded", "fallback_switch"} <= names
    capsys.readouterr()
    assert main(["graph", "--loop", "world", "--run", str(run), "--out",
                 str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--loop world draws the taxi's open-loop world" in err


@pytest.mark.parametrize("argv, message", [
    (["--loop", "guarded"], "the built-in scenario: monitor.detector is not set; the "
                            "guarded loop needs a detector checkpoint"),
    (["--loop", "guarded", "--run", "RUN"], "run file RUN: scenario.monitor.detector is not "
                                            "set"),
    (["--run", "RUN", "--env", "KSFO_9h_clear"], "--env KSFO_9h_clear: the run file RUN has "
                                                 "no such environment; its environments: "
                                                 "KMWH_9h_clear, KSFO_17h_clear"),
    (["--env", "KMWH_9h_clear"], "--env picks one of a run file's environments"),
    (["--set", "monitor.detector=nowhere.pt"], "monitor.detector"),
])
def test_graph_errors_are_one_line_with_rc_2(tmp_path, capsys, argv, message):
    run = tmp_path / "run.yaml"
    run.write_text("train: [{runway: KMWH, hour: 9.0, sky: clear}]\n"
                   "test: [{runway: KSFO, hour: 17.0, sky: clear}]\n")
    argv = [str(run) if a == "RUN" else a for a in argv]
    assert main(["graph", "--out", str(tmp_path / "g"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message.replace("RUN", str(run)) in err, err
    assert not (tmp_path / "g").exists()


def test_cli_contact_sheet(tmp_path):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("camera: {width: 32, height: 16}\n")
    assert main(["render", "--contact-sheet", "--scenario", str(scenario),
                 "--out", str(tmp_path)]) == 0
    sheet = cv2.imread(str(tmp_path / "contact_sheet.png"))
    assert sheet.shape == (5 * 16, 6 * 32, 3)


def test_cli_bad_scenario_reports_field(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("camera: {heigth: 200}\n")
    assert main(["render", "--scenario", str(scenario), "--out", str(tmp_path)]) == 2
    assert "scenario.camera.heigth" in capsys.readouterr().err


def test_cli_help_on_every_subcommand(capsys):
    for command in ["render", "graph"]:
        with pytest.raises(SystemExit) as info:
            main([command, "--help"])
        assert info.value.code == 0
    assert "--out" in capsys.readouterr().out
