"""``reachwatch run``: a tiny end-to-end run with every report section, stage skipping,
downstream-only re-runs, resume after a failure, Dask (the run file's checks are in
test_run_spec.py)."""

import dataclasses as dc
import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from reachwatch.pipeline.run import STAGES, run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.stages import Run
from reachwatch.training.dataset import load_dataset
from reachwatch.training.evaluation import NOT_FAILED
from tiny_run import TINY

SECTIONS = ("environments", "diagrams", "brts", "fidelity", "labels", "table2", "margin", "guard",
            "incremental", "benchmarks", "configuration")


def _run(out, text=TINY, **kw):
    log = []
    run = run_pipeline(load_run_spec(data=text), out, progress=False, log=log.append, **kw)
    return run, log


def _ran(log):
    return {re.match(r"\[(\S+)\]", m).group(1) for m in log if "] running" in m}


def test_random_families_a_held_out_threshold_and_held_out_labels_run_through_the_pipeline(
        tmp_path, seed_caches):
    seed_caches(tmp_path)
    text = (TINY.replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                         "train_random: {count: 1, seed: 0}\ntest_random: {count: 1, seed: 1}\n"
                         "held_out_labels: {source: rollout, max_rollouts: 6}")
                .replace("batch_size: 8", "batch_size: 8\n  threshold_folds: 2")
                .replace("fidelity: {starts: 3", "fidelity: {starts: 0"))
    run, _ = _run(tmp_path, text, until="evaluate")
    trained = run.outputs["train"]["held_out_threshold"]
    assert list(trained["per_group"]) == ["KMWH_9h_clear", run.spec.training_environments()[1].name]
    assert run.outputs["train"]["threshold"] == trained["threshold"]
    assert len(list((tmp_path / "detectors").glob("detector_brt_heldout_*.pt"))) == 2
    # The prediction-error baseline's threshold is chosen on left-out groups too.
    baseline = run.outputs["train"]["prediction_error_held_out_threshold"]
    assert list(baseline["per_group"]) == list(trained["per_group"])
    assert run.outputs["train"]["prediction_error_detector_threshold"] == baseline["threshold"]
    assert len(list((tmp_path / "detectors").glob(
        "detector_prediction_error_heldout_*.pt"))) == 2
    held_out = run.spec.held_out_environments()[0].name
    assert held_out.startswith("RND1-")
    assert {r["environment"] for r in run.outputs["evaluate"]["rows"]} == {held_out}
    assert set(run.outputs["dataset"]["folders"]) == {e.name for e in
                                                      run.spec.training_environments() +
                                                      run.spec.held_out_environments()}
    # held_out_labels: the held-out dataset is labelled by the real loop (capped at 6
    # rollouts), the training ones by the BRT, and Table 2 scores the held-out
    # environment against both its true labels and the BRT's verdicts on the same states
    labels = run.outputs["dataset"]["labels"]
    assert labels[held_out]["source"] == "rollout"
    assert {labels[e.name]["source"] for e in run.spec.training_environments()} == {"brt"}
    data = load_dataset(tmp_path / run.outputs["dataset"]["folders"][held_out])
    assert 1 <= labels[held_out]["counts"]["rollout"] <= 6 and len(data.labels) < 40
    own = [r for r in run.outputs["evaluate"]["rows"] if r["states"] == "all"
           and r["method"].startswith("detector (BRT labels)")]
    assert [r["labels"] for r in own] == ["rollout", "brt"]
    assert [r["positives"] for r in own] == [int(data.labels.sum()), int(data.brt_labels.sum())]


