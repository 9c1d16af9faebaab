"""The monitor study of a run file (``monitor: {kind: history}``): the study runs end
to end at a tiny size on the real rendered loop (record, train every variant, calibrate, conformal threshold, judge
offline and in the guarded real loop), its kept monitor a checkpoint the guarded loop
takes, and its tables render."""

import json
from dataclasses import replace as dc_replace

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario, save_checkpoint
from reachwatch.diagrams.checkpoints import load_history_monitor
from reachwatch.pipeline.monitor_sections import markdown_tables
from reachwatch.pipeline.monitor_guarded import ORACLE
from reachwatch.pipeline.monitor_study import (DETECTOR_ROW, checkpoint_file,
                                               clear_previous_result, run_monitor_study,
                                               starts_seed, study_outputs)
from reachwatch.pipeline.spec import MonitorVariant, load_run_spec
from reachwatch.training.conformal import conformal_threshold
from tiny_run import MONITOR_STUDY, TINY
from reachwatch.taxi.application import TAXI_APPLICATION


def test_threshold_tradeoff_leaves_a_blank_row_only_where_no_threshold_exists():
    """Too few calibration environments for an alpha: a row without a threshold; a bad
    alpha is an error, not a blank row."""
    from reachwatch.pipeline.monitor_sections import threshold_tradeoff
    row = {"scores": {"held_out": [{"warning": [0.9, 0.3], "safe_max": [0.1, 0.5]}],
                      "calibrate": [{"warning": [0.7], "safe_max": [0.4]},
                                    {"warning": [0.6, 0.8], "safe_max": [0.2]}]}}
    blank, kept = threshold_tradeoff(row, (0.1, 0.5))
    assert blank == [0.1, None, 0, 0, 0, 0]             # 2 environments bound no more than 1/3
    # alpha 0.5 over 2 environments: a mean miss of 0.25 at most, so 0.7 (0.6 missed,
    # (0.5 + 1) / 3 = 0.5); held out it misses 0.3 of 2 and flags neither safe run
    assert kept == [0.5, pytest.approx(0.7), 1, 2, 0, 2]
    with pytest.raises(ValueError, match=r"alpha must be in \(0, 1\), got 1.5"):
        threshold_tradeoff(row, (1.5,))
    # bounded as the variant's threshold was: given failures, the environments without
    # one are left out of the bound
    row["scores"]["calibrate"] += [{"warning": [], "safe_max": [0.3]}] * 2
    scores = [np.asarray(e["warning"]) for e in row["scores"]["calibrate"]]
    for given in (False, True):
        row["given_failures"] = given
        assert threshold_tradeoff(row, (0.45,))[0][1] == conformal_threshold(
            scores, 0.45, given_failures=given).threshold
    assert threshold_tradeoff(row, (0.45,))[0][1] != threshold_tradeoff(
        {**row, "given_failures": False}, (0.45,))[0][1]


def test_run_ranking_pools_environments_and_sets_the_least_needless_threshold():
    from reachwatch.pipeline.monitor_sections import run_ranking
    row = {"scores": {"held_out": [{"warning": [0.9, 0.3], "safe_max": [0.1, 0.5]},
                                   {"warning": [0.8], "safe_max": [0.85, 0.2]}],
                      "calibrate": [{"warning": [], "safe_max": [0.4]}]}}
    held = run_ranking(row, "held_out")
    # pairs a failing run outranks: 0.9 all 4, 0.8 three, 0.3 two, of 12
    assert held["auroc"] == pytest.approx(9 / 12)
    # 10 % of 3 warnable runs: none may be missed, so the threshold is the lowest
    # warning score (0.3), and it flags the safe runs at 0.5 and 0.85
    assert (held["needless"]["count"], held["needless"]["of"]) == (2, 4)
    # a third of them may be missed: the threshold rises to 0.8, flagging only 0.85
    assert run_ranking(row, "held_out", miss=1 / 3)["needless"]["count"] == 1
    cal = run_ranking(row, "calibrate")                 # no failing run: nothing to rank
    assert np.isnan(cal["auroc"]) and cal["needless"] is None
    # two of three warnable runs cannot be flagged before the lead (-inf under a k-of-n
    # rule): no threshold misses only 10 %; before, -inf flagged every safe run
    row["scores"]["held_out"][0]["warning"] = [0.9, -np.inf]
    row["scores"]["held_out"][1]["warning"] = [-np.inf]
    assert run_ranking(row, "held_out")["needless"] is None


