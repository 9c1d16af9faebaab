"""The run file of ``reachwatch run``: errors that name the field, file errors, the
shipped run files, the CLI's exit code for a bad file, and a run refused before any
sweep when the check is bound to refuse its labels."""

import re
from pathlib import Path

import pytest

from reachwatch.diagrams import ScenarioError
from reachwatch.pipeline.fidelity_stages import BoxExitError, check_downtrack_room
from reachwatch.pipeline.run import run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from tiny_run import TINY


@pytest.mark.parametrize("edit, message", [
    (("epochs: 1", "epoch: 1"), "run.detector.epoch: unknown field"),
    (("horizon: 4.0", "horizon: soon"), "run.horizon: expected float"),
    (("train: [{runway: KMWH, hour: 9.0, sky: clear}]", "train: []"), "train: list at least one"),
    (("runway: KSFO", "runway: XXXX"), "unknown runway 'XXXX'"),
    (("grid: [5, 3, 5]", "grid: [5, 3]"), "grid must be 3 sizes"),
    (("horizon: 4.0", "horizon: 4.0\nperiods_per_step: 0"), "periods_per_step must be a whole number in [1, 10000], got 0"),
    (("fidelity: {starts: 3", "fidelity: {starts: -1"), "fidelity.starts must be a whole number in [0, 1000000], got -1"),
    (("horizon: 4.0", "horizon: 4.0\nrefine: {levels: -1}"), "refine.levels must be a whole number in [0, 5], got -1"),
    (("horizon: 4.0", "horizon: 4.0\nsolved_theta_deg: 20"), "solved_theta_deg must be a finite number in [28, 180] deg"),
    (("horizon: 4.0", "horizon: 4.0\nsolved_py_max: 200"), "solved_py_max must be a finite number in [250, 10000] m"),
    (("horizon: 4.0", "horizon: 4.0\nrefine: {levels: 1, band: -2}"), "refine.band must be a finite"),
    (("horizon: 4.0", "horizon: 4.0\nmap_selection: {starts: -3}"),
     "map_selection.starts must be a whole number in [0, 1000000], got -3"),
    (("horizon: 4.0", "horizon: 4.0\nmap_selection: {starts: 5, robust_spreads_deg: [10, -2]}"),
     "map_selection.robust_spreads_deg[1] must be a finite number in [0, 360] deg"),
    (("horizon: 4.0", "horizon: 4.0\nmap_selection: {starts: 5, false_safe_weight: 0.5}"),
     "map_selection.false_safe_weight must be a finite number in [1, 1000]"),
    (("horizon: 4.0", "horizon: 4.0\nrobust: {min_spread_deg: -1}"),
     "robust.min_spread_deg must be a finite number >= 0 deg"),
    (("horizon: 4.0", "horizon: 4.0\nrobust: {min_spread_deg: 5, neighbourhood: 4}"),
     "robust.neighbourhood must be an odd whole number of nodes"),
    (("{samples: 40, height: 24", "{labels: {source: oracle}, samples: 40, height: 24"),
     "dataset.labels.source must be one of"),
    (("{samples: 40, height: 24", "{samples: 40, height: 32"), "must equal the detector input"),
    (("horizon: 4.0", "horizon: 4.0\nheld_out_labels: {source: oracle}"),
     "held_out_labels.source must be one of"),
    (("guard: {candidates: 2", "guard: {strategies: [stop], candidates: 2"),
     "guard.strategies[0]: fallback 'stop'"),
    (("guard: {candidates: 2", "guard: {strategies: [slow_down+gps], candidates: 2"),
     "guard.strategies[0]: fallback 'slow_down+gps'"),
    (("check_starts: 2", "check_starts: -2"), "guard.check_starts must be a whole number in [0, 1000000], got -2"),
    (("noise_starts: 0", "noise_starts: -3"), "guard.noise_starts must be a whole number in [0, 1000000], got -3"),
    (("noise_starts: 0}", "noise_starts: 0, flag_budget: 1.5}"),
     "guard.flag_budget must be a finite number in (0, 1)"),
    (("noise_starts: 0}", "noise_starts: 0, flag_budget: 0.1, strategies: []}"),
     "guard.flag_budget: the budget is set on the first of guard.strategies, and there are none"),
    (("noise_starts: 0}", "noise_starts: 0, flag_budget: 0.1, flag_budget_starts: 0}"),
     "guard.flag_budget_starts must be a whole number in [1, 1000000]"),
    (("batch_size: 8", "batch_size: 8\n  threshold_folds: 2"),
     "detector.threshold_folds 2: there are only 1 training environments to leave out"),
])
def test_run_spec_errors_name_the_field(edit, message):
    with pytest.raises(ScenarioError, match=re.escape(message)):
        load_run_spec(data=TINY.replace(*edit))


