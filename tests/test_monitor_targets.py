"""benchmarks/monitor_targets.py: a finished study's figures against the monitor's
targets, each verdict read the way the target states it."""

import importlib.util
import sys
from pathlib import Path

import numpy as np

from reachwatch.pipeline.monitor_guarded import ORACLE
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW
from reachwatch.training.monitor_eval import rate

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(_BENCHMARKS))        # monitor_targets imports monitor_bound
_SPEC = importlib.util.spec_from_file_location("monitor_targets",
                                               _BENCHMARKS / "monitor_targets.py")
targets = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(targets)
sys.path.remove(str(_BENCHMARKS))


def _variant(auroc, ece, misses, threshold, warning, safe):
    environments = [{"miss": rate(m, 10), "auroc_4s": a} for m, a in zip(misses, auroc)]
    group = {"environments": environments, "ece": ece,
             "pooled": {"miss": rate(sum(misses), 10 * len(misses))}}
    scores = [{"warning": np.asarray(warning, float), "safe_max": np.asarray(safe, float)}]
    return {"threshold": threshold, "held_out": group,
            "also_held_out": {"environments": [], "ece": float("nan"),
                              "pooled": {"miss": rate(0, 0)}},
            "scores": {"held_out": scores}}


def _guarded(prevented, failed, needless, safe):
    return {"prevented": prevented, "prevented_rate": rate(prevented, failed),
            "needless_rate": rate(needless, safe)}


def test_the_targets_read_as_stated():
    result = {
        "kept": "GRU", "within_s": 4.0, "lead_s": 1.67, "alpha": 0.1,
        "variants": {
            # misses 1 of 20 (5 %); warns 3 of 4 failing runs at 1 needless flag of 4
            "GRU": _variant([0.95, 0.90], 0.03, [1, 0], 0.5, [0.9, 0.8, 0.7, 0.1],
                            [0.6, 0.2, 0.1, 0.1]),
            # the detector warns 2 of 4 at that needless count (its threshold just over 0.2)
            DETECTOR_ROW: _variant([0.80, 0.88], 0.2, [2, 2], 0.5, [0.9, 0.3, 0.2, 0.1],
                                   [0.95, 0.2, 0.1, 0.1])},
        "prediction_error_auroc_4s": {"held_out": [0.9, 0.95], "also_held_out": []},
        "guarded": {"GRU": _guarded(9, 10, 5, 100), ORACLE: _guarded(10, 10, 0, 100),
                    DETECTOR_ROW: _guarded(6, 10, 20, 100)},
    }
    rows = {r[0]: r for r in targets.target_rows(result)}
    prevented = rows["prevented >= 0.85 of the oracle's"]
    assert "9 of the oracle's 10 (0.90)" in prevented[2] and prevented[3] == "met"
    assert rows["needless stops <= 10 % (upper bound <= 13 %)"][3] == "met"     # 5/100
    offline = rows["+10 points over the detector at the same needless flags (offline)"]
    assert "(+25.0 points)" in offline[2] and offline[3] == "met"
    miss = rows["miss rate <= 10 % (upper bound <= 13 %)"]
    assert miss[2].startswith("5.0 %") and miss[3] == "not met"       # its bound is 23.6 %
    assert rows["ECE <= 0.05"][3] == "met"
    worst = rows["worst AUROC (fails within 4 s) >= detector's + 5 points, above the "
                 "prediction error everywhere"]
    # 0.90 against the detector's 0.80 (+10 points), but below the prediction error in
    # the second environment (0.90 against 0.95)
    assert "above the prediction error in 1 of 2" in worst[2] and worst[3] == "not met"
    assert all(r[1] == "family" for r in rows.values())      # no night was judged


