import os
import shutil

import cv2
import pytest

from reachwatch.diagrams import GraphvizMissing, Scenario, export_graph, make_world_diagram
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
    assert main(["graph", "--scenario", str(scenario), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "world.dot").exists()


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