def test_a_variant_meets_the_detector_at_its_own_needless_flags():
    """The detector's threshold is the lowest flagging no more runs that did not fail
    than the variant does at its threshold; warned runs are then compared."""
    from reachwatch.pipeline.monitor_sections import same_needless
    variant = {"threshold": 0.5, "scores": {"held_out": [
        {"warning": [0.9, 0.6, 0.2], "safe_max": [0.1, 0.55]},
        {"warning": [0.7], "safe_max": [0.3, 0.2]}]}}
    detector = {"threshold": 0.4, "kind": "detector", "scores": {"held_out": [
        {"warning": [0.8, 0.35, 0.3], "safe_max": [0.6, 0.5]},
        {"warning": [0.2], "safe_max": [0.45, 0.1]}]}}
    result = {"variants": {"GRU": variant, DETECTOR_ROW: detector}}
    [(name, warned, needless, detector_warned, points)] = same_needless(result)
    # the variant warns 3 of 4 with 1 of 4 safe runs flagged; the detector flags only
    # one safe run from 0.5 + (up to 0.6), where it warns only the 0.8 run
    assert name == "GRU" and (warned["count"], needless["count"]) == (3, 1)
    assert (detector_warned["count"], detector_warned["of"]) == (1, 4)
    assert points == pytest.approx(50.0)
    assert same_needless({"variants": {"GRU": variant}}) == []


class _Run:
    """What the report's monitor section reads of a run: its study in ``folder/out``."""

    def __init__(self, folder):
        self.folder = folder
        self.outputs = {"monitor": {"result": "out/monitor.json"}}

    def path(self, relative):
        return self.folder / relative


def _monitor_report(folder):
    """``(html, markdown)`` of the report's monitor section for the study in
    ``folder/out``."""
    from reachwatch.pipeline.monitor_sections import monitor_section
    from reachwatch.pipeline.report import Page
    page = Page("run")
    monitor_section(page, _Run(folder))
    return page.done()