def test_the_bound_is_read_as_the_threshold_was_fixed_and_nothing_judged_is_no_verdict():
    """Fixed ``given_failures``, alpha bounds the mean over the environments where runs
    fail, not the mean with the others counting 0; a group without safe runs or warnable
    failures gets no verdict."""
    # two environments: one misses 3 of 10 warnable runs, one has none (counted 0)
    row = _variant([0.9, 0.9], 0.03, [3, 0], 0.5, [0.9], [0.1])
    row["held_out"]["environments"][1]["miss"] = rate(0, 0)
    result = {"kept": "GRU", "within_s": 4.0, "lead_s": 1.67, "alpha": 0.2,
              "variants": {"GRU": row},
              "prediction_error_auroc_4s": {"held_out": [0.5, 0.5], "also_held_out": []},
              "guarded": {"GRU": _guarded(0, 0, 0, 0), ORACLE: _guarded(0, 0, 0, 0)}}
    bound = "the conformal bound (alpha) on the mean miss rate"
    assert {r[0]: r for r in targets.target_rows(result)}[bound][3] == "met"   # 15 % <= 20 %
    row["given_failures"] = True
    rows = {r[0]: r for r in targets.target_rows(result)}
    assert rows[bound][3] == "not met"                                          # 30 % > 20 %
    assert rows["needless stops <= 10 % (upper bound <= 13 %)"][3] == "-"       # no safe run


def test_the_bound_over_redrawn_splits_reads_the_saved_calibration_and_held_out_scores():
    """Twelve environments, each with one warnable failing run: a monitor that warns
    every one of them at 0.9 misses none in any draw; one that scores half of them
    below every safe run needs a threshold under its safe runs, and some groups of
    new environments then miss more than alpha, the mean over draws staying within it.
    The row gives context, not a verdict."""
    def result(warnings):
        envs = [{"warning": np.array([w]), "safe_max": np.array([0.5])} for w in warnings]
        row = _variant([0.9], 0.03, [0], 0.5, [0.9], [0.1])
        row["scores"] = {"calibrate": envs[:9], "held_out": envs[9:]}
        return {"kept": "GRU", "alpha": 0.2, "kept_chosen_among": 0, "variants": {"GRU": row}}
    good = targets.redrawn_bound_row(result([0.9] * 12), "family")
    assert good[2].startswith("0.0 % (an environment without failures counting 0) over "
                              "1000 splits of the 12 environments (9 to calibrate, 3 new; "
                              "0 % of the groups") and good[3] == "-"
    assert "fixed before calibration" in good[2]
    rng = np.random.default_rng(0)
    poor = targets.redrawn_bound_row(result(rng.uniform(0, 1, 12)), "family")
    mean, _, share = poor[2].partition(" % (an environment without failures counting 0) "
                                       "over 1000 splits")
    above = int(share.split("3 new; ")[1].split(" %")[0])
    assert 0 < float(mean) <= 20.0 + 3.0 and above > 0      # alpha, and the draws' noise
    # thresholds fixed given failures: the bounded mean is over environments with one
    given = result([0.9] * 12)
    given["variants"]["GRU"]["given_failures"] = True
    assert targets.redrawn_bound_row(given, "family")[2].startswith("0.0 % (where runs fail)")
    # environments recorded with other run counts are not swapped between the groups
    unlike = result([0.9] * 12)
    unlike["failing_runs"] = {"calibrate": {f"c{i}": [1, 20] for i in range(9)},
                              "held_out": {f"h{i}": [1, 200] for i in range(3)}}
    assert targets.redrawn_bound_row(unlike, "family")[2] == (
        "not drawn: the calibration environments were recorded with 20 runs each and the "
        "held-out ones with 200, so a split could not swap them")
    unlike["failing_runs"]["calibrate"] = {f"c{i}": [0, 200] for i in range(9)}
    assert targets.redrawn_bound_row(unlike, "family")[2].startswith("0.0 % ")
    # a study that saved no calibration scores has no such row
    assert targets.redrawn_bound_row({"kept": "GRU", "variants": {"GRU": _variant(
        [0.9], 0.03, [0], 0.5, [0.9], [0.1])}}, "family") is None