def test_tiny_run_end_to_end_skips_finished_stages_and_reruns_downstream(tiny_run, tmp_path):
    # the session's tiny run (rendered from nothing, tests/conftest.py), copied here
    shutil.copytree(tiny_run[0], tmp_path, dirs_exist_ok=True)
    log = tiny_run[1]
    records = {p.name: p.stat().st_mtime for p in (tmp_path / "stages").iterdir()}
    run, again = _run(tmp_path)                                # nothing changed: all skipped
    assert _ran(again) == set()
    assert {p.name: p.stat().st_mtime for p in (tmp_path / "stages").iterdir()} == records
    html = (tmp_path / "report.html").read_text()
    md = (tmp_path / "report.md").read_text()
    for anchor in SECTIONS:
        assert f"id='{anchor}'" in html, anchor
    for src in re.findall(r"src='([^']+)'", html):
        assert (tmp_path / src).is_file(), src
    for src in re.findall(r"\]\(([^)]+)\)", md):
        assert (tmp_path / src).is_file(), src
    assert re.search(r"Labels against the target .*: met in \d+ of 2 environments", md)
    # the log says how each environment's dataset was labelled, as it finishes
    labelled = [re.match(r"\[dataset_(\S+)\] labelled: (.*)", m) for m in log]
    assert sorted(m.group(1) for m in labelled if m) == ["KMWH_9h_clear", "KSFO_17h_clear"]
    assert any(m.group(2).startswith("brt; 40 labels") for m in labelled if m)
    rows = run.outputs["evaluate"]["rows"]
    every = [r for r in rows if r["states"] == "all"]
    assert [r["environment"] for r in every] == ["KSFO_17h_clear"] * 4
    for r in every:
        assert f"| KSFO_17h_clear | {r['method']} | brt | all | 40 |" in md
        assert r["tp"] + r["fn"] == r["positives"] and r["tp"] + r["fp"] + r["fn"] + r["tn"] == 40
    mine = every[0]
    # Table 2 against the target, first: one held-out environment, so min = median
    recall = "-" if np.isnan(mine["recall"]) else f"{100 * mine['recall']:.2f}"
    meet_recall = int(mine["recall"] >= 0.95)
    meet_both = int(mine["recall"] >= 0.95 and mine["accuracy"] >= 0.95)
    assert (f"| listed | brt | all | 1 | {recall} / {recall} | {100 * mine['accuracy']:.2f} / "
            f"{100 * mine['accuracy']:.2f} |") in md
    assert f"| {meet_recall} of 1 | {meet_both} of 1 |" in md
    assert md.index("| listed | brt | all | 1 |") < md.index("KSFO_17h_clear: the detector flags")
    assert (f"KSFO_17h_clear: the detector flags {100 * (mine['tp'] + mine['fp']) / 40:.2f}% of "
            f"the images") in md
    figures = run.outputs["evaluate"]["figures"]["KSFO_17h_clear"]
    assert f"![{figures['roc']}]({figures['roc']})" in md
    assert f"![{figures['mistakes']}]({figures['mistakes']})" in md
    detector = every[0]
    assert figures["mistake_counts"] == {"misses": min(4, detector["fn"]),
                                         "false_alarms": min(4, detector["fp"])}
    # the same rows over the states still on the runway, counted from the dataset itself
    data = run.datasets(run.spec.test)[0]
    on_runway = np.abs(data.states[:, 0]) < run.spec.test[0].half_width
    inside = [r for r in rows if r["states"] == NOT_FAILED]
    assert [r["method"] for r in inside] == [r["method"] for r in every]
    assert {r["n"] for r in inside} == {int(on_runway.sum())}
    assert {r["positives"] for r in inside} == {int(data.labels[on_runway].sum())}
    guard = run.outputs["guard"]["KSFO_17h_clear"]
    assert set(guard["volumes"]) == {"unguarded", "slow_down", "brake",
                                     "slow_down+dead_reckoning", "slow_down+oracle"}
    assert guard["volumes"]["brake"] <= guard["volumes"]["unguarded"]
    # liveness beside every failure set, the trade-off curve, the real-loop check
    nodes = run.grid_for(run.spec.test[0]).states()
    outside = int(np.sum(np.abs(nodes[:, 0]) >= run.spec.test[0].half_width))
    off_runway = next(iter(guard["liveness"].values()))["failed_at_start"]
    assert (off_runway["count"], off_runway["of"]) == (outside, len(nodes))
    for name, figures in guard["liveness"].items():
        assert figures["failure_set"]["rate"] == guard["volumes"][name]
        assert figures["alone_failure_set"]["rate"] == guard["volumes"]["unguarded"]
        assert len(guard["tradeoff"][name]) in (2, 3)
        assert {"same_distance_failure_set", "short_of_distance"} <= set(guard["tradeoff"][name][0])
        # judged by distance too: the controller alone covers the distance within the
        # horizon, so its failure set is the same either way
        assert figures["alone_same_distance_failure_set"]["rate"] == guard["volumes"]["unguarded"]
        perfect = guard["perfect_detector"][name]
        assert perfect["alone_failure_set"] == figures["alone_failure_set"]
        # the grid's off-runway nodes fail before their first tick, whatever the fallback
        assert figures["failed_at_start"] == perfect["failed_at_start"] == off_runway
    assert "fails at the same distance %" in md and "perfect detector" in md
    assert "cut, on-runway starts %" in md
    assert (tmp_path / guard["tradeoff_figure"]).is_file()
    real = guard["check"]["fallbacks"]["brake"]["real"]
    assert guard["check"]["starts"] == real["starts"] == 2
    assert "needless stops" in md and "The same figures in the real Drake loops" in md
    assert guard["online"]["alone_ticks_per_s"] > 0 and guard["online"]["guarded_ticks_per_s"] > 0
    fidelity = run.outputs["fidelity"]
    assert set(fidelity) == {"KMWH_9h_clear", "KSFO_17h_clear", "KMWH_17h_clear"}
    check = fidelity["KSFO_17h_clear"]
    assert check["brt"]["n"] == check["table_rollouts"]["n"] == 3 and check["frames"] > 0
    assert check["labels"]["source"] == "brt" and check["labels"]["agree"] == check["brt"]["agree"]
    assert "labels" not in fidelity["KMWH_17h_clear"]          # incremental only: no dataset
    assert "Fidelity against the real Drake loop" in md and "false-safe" in md
    label_row = next(r for r in md.splitlines() if r.startswith("| KSFO_17h_clear | brt | - |"))
    assert label_row.endswith("| 40 | 0 | 0.0 |")             # BRT labels render nothing
    # the guard's failure set beside its Monte-Carlo estimate from the real runs
    real = check["brt"]["real_failures"]
    assert ("The controller alone in the real loop, from 3 random on-runway starts" in md
            and f"real loop {100 * real / 3:.1f} [" in md and f"({real} of 3 starts)" in md)
    inc = run.outputs["incremental"]
    assert inc["environment"] == "KMWH_17h_clear" and 0 <= inc["after"] <= 1
    assert (tmp_path / inc["checkpoint"]).is_file()
    assert _ran(log) >= {"dataset", "train", "evaluate", "incremental", "report",
                         "sweep_KMWH_9h_clear", "solve_KSFO_17h_clear", "guard_KSFO_17h_clear"}

    # the detector changed (the guard's real-loop check left out: it would only render)
    _, log = _run(tmp_path, TINY.replace("epochs: 1", "epochs: 2").replace("check_starts: 2",
                                                                           "check_starts: 0"))
    assert _ran(log) == {"train", "evaluate", "guard_KSFO_17h_clear", "report"}
    assert not any("sweep_" in m and "running" in m for m in log)

    # a flag budget sets the guard's threshold without labels: only the guard reruns
    # (without its real-loop runs, which the budget does not need)
    run, log = _run(tmp_path, TINY.replace("epochs: 1", "epochs: 2").replace(
        "noise_starts: 0}", "noise_starts: 0, flag_budget: 0.3}").replace(
        "candidates: 2", "candidates: 0").replace("check_starts: 2", "check_starts: 0"))
    assert _ran(log) == {"guard_KSFO_17h_clear", "report"}
    guard, trained = run.outputs["guard"]["KSFO_17h_clear"], run.outputs["train"]
    budget = guard["flag_budget"]
    assert budget["threshold"] == guard["threshold"] and budget["fallback"] == "slow_down"
    assert budget["scenario_threshold"] == trained["threshold"] and not budget["score_noise"]
    assert budget["flagged_ticks"] <= 0.3 and budget["starts"] == 600
    md = (tmp_path / "report.md").read_text()
    assert f"The threshold {guard['threshold']:.3g} was set here, without labels" in md