def test_the_study_runs_end_to_end_on_the_rendered_loop(tmp_path, detector_path):
    """The study with a single-image detector judged beside its variants (the run's,
    here an untrained one)."""
    spec = load_run_spec(data=TINY + MONITOR_STUDY.replace(
        "  guarded_runs: 2", "  guarded_runs: 2\n  also_held_out: [{runway: KSFO, hour: 21.0, "
                             "sky: overcast}]")).monitor
    scenario = load_scenario(data="")
    result = run_monitor_study(spec, scenario, tmp_path / "out", cache_dir=tmp_path / "cache",
                               progress=False, log=lambda m: None, detector=detector_path)
    # strict JSON (no NaN or -Infinity), its nulls read back as NaN
    text = (tmp_path / "out" / "monitor.json").read_text()
    strict = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in monitor.json"))
    assert strict["kept"] == result["kept"]
    # the stage's record names every file the study wrote (and checks them all)
    outputs = study_outputs(result, folder="out")
    assert sorted([outputs["result"], *outputs["files"]]) == sorted(
        f"out/{p.name}" for p in (tmp_path / "out").iterdir())
    from reachwatch.pipeline.monitor_sections import read_study_result
    back = read_study_result(tmp_path / "out" / "monitor.json")
    assert json.dumps(back, sort_keys=True) == json.dumps(
        json.loads(json.dumps(result, default=float)), sort_keys=True)
    assert set(result["variants"]) == {"one frame", "GRU 3 + signals", DETECTOR_ROW}
    # the controller's prediction error, one AUROC per judged environment
    assert len(result["prediction_error_auroc_4s"]["held_out"]) == len(
        result["variants"]["one frame"]["held_out"]["environments"])
    assert result["variants"][DETECTOR_ROW]["kind"] == "detector"
    # kept: the first variant, fixed before calibration (not the one the calibration
    # environments flattered)
    assert (result["kept"], result["kept_chosen_among"]) == ("one frame", 0)
    assert result["lead_s"] == pytest.approx(5.0 / 3.0)
    # the recordings' failure times over the longer watch (duration + within): the
    # recorded one where a run failed within it, else one within the 4 s after, or none
    with np.load(tmp_path / "out" / "risks.npz") as saved:
        failure, watched = saved["held_out/failure_time"], saved["held_out/watched_failure_time"]
    ended = np.isfinite(failure)
    np.testing.assert_array_equal(watched[ended], failure[ended])
    later = watched[~ended & np.isfinite(watched)]
    assert np.all((later > spec.duration) & (later <= spec.duration + spec.within + 1e-9))
    after = len(later)
    from reachwatch.pipeline.monitor_sections import threshold_tradeoff
    for name, row in result["variants"].items():
        assert 0 <= row["threshold"] <= 1
        # the recorded scores give back the chosen threshold and its held-out figures
        alpha, tau, missed, warnable, needless, safe = threshold_tradeoff(row, (0.5,))[0]
        pooled = row["held_out"]["pooled"]
        assert tau == row["threshold"] and (missed, warnable) == (
            pooled["miss"]["count"], pooled["miss"]["of"])
        assert (needless, safe) == (pooled["needless"]["count"], pooled["needless"]["of"])
        # every held-out run is safe, warnable and failing, or failing just after
        assert pooled["needless"]["of"] + pooled["miss"]["of"] + after == 6
    # the kept monitor (and the single-frame one) are checkpoints with their calibration,
    # each file named after its variant
    for name, file in result["checkpoints"].items():
        model, config, meta = load_history_monitor(tmp_path / "out" / file)
        assert meta["variant"] == name and meta["threshold"] == result["variants"][name]["threshold"]
        assert file == checkpoint_file(name)
        assert meta["image_size"] == [scenario.camera.height, scenario.camera.width]  # enforced online
    # the guarded real loop ran from the held-out starts, for each saved monitor and the
    # oracle, which stops no safe run and covers a safe run's whole distance
    assert set(result["guarded"]) == set(result["checkpoints"]) | {ORACLE, DETECTOR_ROW}
    oracle = result["guarded"][ORACLE]
    assert oracle["runs"] == 2 and oracle["needless_stops"] == 0
    if oracle["failed_alone"] == 0:
        assert oracle["distance_guarded_m"] == oracle["distance_alone_m"]
    # and from the starts of the environment outside the family, the same rows
    night = result["guarded_also_held_out"]
    assert set(night) == set(result["guarded"])
    assert [e["environment"] for e in night[ORACLE]["environments"]] == ["KSFO_21h_overcast"]
    for counts in result["guarded"].values():
        assert counts["runs"] == 2 and counts["failed_guarded"] <= counts["runs"]
    # each monitor's row says how many of its runs were rendered: those it may flag and
    # the first it cannot, in each environment (here one)
    from reachwatch.pipeline.monitor_sections import rendered_text
    for name, counts in result["guarded"].items():
        assert (name == ORACLE) == ("rendered" not in counts)
        assert 1 <= counts.get("rendered", 1) <= counts["runs"]
    assert f"{result['kept']} {result['guarded'][result['kept']]['rendered']} of 2" in (
        rendered_text(result["guarded"]))
    assert rendered_text({ORACLE: oracle}) == ""
    # every variant's risk at every tick is kept, run by run, for other flag rules
    with np.load(tmp_path / "out" / "risks.npz") as saved:
        ticks = saved["held_out/ticks"]
        assert len(ticks) == 6 and len(saved["held_out/failure_time"]) == 6
        for name in result["variants"]:
            assert len(saved[f"{name}/held_out/risk"]) == ticks.sum()
            assert len(saved[f"{name}/calibrate/risk"]) == saved["calibrate/ticks"].sum()
        # the detector's row reads the detector's own score along the same runs
        import dataclasses as dc
        from reachwatch.diagrams import MonitorConfig
        from reachwatch.reach.application import load_application
        taxi, env = load_application(TAXI_APPLICATION), spec.environments()["held_out"][0]
        here = dc.replace(scenario, environment=env,
                          monitor=MonitorConfig(detector=str(detector_path)))
        box = taxi.grid(here, (3, 3, 3))
        first = taxi.starts(here, (box.lo, box.hi), spec.judged_runs,
                            starts_seed(spec, spec.train + spec.calibrate))[:1]
        online = taxi.score_runs(here, first, duration=spec.duration,
                                 cache_dir=tmp_path / "scores", progress=False)
        np.testing.assert_allclose(saved[f"{DETECTOR_ROW}/held_out/risk"][:ticks[0]],
                                   online["score"][0, :ticks[0]], rtol=1e-6)
    # a rerun renders nothing new, trains nothing new (its encoder and every head read
    # back) and gives the same figures (cached by content, seeded)
    logged = []
    again = run_monitor_study(spec, scenario, tmp_path / "again", cache_dir=tmp_path / "cache",
                              progress=False, log=logged.append, detector=detector_path)
    read_back = [m for m in logged if "the trained model read back" in m]
    assert len(read_back) == 1 + len(spec.variants), read_back
    for part in ("variants", "guarded", "oracle"):           # NaN where a group is empty
        assert json.dumps(again[part], sort_keys=True) == json.dumps(result[part], sort_keys=True)
    # the heads' training changed: the encoder is read back, only the heads train again
    logged.clear()
    run_monitor_study(dc.replace(spec, head_epochs=spec.head_epochs + 1), scenario,
                      tmp_path / "heads", cache_dir=tmp_path / "cache", progress=False,
                      log=logged.append, detector=detector_path)
    read_back = [m for m in logged if "the trained model read back" in m]
    assert len(read_back) == 1 and "encoder" in read_back[0], read_back
    # keep: choose, with k-of-n flag rules: each variant keeps the rule with the fewest
    # needless flags on the calibration environments (never more than 1-of-1's), its
    # guarded runs use it, and the kept variant is the one with the fewest of all
    ruled = run_monitor_study(dc.replace(spec, keep="choose", flag_rules=[[1, 1], [3, 3]]),
                              scenario,
                              tmp_path / "rules", cache_dir=tmp_path / "cache", progress=False,
                              log=lambda m: None, detector=detector_path)
    for name, row in ruled["variants"].items():
        assert row["flag_rule"] in ([1, 1], [3, 3]) and result["variants"][name]["flag_rule"] == [
            1, 1]
        assert row["calibration_needless"] <= result["variants"][name]["calibration_needless"]
        if row["flag_rule"] == [1, 1]:
            assert row["threshold"] == result["variants"][name]["threshold"]
    candidates = {n: r["calibration_needless"] for n, r in ruled["variants"].items()
                  if n != DETECTOR_ROW}
    assert ruled["kept"] == min(candidates, key=candidates.get)
    assert ruled["kept_chosen_among"] == 2 * len(spec.variants)
    for name, file in ruled["checkpoints"].items():
        _, _, meta = load_history_monitor(tmp_path / "rules" / file)
        assert meta.get("flag_rule", [1, 1]) == ruled["variants"][name]["flag_rule"]
    text = markdown_tables(result)
    assert "Guarded real loop" in text and "oracle (privileged)" in text
    assert "pooled over the named environments outside the family" in text
    assert "at most 50.0 %" in text and "How each variant ranks whole runs" in text
    assert "Observed on the held-out environments of the family, the mean miss rate" in text
    assert "against the single-image detector at the same needless flags" in text

    html, md = _monitor_report(tmp_path)
    assert "Runtime monitor on environments it has never seen" in md
    assert "Guarded real loop" in md and html.count("<table>") >= 3
    assert (tmp_path / "out" / result["reliability_figure"]).stat().st_size > 1000
    from reachwatch.pipeline.summary_section import summary_rows
    rows = {row[0].split(" (")[0].split(",")[0]: row for row in summary_rows(_Run(tmp_path))}
    assert rows["labels against the real loop"][1].startswith("not checked")
    miss = result["variants"][result["kept"]]["held_out"]["pooled"]["miss"]
    assert rows["monitor miss rate"][1] == "-" if not miss["of"] else \
        rows["monitor miss rate"][1].endswith(f"({miss['count']}/{miss['of']})")
    guarded, prevented = result["guarded"][result["kept"]], oracle["prevented"]
    assert rows["failures prevented"][3] == (
        "-" if not prevented else
        "meets" if guarded["prevented"] >= 0.85 * prevented else "misses")
    assert rows["calibration error"][3] in ("meets", "misses")
    assert "out/reliability.png" in md


