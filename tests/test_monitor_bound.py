"""The arithmetic of benchmarks/monitor_bound.py: redrawn splits of a study's family
judge each new environment at the threshold its calibration draw fixes."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "monitor_bound.py"
_SPEC = importlib.util.spec_from_file_location("monitor_bound", _PATH)
bound = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bound)


def test_a_monitor_that_separates_runs_misses_nothing_and_flags_no_safe_run():
    # warnable failing runs score 0.9, safe runs at most 0.1: any draw's threshold lies
    # between (the largest that bounds alpha is 0.9 itself)
    envs = [(np.full(1 + i % 3, 0.9), np.full(4, 0.1)) for i in range(12)]
    figures = bound.draw_figures(envs, 9, 0.1, draws=50)
    assert len(figures) == 2, figures                   # every draw, and given failures
    for mode, f in figures.items():
        assert f["E[miss]"] == f["E[miss | fails]"] == f["pooled"] == 0.0, mode
        assert f["needless"] == 0.0 and f["refused"] == 0.0 and f["over alpha"] == 0.0, mode


def test_failure_free_environments_dilute_the_default_bound_only():
    """Half the environments never fail. The miss rates where runs fail are the same in
    both modes' draws, but the default's E[miss] counts the others as 0."""
    rng = np.random.default_rng(0)
    envs = [(rng.uniform(0, 1, 3) if i % 2 else np.zeros(0), rng.uniform(0, 0.5, 3))
            for i in range(40)]
    f = bound.draw_figures(envs, 20, 0.2, draws=200)["every"]
    assert f["E[miss]"] == pytest.approx(f["E[miss | fails]"] / 2, rel=0.15)
    given = bound.draw_figures(envs, 20, 0.2, draws=200)["given failures"]
    assert given["E[miss | fails]"] < f["E[miss | fails]"]     # a lower threshold
    assert given["needless"] > f["needless"]                    # bought with flags


def test_too_few_calibration_environments_are_refused_and_counted():
    envs = [(np.array([0.5]), np.array([0.1]))] * 6
    f = bound.draw_figures(envs, 4, 0.1, draws=5)
    assert f["every"]["refused"] == 1.0 and np.isnan(f["every"]["pooled"])
    with pytest.raises(ValueError, match="more environments than"):
        bound.draw_figures(envs, 6, 0.1, draws=1)


def test_choosing_among_candidates_on_the_calibration_draw_misses_more_than_one_fixed():
    """Ten candidates alike in distribution, each environment's scores drawn for each
    apart: the one the calibration draw flattered (its failing runs scored high there,
    so its threshold is high and it flags fewest safe runs) is chosen, and on new
    environments it is no better than the others, so it misses more than a candidate
    fixed in advance; the fixed one keeps the bound."""
    rng = np.random.default_rng(1)
    candidates = {f"c{c}": [(rng.uniform(0.2, 1.0, 3), rng.uniform(0.0, 0.8, 6))
                            for _ in range(40)] for c in range(10)}
    f = bound.choice_figures(candidates, 20, 0.2, draws=300)
    assert sum(f["times chosen"].values()) == 300 and f["fixed"]["refused"] == 0.0
    assert f["fixed"]["E[miss]"] <= 0.2
    assert f["chosen"]["E[miss]"] > 1.2 * f["fixed"]["E[miss]"]
    assert f["chosen"]["needless"] < f["fixed"]["needless"]      # what it was chosen for
    # one group of new environments reads above alpha more often for the chosen one
    assert f["chosen"]["over alpha"] > f["fixed"]["over alpha"]
    # one candidate: the choice is the fixed one, draw by draw
    one = bound.choice_figures({"c0": candidates["c0"]}, 20, 0.2, draws=50)
    assert one["chosen"] == one["fixed"]
    assert one["fixed"]["E[miss]"] == bound.draw_figures(
        candidates["c0"], 20, 0.2, draws=50)["every"]["E[miss]"]


def test_a_smaller_alpha_misses_less_and_flags_more_on_the_same_draws():
    """``--alpha``: the same draws at a smaller alpha fix a lower threshold in each, so
    no figure of misses rises and needless flags do not fall; ``pooled p90`` is the 90th
    percentile over draws of the pooled miss rate, at least its mean here."""
    rng = np.random.default_rng(2)
    envs = [(rng.uniform(0.2, 1.0, 4), rng.uniform(0.0, 0.8, 8)) for _ in range(40)]
    loose = bound.draw_figures(envs, 20, 0.2, draws=200, seed=3)["every"]
    tight = bound.draw_figures(envs, 20, 0.05, draws=200, seed=3)["every"]
    for figure in ("E[miss]", "pooled", "pooled p90", "p90 | fails"):
        assert tight[figure] <= loose[figure], figure
    assert tight["E[miss]"] < loose["E[miss]"] and tight["needless"] > loose["needless"]
    assert loose["pooled"] < loose["pooled p90"] <= 1


def test_the_alpha_option_reaches_every_draw(tmp_path, monkeypatch, capsys):
    """The command line's ``--alpha`` replaces the study's own in the table (and says so)."""
    folder = tmp_path / "study"
    folder.mkdir()
    rng = np.random.default_rng(4)
    scores = {split: [{"warning": rng.uniform(0.2, 1.0, 3).tolist(),
                       "safe_max": rng.uniform(0.0, 0.8, 6).tolist()} for i in range(n)]
              for split, n in (("calibrate", 10), ("held_out", 10))}
    monkeypatch.setattr(bound, "read_study_result", lambda path: {
        "alpha": 0.2, "kept": "v", "variants": {"v": {"scores": scores}}})
    rows = {}
    for alpha in (None, "0.2", "0.05"):
        monkeypatch.setattr("sys.argv", ["monitor_bound.py", str(folder), "--draws", "50"]
                            + (["--alpha", alpha] if alpha else []))
        bound.main()
        out = capsys.readouterr().out
        rows[alpha] = [line for line in out.splitlines() if line.startswith("| study | v")]
        assert ("alpha as each study's" in out) == (alpha is None), out
    assert rows[None] == rows["0.2"] != rows["0.05"]
    monkeypatch.setattr("sys.argv", ["monitor_bound.py", str(folder), "--alpha", "1.5"])
    with pytest.raises(SystemExit) as stop:
        bound.main()
    assert stop.value.code == 2 and "alpha" in capsys.readouterr().err