def test_a_slice_runs_its_environments_alone_with_the_whole_runs_records(tmp_path, capsys,
                                                                         seed_caches):
    """``only``: the per-environment stages (sweep, solve, dataset, fidelity) for the
    named environments alone, each with the record the whole run gives it; stages that
    pool every environment are refused, and so are names the run lacks."""
    seed_caches(tmp_path / "whole")
    seed_caches(tmp_path / "part")
    whole, _ = _run(tmp_path / "whole", until="fidelity")
    part, log = _run(tmp_path / "part", until="fidelity", only=["KSFO_17h_clear"])
    assert any("a slice of 1 of the run's 3 environments, up to fidelity: KSFO_17h_clear" in m
               for m in log)
    env = "KSFO_17h_clear"
    assert sorted(p.stem for p in (tmp_path / "part" / "stages").iterdir()) == sorted(
        ["dataset", f"sweep_{env}", f"solve_{env}", f"fidelity_{env}"])
    def timeless(outputs):                  # wall times ("seconds", "sweep_seconds") left out
        return {k: v for k, v in outputs.items() if not k.endswith("seconds")}
    for stage in (f"sweep_{env}", f"solve_{env}", f"fidelity_{env}"):
        a, b = (json.loads((tmp_path / d / "stages" / f"{stage}.json").read_text())
                for d in ("whole", "part"))
        assert a["key"] == b["key"] and a["files"] == b["files"], stage
        assert timeless(a["outputs"]) == timeless(b["outputs"]), stage
    assert part.outputs["dataset"]["folders"] == {env: whole.outputs["dataset"]["folders"][env]}
    assert part.outputs["dataset"]["labels"][env] == whole.outputs["dataset"]["labels"][env]
    # the slice's page: the fidelity section over what is checked so far in its directory
    md = (tmp_path / "part" / "checked.md").read_text()
    assert "1 of the run's 3 environments have a real-loop check on record" in md
    assert "Not checked yet: KMWH_9h_clear, KMWH_17h_clear." in md
    assert f"| {env} | test | 3 |" in md and "met in 1 of 1 environments" in md
    assert any(m.startswith("checked so far: 1 of the run's 3 environments, labels meeting "
                            "the target in 1 of 1; ") for m in log)
    # the same function finds the whole run's three records current, and none once the
    # check's settings change (the keys are computed, all the way down, without rendering)
    from reachwatch.pipeline.checked_page import checked_environments
    assert list(checked_environments(whole)["checks"]) == ["KMWH_9h_clear", env, "KMWH_17h_clear"]
    changed = Run(load_run_spec(data=TINY.replace("starts: 3", "starts: 4")), tmp_path / "whole")
    found = checked_environments(changed)
    assert found["checks"] == {} and found["stale"] == dict.fromkeys(
        ["KMWH_9h_clear", env, "KMWH_17h_clear"], "the check's settings or its dataset changed")
    folder = whole.outputs["dataset"]["folders"][env]
    (tmp_path / "whole" / folder / "manifest.json").unlink()
    found = checked_environments(whole)                 # its dataset is gone: not current
    assert found["stale"] == {env: f"its dataset ({folder}) is not there"}
    assert list(found["checks"]) == ["KMWH_9h_clear", "KMWH_17h_clear"]
    changed = Run(load_run_spec(data=TINY.replace("horizon: 4.0", "horizon: 3.0")), tmp_path / "whole")
    assert set(checked_environments(changed)["stale"].values()) == {
        "its BRT is not the run file's (sweep or solve inputs changed)"}
    from reachwatch.pipeline.checked_page import write_checked_page
    page = write_checked_page(changed)
    assert page["checks"] == [] and page["stale"] == ["KMWH_9h_clear", env, "KMWH_17h_clear"]
    assert ("running them again brings them up to date): KMWH_9h_clear (its BRT is not the run "
            "file's (sweep or solve inputs changed)); KSFO_17h_clear (its BRT") in (
        tmp_path / "whole" / "checked.md").read_text()
    with pytest.raises(ValueError, match=r"no environment named 'KSFO_21h_clear' in run 'tiny'; "
                                         r"its environments are: KMWH_9h_clear, KSFO_17h_clear"):
        _run(tmp_path / "bad", until="fidelity", only=["KSFO_21h_clear"])
    with pytest.raises(ValueError, match="no environment given"):
        _run(tmp_path / "bad", until="fidelity", only=[])
    with pytest.raises(ValueError, match="up to fidelity at most .* got --until train"):
        _run(tmp_path / "bad", until="train", only=[env])
    assert not (tmp_path / "bad").exists()
    # the command line: --only alone stops after fidelity, and the slice is finished
    from reachwatch.pipeline.cli import main
    spec_path = tmp_path / "tiny.yaml"
    spec_path.write_text(TINY)
    main(["run", "--scenario", str(spec_path), "--out", str(tmp_path / "part"), "--executor",
          "inline", "--only", env])
    assert not (tmp_path / "part" / "stages" / "train.json").exists()