def test_an_ensemble_study_saves_every_member_and_judges_their_mean(tmp_path):
    """``ensemble: 2``: each variant is two trainings (seeds 0 and 1); the risk the study
    judges at every held-out tick is what its checkpoint (both members) gives offline,
    and neither member's alone."""
    import dataclasses as dc
    from reachwatch.pipeline.monitor_runs import record_split
    from reachwatch.reach.application import load_application
    from reachwatch.systems import HistoryRiskEnsemble, platt
    spec = load_run_spec(data=TINY + MONITOR_STUDY).monitor
    spec = dc.replace(spec, ensemble=2, guarded_runs=0, held_out_runs=spec.runs + 1,
                      variants=[MonitorVariant("one frame")])
    scenario = load_scenario(data="")
    result = run_monitor_study(spec, scenario, tmp_path / "out", cache_dir=tmp_path / "cache",
                               progress=False, log=lambda m: None)
    model, _, meta = load_history_monitor(tmp_path / "out" / result["checkpoints"]["one frame"])
    assert isinstance(model, HistoryRiskEnsemble) and meta["members"] == 2
    assert result["ensemble"] == 2
    # judged and calibration environments record held_out_runs (calibration_runs 0:
    # measured as the judged ones, which the bound speaks of), the training ones runs
    assert {n for _, n in result["failing_runs"]["held_out"].values()} == {spec.runs + 1}
    assert {n for _, n in result["failing_runs"]["calibrate"].values()} == {spec.runs + 1}
    assert {n for _, n in result["failing_runs"]["train"].values()} == {spec.runs}
    held_out = record_split(spec, load_application(TAXI_APPLICATION), scenario, spec.environments()["held_out"],
                       spec.train + spec.calibrate, runs=spec.judged_runs,
                       cache_dir=tmp_path / "cache" / "runs", executor=None, progress=False)[0]
    calibration = lambda q: platt(q, *meta["calibration"])  # noqa: E731
    mine, raw, each = [], [], [[] for _ in model.members]
    for r, n in enumerate(held_out["ticks"]):
        frames, signals = held_out["frames"][r, :n], held_out["signals"][r, :n, :0]
        mine.append(model.risk_sequence(frames, signals, calibration))
        raw.append(model.risk_sequence(frames, signals))
        for e, member in zip(each, model.members):
            e.append(member.risk_sequence(frames, signals))
    with np.load(tmp_path / "out" / "risks.npz") as saved:
        judged = saved["one frame/held_out/risk"]
    # the study judged the calibrated mean of the members' raw risks, not one member's
    np.testing.assert_allclose(judged, np.concatenate(mine), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.concatenate(raw), np.mean([np.concatenate(e) for e in each], 0),
                               rtol=1e-5, atol=1e-7)
    for e in each:
        assert np.abs(np.concatenate(raw) - np.concatenate(e)).max() > 1e-4
    assert "the mean of 2 trainings' raw risks" in _monitor_report(tmp_path)[1]


CART_STUDY = """
monitor:
  kind: history
  family: {seed: 5}
  train: 1
  calibrate: 1
  held_out: 1
  alpha: 0.5
  runs: 12
  duration: 1.5
  within: 0.5
  height: 16
  width: 24
  pool: [1, 1]
  epochs: 1
  head_epochs: 2
  guarded_runs: 2
  variants:
    - {name: one frame}
    - {name: stacked 2 + signals, frames: 2, signals: true}
"""