def test_run_spec_file_errors(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_run_spec(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("train: [")
    with pytest.raises(ScenarioError, match=r"bad.yaml: not valid YAML: .* at line 2, column 1$"):
        load_run_spec(tmp_path / "bad.yaml")
    # a scenario file given where a run file goes says so
    (tmp_path / "scenario.yaml").write_text("environment: {runway: KSFO}\n")
    with pytest.raises(ScenarioError, match=r"scenario.yaml: this looks like a scenario file .* "
                                            r"which a run file holds under scenario:; "
                                            r"run.environment: unknown field"):
        load_run_spec(tmp_path / "scenario.yaml")
    # every error names the file, also those of the schema's field and type checks
    for edit in [("grid: [5, 3, 5]", "grids: [5, 3, 5]"), ("grid: [5, 3, 5]", "grid: [5, 3.5, 5]"),
                 ("horizon: 4.0", "horizon: -4.0")]:
        (tmp_path / "edited.yaml").write_text(TINY.replace(*edit))
        with pytest.raises(ScenarioError, match=re.escape(f"{tmp_path / 'edited.yaml'}: ")):
            load_run_spec(tmp_path / "edited.yaml")


def test_shipped_run_files_load():
    root = Path(__file__).resolve().parents[1] / "scenarios"
    demo, paper = load_run_spec(root / "demo.yaml"), load_run_spec(root / "paper.yaml")
    assert len(paper.train) == 12 and len(paper.test) == 18 and paper.grid == [101] * 3
    assert paper.dataset.samples == 20000 and paper.detector.detector.arch == "efficientnet_b0"
    assert len(demo.train) < len(paper.train)


def test_run_command_reports_a_bad_run_file_and_exits_2(tmp_path, capsys):
    from reachwatch.pipeline.cli import main
    bad = tmp_path / "bad.yaml"
    bad.write_text(TINY.replace("grid: [5, 3, 5]", "grids: [5, 3, 5]"))
    assert main(["run", "--scenario", str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "run.grids: unknown field of RunSpec" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()          # nothing written for a bad file


def test_a_run_without_room_downtrack_is_refused_before_any_sweep(tmp_path):
    """With BRT labels and the real-loop check's default 5 %, a solved box ending at the
    paper's py = 250 m is bound to be refused (starts in its last 5 m/s x 4 s x cos 28
    deg = 17.7 m of 150 run past it): said before anything is swept, not after."""
    text = TINY.replace("fidelity: {starts: 3, max_box_exits: 1.0}", "fidelity: {starts: 3}")
    with pytest.raises(BoxExitError, match=r"solved_py_max 250 m leaves no room downtrack: "
                                           r"about 12 % .* Set solved_py_max: 270"):
        run_pipeline(load_run_spec(data=text), tmp_path / "run", progress=False,
                     log=lambda m: None)
    assert not (tmp_path / "run").exists()                  # nothing swept or written
    run_pipeline(load_run_spec(data=text), tmp_path / "run", until="solve", progress=False,
                 log=lambda m: None)                         # stops before the check: allowed
    for old, new in (("horizon: 4.0", "horizon: 4.0\nsolved_py_max: 270.0"),
                     ("fidelity: {starts: 3}", "fidelity: {starts: 0}"),
                     ("fidelity: {starts: 3}", "fidelity: {starts: 3, max_box_exits: 0.15}"),
                     ("chunk_size: 16}", "chunk_size: 16, labels: {source: hybrid}}")):
        assert old in text
        check_downtrack_room(load_run_spec(data=text.replace(old, new)))
    with pytest.raises(BoxExitError, match="about 5 %"):
        check_downtrack_room(load_run_spec(data=text + "solved_py_max: 260.0\n"))