def test_refined_run_solves_and_checks_on_the_refined_table(tmp_path, seed_caches):
    seed_caches(tmp_path)
    text = TINY.replace("horizon: 4.0", "horizon: 4.0\nrefine: {levels: 1, band: 1.0}\n"
                                        "solved_theta_deg: 56\nsolved_py_max: 290")
    # the held-out environment alone (a slice): the others would check the same again
    run, _ = _run(tmp_path, text, until="fidelity", only=["KSFO_17h_clear"])
    solved = run.outputs["solve"]["KSFO_17h_clear"]
    # the tables and the BRT cover |theta| <= 56 deg and py <= 290 m; the labelled states
    # stay within the paper's box (28 deg, 250 m)
    states = load_dataset(tmp_path / run.outputs["dataset"]["folders"]["KSFO_17h_clear"]).states
    assert np.abs(states[:, 2]).max() <= np.deg2rad(28.0) + 1e-9
    assert states[:, 1].max() <= 250.0 + 1e-9
    assert np.allclose(run.value_function("KSFO_17h_clear").grid.hi[1:], [290.0, np.deg2rad(56.0)])
    assert solved["grid"] == [9, 5, 9] and solved["nodes_rendered"][0] == 75
    assert 75 < solved["nodes_rendered"][1] < 9 * 5 * 9
    vf = run.value_function("KSFO_17h_clear")
    assert vf.grid.shape == (9, 5, 9)
    grid, steering = run.steering_table(run.spec.test[0])
    assert grid == vf.grid and steering.shape == (9, 5, 9, 1)
    with np.load(tmp_path / solved["table"]) as saved:
        assert saved["rendered"].sum() == solved["nodes_rendered"][1]
    assert run.outputs["fidelity"]["KSFO_17h_clear"]["table_rollouts"]["n"] == 3