def test_the_cart_runs_the_study_through_the_generic_application(tmp_path, monkeypatch):
    """Another application's loop (examples/cart) through the study: the generic
    `Application.recorded_runs` reads its camera and steering inside its loop, and the
    generic `Application.missions` runs it alone and guarded by the study's monitors."""
    from pathlib import Path
    from reachwatch.reach.application import load_application
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    spec = load_run_spec(data=text.replace("width: 160, height: 80", "width: 48, height: 24")
                         + CART_STUDY)                # validates: not refused for the cart
    scenario, cart = spec.scenario, load_application(spec.application)
    # the recording: from the start, every tick until the first one on a rail
    env = spec.monitor.environments()["train"][0]
    here = dc_replace(scenario, environment=env)
    starts = np.array([[0.0, 0.0], [0.4, 0.69]])    # straight on; turned near a rail
    runs = cart.recorded_runs(here, starts, duration=1.0, height=16, width=24,
                              cache_dir=tmp_path / "rec", progress=False)
    assert runs["frames"].shape == (2, 11, 16, 24, 3) and runs["signals"].shape == (2, 11, 1)
    np.testing.assert_allclose(runs["state"][:, 0], starts)
    assert list(runs["failed"]) == [False, True] and runs["ticks"][0] == 11
    n = runs["ticks"][1]
    assert 1 < n < 11 and abs(runs["state"][1, n - 1, 0]) >= 0.5 > abs(runs["state"][1, n - 2, 0])
    assert runs["failure_time"][1] == pytest.approx((n - 1) * scenario.controller.period)
    assert np.isnan(runs["state"][1, n:]).all() and not runs["frames"][1, n:].any()
    assert runs["frames"][0, 0].std() > 0                   # a rendered view, not a blank
    assert runs["signals"][1, 0, 0] < 0                      # steers away from the left rail
    # the loop alone's outcomes read off the recordings are those it runs to; recordings
    # that are not its runs are refused
    from reachwatch.pipeline.monitor_runs import alone_from_recordings, alone_reads_recordings
    assert alone_reads_recordings(cart, here)
    read = alone_from_recordings(cart, here, {**runs, "starts": starts}, 2, duration=1.0,
                                 cache_dir=tmp_path / "rec", executor=None, progress=False)
    ran = cart.missions(here, starts, duration=1.0, cache_dir=tmp_path / "rec", progress=False)
    for name, value in ran.as_fields().items():
        np.testing.assert_array_equal(getattr(read, name), value, err_msg=name)
    with pytest.raises(RuntimeError, match=r"starts \[0, 1\] differ from their recordings in "
                                           r"\['distance'\]"):
        alone_from_recordings(cart, here, {**runs, "starts": starts, "ticks": runs["ticks"] - [1, 0]},
                              2, duration=1.0, cache_dir=tmp_path / "rec", executor=None,
                              progress=False)

    result = run_monitor_study(spec.monitor, scenario, tmp_path / "out",
                               cache_dir=tmp_path / "cache", progress=False, log=lambda m: None,
                               application=cart)
    assert set(result["variants"]) == {"one frame", "stacked 2 + signals"}
    assert result["lead_s"] == pytest.approx(1.0 / 3.0)
    for row in result["variants"].values():
        pooled = row["held_out"]["pooled"]
        # safe runs + failing runs; misses count among the warnable failing ones
        assert pooled["needless"]["of"] + pooled["warnable"]["of"] == 12
        assert pooled["miss"]["of"] == pooled["warnable"]["count"]
    for name, file in result["checkpoints"].items():
        model, config, meta = load_history_monitor(tmp_path / "out" / file)
        assert config.signals == (1 if "signals" in name else 0)   # the cart's steering
    assert set(result["guarded"]) == set(result["checkpoints"]) | {ORACLE}
    for counts in result["guarded"].values():
        assert counts["runs"] == 2 and counts["failed_guarded"] <= counts["runs"]
        assert counts["distance_guarded_m"] <= counts["distance_alone_m"] + 1e-9
    # the generic recordings with a detector's score along them (here a history
    # monitor's): the same runs, and the score `score_runs` reads along the loop alone
    from reachwatch.diagrams import MonitorConfig
    watched = dc_replace(here, monitor=MonitorConfig(
        detector=str(tmp_path / "out" / result["checkpoints"]["one frame"])))
    scored = cart.recorded_runs(watched, starts, duration=1.0, height=16, width=24,
                                cache_dir=tmp_path / "rec", progress=False, scored=True)
    for key in ("frames", "signals", "state", "ticks", "failed"):
        np.testing.assert_array_equal(scored[key], runs[key], err_msg=key)
    along = cart.score_runs(watched, starts, duration=1.0, cache_dir=tmp_path / "rec",
                            progress=False)
    np.testing.assert_array_equal(scored["score"], along["score"])
    assert np.isfinite(scored["score"][0]).all() and not scored["engaged"].any()
    # the generic missions: a monitor that flags every tick brakes the cart from the start
    held = dc_replace(scenario, environment=spec.monitor.environments()["held_out"][0])
    alone = cart.missions(held, starts, duration=1.5, cache_dir=tmp_path / "m", progress=False)
    always = MonitorConfig(detector=str(tmp_path / "out" / result["checkpoints"]["one frame"]),
                           threshold=0.0, strategy="brake", brake_deceleration=3.0)
    braked = cart.missions(dc_replace(held, monitor=always), starts, fallback="brake",
                           duration=1.5, cache_dir=tmp_path / "m", progress=False)
    assert list(alone.failed) == [False, True] and not alone.flagged_ticks.any()
    assert alone.distance[0] == pytest.approx(1.5) and not alone.ever_stopped[0]
    assert braked.flagged_ticks[0] == braked.ticks[0] == 15 and braked.stopped[0]
    assert braked.distance[0] < 0.5 * alone.distance[0]
    # with a mission limit the runs go on past the horizon, judged by distance too; the
    # showcase's uncached runs are the same runs
    limited = cart.missions(dc_replace(held, monitor=always), starts, fallback="brake",
                            duration=1.5, mission_limit=2.0, cache_dir=tmp_path / "m",
                            progress=False)
    # braked to a stop from the first tick, both park short of the distance (the one
    # turned near a rail stops 0.12 m on, before it)
    assert limited.short_of_distance.tolist() == [True, True]
    assert not limited.failed_same_distance.any() and not limited.failed.any()
    # parked within the horizon, a run goes on to it: its ticks there are those without
    # a mission limit
    np.testing.assert_array_equal(limited.ticks, braked.ticks)
    np.testing.assert_array_equal(limited.flagged_ticks, braked.flagged_ticks)
    again = cart.mission_rollouts(dc_replace(held, monitor=always), "brake", 1.5, starts,
                                  mission_limit=2.0)
    for name, value in again.items():
        np.testing.assert_array_equal(value, getattr(limited, name))


