"""benchmarks/monitor_mean.py: the mean of finished studies' risks, judged as one
monitor. Two fake studies of the same runs: a monitor averaged with itself is itself,
two that disagree average, and studies of other runs are refused."""

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(_BENCHMARKS))         # monitor_mean imports monitor_bound
_SPEC = importlib.util.spec_from_file_location("monitor_mean", _BENCHMARKS / "monitor_mean.py")
mean = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(mean)
sys.path.remove(str(_BENCHMARKS))


def _study(folder: Path, risk_of, *, ticks=(5, 3, 5, 5)):
    """A finished study with one variant ``v``: two environments per split, two runs each
    (the second of each environment fails at its third tick), ``risk_of(split, run)`` its
    risks."""
    folder.mkdir()
    (folder / "monitor.json").write_text(json.dumps(
        {"alpha": 0.5, "lead_s": 0.1, "within_s": 0.1, "variants": {"v": {}}}))
    arrays = {}
    for split in mean.SPLITS:
        arrays[f"{split}/ticks"] = np.array(ticks)
        failure = np.array([np.nan, 0.1, np.nan, np.nan])
        arrays[f"{split}/failure_time"] = failure
        arrays[f"{split}/watched_failure_time"] = failure
        arrays[f"{split}/environment"] = np.array([0, 0, 1, 1])
        arrays[f"{split}/names"] = np.array(["a", "b"])
        arrays[f"v/{split}/risk"] = np.concatenate(
            [risk_of(split, i) * np.ones(n) for i, n in enumerate(ticks)]).astype(np.float32)
    np.savez(folder / "risks.npz", **arrays)
    return folder


def test_the_mean_of_a_monitor_and_itself_is_that_monitor_and_two_average_their_risks(tmp_path):
    one = _study(tmp_path / "one", lambda split, i: 0.2 + 0.1 * i)
    same = _study(tmp_path / "same", lambda split, i: 0.2 + 0.1 * i)
    other = _study(tmp_path / "other", lambda split, i: 0.5)
    saved = {f: np.load(f / "risks.npz") for f in (one, same, other)}
    chosen = mean.monitors([f"{one}:v", str(same)])
    assert [label for label, _, _ in chosen] == ["one: v", "same: v"]
    alone = mean.mean_groups(chosen[:1], saved)
    both = mean.mean_groups(chosen, saved)
    for split in mean.SPLITS:
        for a, b in zip(alone[split], both[split]):
            for ra, rb in zip(a[0], b[0]):
                np.testing.assert_allclose(ra, rb, rtol=1e-6)
    mixed = mean.mean_groups([chosen[0], (None, other, "v")], saved)
    # the risks' mean (0.35), not their logits' (0.333)
    np.testing.assert_allclose(mixed["held_out"][0][0][0], 0.35, atol=1e-6)    # 0.2 and 0.5


def test_a_variant_the_study_lacks_is_named(tmp_path):
    one = _study(tmp_path / "one", lambda split, i: 0.5)
    with pytest.raises(SystemExit, match="has no variant 'w'"):
        mean.monitors([f"{one}:w"])


def test_studies_of_other_runs_are_refused(tmp_path):
    one = _study(tmp_path / "one", lambda split, i: 0.5)
    same = _study(tmp_path / "same", lambda split, i: 0.7)
    longer = _study(tmp_path / "longer", lambda split, i: 0.5, ticks=(5, 3, 5, 6))
    mean.check_same_runs({f: np.load(f / "risks.npz") for f in (one, same)}, mean.SPLITS)
    with pytest.raises(ValueError, match="did not record the same runs .calibrate/ticks differ"):
        mean.check_same_runs({f: np.load(f / "risks.npz") for f in (one, longer)}, mean.SPLITS)
    # runs that did not fail last the study's duration: 5 ticks of 0.1 s is 0.4 s
    mean.check_run_length(np.load(one / "risks.npz"), period=0.1, duration=0.4)
    # a duration that is no whole number of periods: ticks at 0, ..., 4 x 0.088 s
    mean.check_run_length(np.load(one / "risks.npz"), period=0.088, duration=0.4)
    with pytest.raises(ValueError, match=r"runs that did not fail have \[5\] ticks, not 9: "
                                         r"give the study's period and duration"):
        mean.check_run_length(np.load(one / "risks.npz"), period=0.05, duration=0.4)


def test_the_alpha_option_replaces_the_studies_own(tmp_path, monkeypatch, capsys):
    one = _study(tmp_path / "one", lambda split, i: 0.2 + 0.1 * i)
    heads = {}
    for alpha in (None, "0.25"):
        monkeypatch.setattr("sys.argv", ["monitor_mean.py", f"{one}:v", "--draws", "20",
                                         "--period", "0.1", "--duration", "0.4"]
                            + (["--alpha", alpha] if alpha else []))
        mean.main()
        heads[alpha] = capsys.readouterr().out.splitlines()[0]
    assert heads[None].startswith("20 draws; alpha 0.5,")
    assert heads["0.25"].startswith("20 draws; alpha 0.25,")
    monkeypatch.setattr("sys.argv", ["monitor_mean.py", f"{one}:v", "--alpha", "0"])
    with pytest.raises(SystemExit) as stop:
        mean.main()
    assert stop.value.code == 2 and "alpha" in capsys.readouterr().err


def test_the_auroc_columns_skip_environments_with_fewer_failing_runs(tmp_path, monkeypatch,
                                                                     capsys):
    """One held-out environment has one failing run, the other none: the worst and median
    AUROC are that environment's, and with ``--min-failing 2`` there is none to read."""
    one = _study(tmp_path / "one", lambda split, i: 0.2 + 0.1 * i)
    rows = {}
    for least in ("1", "2"):
        monkeypatch.setattr("sys.argv", ["monitor_mean.py", f"{one}:v", "--draws", "20",
                                         "--period", "0.1", "--duration", "0.4",
                                         "--min-failing", least])
        mean.main()
        out = capsys.readouterr().out
        rows[least] = [line for line in out.splitlines() if line.startswith("| one: v")][0]
        assert ("2+ failing runs" in out) == (least == "2")
    worst, median = rows["1"].rstrip(" |").rsplit("|", 1)[1].strip().split(", ")
    assert worst == median and float(worst) > 0.5
    assert rows["2"].endswith("| nan, nan |")