def test_map_selection_keeps_the_level_and_variant_its_own_runs_find_best(tmp_path, seed_caches):
    seed_caches(tmp_path)
    from reachwatch.reach import Fidelity, select_map
    from reachwatch.taxi import on_runway_starts
    text = TINY.replace("horizon: 4.0", "horizon: 4.0\nrefine: {levels: 1, band: 1.0}\n"
                        "map_selection: {starts: 6, seed: 7, robust_spreads_deg: [0]}")
    run, _ = _run(tmp_path, text, until="solve", only=["KSFO_17h_clear"])  # one is enough
    env = run.spec.test[0]
    solved = run.outputs["solve"][env.name]
    chosen = solved["map_selection"]
    # two levels, each nominal and robust (0 deg), all scored on the same 6 runs
    assert [c["map"] for c in chosen["candidates"]] == [
        "level 0", "level 0, robust 0 deg", "level 1", "level 1, robust 0 deg"]
    assert {c["n"] for c in chosen["candidates"]} == {6}
    fields = [f.name for f in dc.fields(Fidelity)]
    scores = [Fidelity(**{k: c[k] for k in fields}) for c in chosen["candidates"]]
    kept = select_map(scores, costs=[c["nodes_rendered"] for c in chosen["candidates"]])
    assert chosen["kept"] == chosen["candidates"][kept]["map"]
    # the saved map is the kept one: its grid, and its verdicts at the selection's starts
    vf = run.value_function(env.name)
    assert vf.metadata["map_selection"] == chosen["kept"] and "_selected_" in solved["value"]
    assert list(vf.grid.shape) == ([5, 3, 5] if kept < 2 else [9, 5, 9]) == solved["grid"]
    starts = on_runway_starts(run.grid_for(env), 6, 7, half_width=env.half_width)
    assert vf.in_brt(starts).sum() == chosen["candidates"][kept]["predicted_failures"]
    grid, _ = run.steering_table(env)
    assert grid == vf.grid
    # the report lists every candidate's verdicts on those runs and marks the kept one
    from reachwatch.pipeline.fidelity_sections import map_selection_section
    from reachwatch.pipeline.report import Page
    page = Page("t")
    map_selection_section(page, run.spec, run.outputs["solve"])
    md = "".join(page.md)
    assert "by 6 real-loop runs from seeded on-runway starts (seed 7)" in md
    kept_row = [r for r in md.splitlines() if r.startswith(f"| {env.name} | {chosen['kept']} |")]
    assert len(kept_row) == 1 and kept_row[0].endswith("| yes |")
    assert md.count("| yes |") == len(run.outputs["solve"])
    page = Page("t")
    map_selection_section(page, run.spec, {env.name: {k: v for k, v in solved.items()
                                                      if k != "map_selection"}})
    assert "".join(page.md) == "# t\n"
    with pytest.raises(ValueError, match="map_selection.seed 1000 equals fidelity.seed"):
        load_run_spec(data=text.replace("seed: 7", "seed: 1000"))