def test_strict_json_writes_non_finite_numbers_as_null_and_reads_them_back(tmp_path):
    """NaN, and -inf in a list of warning scores (a run no rule can warn in time: missed
    at every threshold, ranked below every run) come back as they were."""
    import numpy as np

    from reachwatch.pipeline.monitor_sections import read_study_result
    from reachwatch.systems.files import nan_for_null, strict_json
    value = {"rate": float("nan"), "scores": [np.float32(0.5), -np.inf, np.inf, 2],
             "count": np.int64(3), "name": "x"}
    text = strict_json(value)
    assert text == ('{"rate": null, "scores": [0.5, null, null, 2], "count": 3, '
                    '"name": "x"}')
    back = nan_for_null(json.loads(text))
    assert np.isnan(back["rate"]) and np.isnan(back["scores"][1:3]).all()
    assert back["scores"][0] == 0.5 and back["count"] == 3 and back["name"] == "x"
    study = {"lead_s": 1.6, "within_s": 4.0, "alpha": 0.1,
             "variants": {"v": {"scores": {"calibrate": [{"warning": [0.3, -np.inf],
                                                          "safe_max": [0.2]}]},
                                "held_out": {"pooled": {"miss": {"rate": float("nan")}}}}}}
    (tmp_path / "monitor.json").write_text(strict_json(study))
    read = read_study_result(tmp_path / "monitor.json")["variants"]["v"]
    assert read["scores"]["calibrate"][0]["warning"] == [0.3, -np.inf]
    assert np.isnan(read["held_out"]["pooled"]["miss"]["rate"])


def test_a_studys_checkpoint_files_are_named_after_their_variants():
    assert checkpoint_file("single frame") == "monitor_single-frame.pt"
    assert checkpoint_file("GRU 16 (0.75 s) + signals") == "monitor_gru-16-0-75-s-signals.pt"
    assert checkpoint_file("Été ☀") == "monitor_t.pt"
    assert checkpoint_file("☀") == "monitor_variant.pt"
    taken = {"monitor_a-b.pt", "monitor_a-b-2.pt"}
    assert checkpoint_file("a b", taken) == "monitor_a-b-3.pt"


def test_a_study_clears_the_previous_result_before_it_writes_its_own(tmp_path):
    """A study killed while it writes leaves no ``monitor.json`` beside files of other
    settings, and the previous study's checkpoints and figure go with its result; other
    files stay."""
    (tmp_path / "monitor.json").write_text(json.dumps(
        {"checkpoints": {"a": "monitor_a.pt", "b": "monitor_b.pt"},
         "reliability_figure": "reliability.png"}))
    for name in ("monitor_a.pt", "monitor_b.pt", "reliability.png", "risks.npz", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    clear_previous_result(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "risks.npz"]
    (tmp_path / "monitor.json").write_text("{not json")        # a torn file: removed
    clear_previous_result(tmp_path)
    clear_previous_result(tmp_path / "missing")                   # nothing there: nothing to do
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "risks.npz"]