def test_killed_run_resumes_at_the_failed_stage(tmp_path, monkeypatch, seed_caches, tiny_run):
    """Interrupted as training starts and resumed (over a torn stage record), the run
    computes the stages from the failed one on, and its outputs (its datasets, rendered
    by these runs, included) are byte for byte those of the session's tiny run, which
    was never interrupted."""
    seed_caches(tmp_path)
    shutil.rmtree(tmp_path / "datasets")          # rendered here, not copied
    from reachwatch.pipeline import detector_stages as stages
    calls = []

    def broken(*args, **kw):
        calls.append(1)
        raise KeyboardInterrupt("killed")
    monkeypatch.setattr(stages, "train_detector", broken)
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, until="evaluate")
    assert calls and not (tmp_path / "stages" / "train.json").exists()
    monkeypatch.undo()
    (tmp_path / "stages" / "dataset.json").write_text("{ truncated")   # a torn record
    _, log = _run(tmp_path, until="evaluate")
    assert _ran(log) == {"dataset", "train", "evaluate"}
    assert any("corrupt" in m for m in log)
    compared, differ = [], []
    for path in sorted(p for p in tmp_path.rglob("*") if p.is_file()):
        name = path.relative_to(tmp_path)
        if not (tiny_run[0] / name).is_file():
            continue
        compared.append(name)
        if name.parts[0] == "stages":           # records: the same, but for their work
            same = _results(path) == _results(tiny_run[0] / name)
        else:
            same = path.read_bytes() == (tiny_run[0] / name).read_bytes()
        if not same:
            differ.append(str(name))
    assert not differ, differ
    assert {"stages", "datasets", "detectors", "figures"} <= {n.parts[0] for n in compared}


def _results(path):
    """A stage record without what says when it ran, how long it took and how much it
    rendered itself (a resumed run reads what an earlier one rendered)."""
    record = json.loads(path.read_text())
    for field in ("seconds", "finished", "check"):
        record.pop(field)
    record["outputs"] = {k: v for k, v in record["outputs"].items()
                         if not k.endswith("seconds") and k != "rendered"}
    return record


def test_until_stops_and_dask_executor_runs_the_heavy_stages(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    from reachwatch.pipeline.shipping_executor import ShippingExecutor
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address="127.0.0.1:0") as cluster, \
            distributed.Client(cluster) as client:
        # the dataset's tasks bring the ensemble's checkpoints (ShippingExecutor)
        run, _ = _run(tmp_path, until="dataset", executor=ShippingExecutor(client))
    assert set(run.outputs) >= {"sweep", "solve", "dataset"} and "train" not in run.outputs
    assert sorted(json.loads(p.read_text())["stage"] for p in (tmp_path / "stages").iterdir()) \
        == sorted(["dataset"] + [f"{s}_{e}" for s in ("sweep", "solve") for e in
                                 ("KMWH_9h_clear", "KSFO_17h_clear", "KMWH_17h_clear")])
    with pytest.raises(ValueError, match="until must be one of"):
        _run(tmp_path, until="deploy")
    # A second run directory sharing the sweep cache sweeps nothing again.
    other = tmp_path / "other"
    chunks = {p: p.stat().st_mtime for p in (tmp_path / "sweeps").rglob("*") if p.is_file()}
    _run(other, until="sweep", sweep_cache=tmp_path / "sweeps")
    assert not (other / "sweeps").exists() and len(list((other / "stages").iterdir())) == 3
    assert {p: p.stat().st_mtime for p in (tmp_path / "sweeps").rglob("*") if p.is_file()} \
        == chunks
    assert STAGES[-1] == "report"


def test_a_robust_run_solves_robust_brts_from_the_same_sweeps(tmp_path, seed_caches):
    """``robust`` changes the solve only: the same sweeps, a BRT at least as large in
    every environment, saved under its own name and said in the metadata."""
    sweeps = seed_caches(tmp_path) / "sweeps"
    nominal, _ = _run(tmp_path / "nominal", until="solve", sweep_cache=sweeps)
    chunks = {p: p.stat().st_mtime for p in sweeps.rglob("*") if p.is_file()}
    robust, _ = _run(tmp_path / "robust", TINY.replace("horizon: 4.0", "horizon: 4.0\nrobust: "
                                                      "{min_spread_deg: 0}"),
                     until="solve", sweep_cache=sweeps)
    assert {p: p.stat().st_mtime for p in sweeps.rglob("*") if p.is_file()} == chunks
    for name, solved in robust.outputs["solve"].items():
        assert "_robust_" in solved["value"]
        assert solved["brt_fraction"] >= nominal.outputs["solve"][name]["brt_fraction"]
        vf = robust.value_function(name)
        assert vf.metadata["robust"] and vf.metadata["robust_min_spread_deg"] == 0
    assert any(solved["brt_fraction"] > nominal.outputs["solve"][name]["brt_fraction"]
               for name, solved in robust.outputs["solve"].items())


@pytest.mark.slow
def test_report_renders_in_headless_chromium(tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    _run(tmp_path)
    shot = tmp_path / "shot.png"
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu",
                    f"--screenshot={shot}", "--window-size=1280,2400",
                    (tmp_path / "report.html").as_uri()], check=True, capture_output=True,
                   timeout=120)
    assert shot.stat().st_size > 20_000