def test_a_killed_studys_checkpoints_go_before_the_next_study_writes(tmp_path):
    """A study killed after it saved its checkpoints (before its guarded runs) wrote no
    ``monitor.json`` to name them: the next study removes them all the same, so none
    stays beside its results to be deployed; a file of that name a study did not save
    stays."""
    from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel
    config = HistoryMonitorConfig(frames=1, height=16, width=16, channels=[4], features=4,
                                  hidden=4)
    save_checkpoint(tmp_path / "monitor_old-variant.pt", kind="history_monitor",
                    model=HistoryRiskModel(config), model_config=config,
                    preprocess_config=None, metadata={"calibration": [1.0, 0.0],
                                                      "threshold": 0.5, "lead_s": 1.0,
                                                      "variant": "old variant"})
    save_checkpoint(tmp_path / "monitor_mine.pt", kind="history_monitor",
                    model=HistoryRiskModel(config), model_config=config,
                    preprocess_config=None, metadata={"threshold": 0.5})
    (tmp_path / "monitor_notes.pt").write_bytes(b"not a checkpoint")
    kept = (tmp_path / "monitor_old-variant.pt").read_bytes()
    (tmp_path / "monitor_keep-v1.pt").write_bytes(kept)          # a copy renamed to keep
    (tmp_path / "monitor_old-variant-2.pt").write_bytes(kept)    # the second of that name
    clear_previous_result(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["monitor_keep-v1.pt",
                                                          "monitor_mine.pt",
                                                          "monitor_notes.pt"]


def test_the_study_refuses_a_cache_url_before_it_records_anything(tmp_path):
    spec = load_run_spec(data=TINY + MONITOR_STUDY).monitor
    for cache, out in (("memory://monitor-cache", tmp_path / "out"),
                       (tmp_path / "cache", "s3://bucket/out")):
        with pytest.raises(ValueError, match=r"must be a local folder .* got "
                                             r"(memory://monitor-cache|s3://bucket/out)$"):
            run_monitor_study(spec, load_scenario(data=""), out, cache_dir=cache,
                              progress=False, log=lambda m: None)
    assert not any(tmp_path.iterdir())


def test_the_summary_judges_prevented_failures_against_the_oracles_guarded_row(tmp_path):
    """The oracle's prevented failures in the guarded loop, from the same starts, are the
    target's reference (not the offline share of warnable runs); an ECE of no held-out
    tick is "-", not a miss."""
    from reachwatch.pipeline.summary_section import summary_rows
    from reachwatch.systems.files import strict_json
    miss = {"count": 1, "of": 4, "rate": 0.25}
    kept = {"held_out": {"pooled": {"miss": miss}, "ece": float("nan")}}
    guarded = {"prevented": 2, "failed_alone": 3, "needless_stops": 0, "safe_alone": 5}
    result = {"kept": "one", "lead_s": 1.67, "within_s": 4.0, "alpha": 0.1,
              "variants": {"one": kept},
              "guarded": {"one": guarded, ORACLE: {**guarded, "prevented": 2}},
              "oracle": {"held_out": {"pooled": {"warnable": {"count": 4, "of": 4,
                                                              "rate": 1.0}}}}}
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "monitor.json").write_text(strict_json(result))
    rows = {row[0].split(",")[0]: row for row in summary_rows(_Run(tmp_path))}
    prevented = rows["failures prevented"]
    assert prevented[1].endswith("(2/3)") and prevented[3] == "meets", prevented
    assert "the oracle: 2 of 3; this monitor 1.00 of that" in prevented[2]
    assert rows["calibration error (ECE) of the risk"][1:] == ["-", "<= 0.05", "-"]


def test_the_prediction_error_baseline_reads_the_estimate_off_the_recorded_signals():
    """TaxiNet's estimate leads the recorded signals (``[px_hat, theta_hat deg,
    steering]``): a run whose estimate is 1 m off fails within 4 s, a run estimated
    exactly survives, so the error ranks every tick right; an application that does not
    say what its controller estimates has no such baseline, nor has a controller whose
    estimate is NaN at a tick of a run."""
    from types import SimpleNamespace

    from reachwatch.diagrams import load_scenario
    from reachwatch.pipeline.monitor_judge import prediction_error_aurocs
    from reachwatch.taxi.application import TaxiApplication
    state = np.zeros((2, 9, 3))
    state[:, :, 0], state[:, :, 2] = 2.0, np.deg2rad(5.0)
    signals = np.zeros((2, 9, 3))
    signals[:, :, 0], signals[:, :, 1], signals[:, :, 2] = 2.0, 5.0, 0.1
    signals[0, :, 0] += 1.0                            # the failing run's estimate: 1 m off
    group = {"state": state, "signals": signals, "ticks": np.array([7, 9]),
             "watched_failure_time": np.array([3.0, np.nan])}
    scenario = load_scenario(data="")
    taxi = TaxiApplication()
    assert prediction_error_aurocs(taxi, scenario, {"s": [group]}, period=0.5,
                                   duration=8.0)["s"] == [1.0]
    # a start that has failed already is recorded with no tick: it adds nothing
    with_empty = {k: np.concatenate([v, v[:1]]) for k, v in group.items()}
    with_empty["ticks"][2] = 0
    assert prediction_error_aurocs(taxi, scenario, {"s": [with_empty]}, period=0.5,
                                   duration=8.0)["s"] == [1.0]
    group["signals"] = signals[..., ::-1].copy()       # the 1 m off in the last column,
    assert prediction_error_aurocs(taxi, scenario, {"s": [group]}, period=0.5,  # not read:
                                   duration=8.0)["s"] == [0.5]                   # a tie
    group["signals"] = signals.copy()
    group["signals"][1, 8, 1] = np.nan                  # NaN at a tick the run has
    assert np.isnan(prediction_error_aurocs(taxi, scenario, {"s": [group]}, period=0.5,
                                            duration=8.0)["s"]).all()
    group["signals"][1, 8, 1] = 5.0
    group["signals"][0, 8, 1] = np.nan                  # past the run's 7 ticks: not read
    assert prediction_error_aurocs(taxi, scenario, {"s": [group]}, period=0.5,
                                   duration=8.0)["s"] == [1.0]
    no_estimate = SimpleNamespace(true_estimate=None, estimate_scale=(),
                                  resolved=lambda s: s)
    assert np.isnan(prediction_error_aurocs(no_estimate, scenario, {"s": [group]}, period=0.5,
                                            duration=8.0)["s"]).all()