def test_evaluate_command_is_the_run_up_to_evaluate(tmp_path, capsys):
    from reachwatch.pipeline.cli import main
    assert main(["evaluate", "--train", "KMWH:9:clear", "--test", "KSFO:17:clear",
                 "--shape", "5", "3", "5", "--samples", "20", "--input-size", "24", "40",
                 "--epochs", "1", "--ensemble", "0", "--executor", "inline", "--check-starts", "0",
                 "--distrusted", "trajectory", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| KSFO_17h_clear | detector (BRT labels) | brt | all | 20 |" in out
    assert "| KSFO_17h_clear | detector (BRT labels) | brt | not yet failed |" in out
    # then Table 2 against the target, one row per held-out group and subset
    assert "against the target of recall >= 95.00% and accuracy >= 95.00%" in out
    assert "| listed | brt | all | 1 |" in out and "| listed | brt | not yet failed | 1 |" in out
    # the label options reach the run file (BRT labels read neither)
    assert "distrusted: trajectory" in (tmp_path / "run.yaml").read_text()
    assert (tmp_path / "table2.csv").is_file() and (tmp_path / "stages" / "evaluate.json").is_file()
    assert not (tmp_path / "stages" / "guard_KSFO_17h_clear.json").exists()


def test_the_report_is_written_anew_when_reachwatch_code_changes(tmp_path, monkeypatch):
    """The report's key carries the source of all of reachwatch: a resumed run whose
    report code changed (nothing else) does not keep the old report."""
    import reachwatch.pipeline.run as run_module
    from reachwatch.reach.fingerprint import LIBRARY, modules_source_digest
    run = Run(load_run_spec(data=TINY), tmp_path / "run")
    before = run_module.report_key(run)
    assert before == run_module.report_key(run)
    monkeypatch.setattr(run_module, "modules_source_digest",
                        lambda *names: modules_source_digest(*names) + "edited")
    assert run_module.report_key(run) != before
    assert LIBRARY[0] == "reachwatch.systems" and LIBRARY[-1] == "reachwatch.pipeline"


def test_the_report_is_written_anew_when_what_it_prints_changes(tmp_path):
    """The report prints the run file and each stage's figures and timings: a stage run
    again for the same files (new timings) or a run-file key no stage reads changes its
    key; the same records and file keep it."""
    import copy
    import reachwatch.pipeline.run as run_module

    def written():                        # a stage's outputs: a file, a float, a NaN
        (tmp_path / "run" / "f.txt").write_text("hello")
        return {"file": "f.txt", "x": 0.1 + 0.2, "n": float("nan")}
    # a run directory opened again, its stage skipped: the same key
    first = Run(load_run_spec(data=TINY), tmp_path / "run", log=lambda m: None)
    first.stage("sweep", "k", written)
    again = Run(load_run_spec(data=TINY), tmp_path / "run", log=lambda m: None)
    again.stage("sweep", "k", lambda: pytest.fail("the stage ran again"))
    assert run_module.report_key(again) == run_module.report_key(first)
    run = Run(load_run_spec(data=TINY), tmp_path / "run")
    run.records = {"sweep": {"stage": "sweep", "key": "k", "files": {},
                             "outputs": {"seconds": 1.0}}}
    before = run_module.report_key(run)
    assert run_module.report_key(copy.deepcopy(run)) == before
    run.records["sweep"]["outputs"]["seconds"] = 2.0
    assert run_module.report_key(run) != before
    run.records["sweep"]["outputs"]["seconds"] = 1.0
    run.spec.scenario.duration += 1.0
    assert run_module.report_key(run) != before



def test_a_directory_holding_another_run_is_refused_and_kept(tmp_path):
    """Another run's directory (its recorded run file names another run) is refused in
    one line, its run file untouched, as is one whose run file cannot be read; the same
    run with an edited file is recorded."""
    Run(load_run_spec(data=TINY), tmp_path / "run")
    recorded = (tmp_path / "run" / "run.yaml").read_bytes()
    other = load_run_spec(data=TINY.replace("name: tiny", "name: other"))
    with pytest.raises(ValueError, match=r"holds the run 'tiny', not 'other': give another "
                                         r"--out, or delete .*run.yaml to reuse"):
        Run(other, tmp_path / "run")
    assert (tmp_path / "run" / "run.yaml").read_bytes() == recorded
    # a run file that cannot be read says nothing of whose run the directory holds: it
    # was rewritten, and the directory's files taken over, without a word
    for broken in (b"name: [", b"\xff\xfe"):
        (tmp_path / "run" / "run.yaml").write_bytes(broken)
        with pytest.raises(ValueError, match=r"run.yaml cannot be read \(.*\), so whose run "
                                             r".* holds is unknown: give another --out"):
            Run(other, tmp_path / "run")
        assert (tmp_path / "run" / "run.yaml").read_bytes() == broken
    # nor does one that names no run (empty, or without a name) beside stage records;
    # in a directory without them it is taken over
    (tmp_path / "run" / "stages").mkdir(exist_ok=True)
    (tmp_path / "run" / "stages" / "sweep_x.json").write_text("{}")
    for nameless in (b"", b"grid: [3, 3, 3]\n", b"- a list\n"):
        (tmp_path / "run" / "run.yaml").write_bytes(nameless)
        with pytest.raises(ValueError, match=r"run.yaml names no run, so whose run .* holds "
                                             r"is unknown: give another --out"):
            Run(other, tmp_path / "run")
        assert (tmp_path / "run" / "run.yaml").read_bytes() == nameless
    (tmp_path / "fresh").mkdir()
    (tmp_path / "fresh" / "run.yaml").write_bytes(b"")
    Run(other, tmp_path / "fresh")
    assert b"name: other" in (tmp_path / "fresh" / "run.yaml").read_bytes()
    (tmp_path / "run" / "stages" / "sweep_x.json").unlink()
    (tmp_path / "run" / "run.yaml").write_bytes(recorded)
    lines = []
    Run(load_run_spec(data=TINY.replace("horizon: 4.0", "horizon: 3.0")), tmp_path / "run",
        log=lines.append)
    assert (tmp_path / "run" / "run.yaml").read_bytes() != recorded
    assert any("the run file differs from the last one run here" in m for m in lines)