def test_a_safe_run_with_no_tick_reads_back_as_never_flagged(tmp_path):
    from reachwatch.pipeline.monitor_sections import read_study_result
    from reachwatch.systems.files import strict_json
    path = tmp_path / "monitor.json"
    path.write_text(strict_json({"lead_s": 1.6, "within_s": 4.0, "alpha": 0.1, "variants": {},
                                 "scores": {"warning": [-np.inf, 0.5], "safe_max": [-np.inf, 0.2]},
                                 "rate": np.nan}))
    back = read_study_result(path)
    assert back["scores"] == {"warning": [-np.inf, 0.5], "safe_max": [-np.inf, 0.2]}
    assert np.isnan(back["rate"])


def test_calibration_runs_that_cannot_bound_the_miss_rate_are_refused_before_training():
    """Known from the recorded calibration runs alone, before any training: with
    ``given_failures``, no calibration environment with a warnable failing run (its
    run failed 0.1 s in, under the 1 s lead) cannot bound the miss rate, whatever the
    monitor; one warnable failing run can, at alpha 0.5."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_judge import check_calibration_bounds
    from reachwatch.training.conformal import NoConformalThreshold
    spec = SimpleNamespace(flag_rules=[[1, 1], [2, 3]], alpha=0.5, given_failures=True)
    early = [{"ticks": np.array([2, 40]), "failure_time": np.array([0.1, np.nan])}]
    with pytest.raises(NoConformalThreshold, match=r"^monitor: the recorded calibration runs "
                                                   r"cannot bound the miss rate, whatever the "
                                                   r"monitor \(flag rule \[1, 1\]\): 0 "
                                                   r"calibration environments with a warnable"):
        check_calibration_bounds(spec, early, period=0.05, lead=1.0)
    later = [{"ticks": np.array([40, 40]), "failure_time": np.array([1.98, np.nan])}]
    check_calibration_bounds(spec, later, period=0.05, lead=1.0)


def test_a_risk_that_is_not_a_number_refuses_the_row_naming_where():
    """Before: a NaN risk flagged in one figure and not in another (the needless-flag
    tables read it as never flagged, the AUROC dropped the environment, Platt scaling
    silently kept its start point)."""
    from reachwatch.pipeline.monitor_study import _judged
    data = {"calibrate": [{"name": "A"}], "held_out": [{"name": "B"}]}
    raw = {"calibrate": [[np.array([0.1, 0.2])]],
           "held_out": [[np.array([0.3]), np.array([np.nan, 0.5, np.inf])]]}
    with pytest.raises(ValueError, match=r"monitor: single frame: 2 of the risks along the "
                                         r"runs of B \(held_out\) are not finite"):
        _judged("single frame", None, data, raw, period=0.05, lead=1.0)


def test_the_estimate_for_one_environment_says_how_many_had_nothing_to_miss():
    from reachwatch.pipeline.monitor_sections import per_environment_text
    kept = {"per_environment_bound_90": 0.0, "given_failures": False,
            "scores": {"calibrate": [{"warning": [0.5, 0.1]}, {"warning": []},
                                     {"warning": []}]}}
    text = per_environment_text(kept)
    assert "at or below 0.0 %" in text and "2 of the 3 had no warnable failing run" in text
    for e in kept["scores"]["calibrate"]:
        e["warning"] = []
    assert per_environment_text(kept) == (
        "For one new environment: no calibration environment had a warnable failing run, "
        "so their miss rates say nothing of one where runs fail.")
    # given failures, environments without any are left out of the rates: nothing to say
    kept["given_failures"] = True
    kept["scores"]["calibrate"][0]["warning"] = [0.4]
    assert "had no warnable" not in per_environment_text(kept)


def test_a_variant_whose_calibration_could_not_be_fitted_is_named():
    """Before: the identity was used without a word, and its ECE read as a calibrated
    risk's."""
    from reachwatch.pipeline.monitor_sections import uncalibrated_text
    result = {"within_s": 4.0, "variants": {"single frame": {"platt_fitted": False},
                                            "GRU": {"platt_fitted": True}, "old": {}}}
    assert uncalibrated_text(result).startswith(
        "Not calibrated: single frame. The calibration environments' ticks were all of "
        "one class (no run failed within 4 s of one")
    result["variants"]["single frame"]["platt_fitted"] = True
    assert uncalibrated_text(result) == ""
