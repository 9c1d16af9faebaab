"""Trajectory labels: every state a real run passes through is labelled by the same
run, checked tick by tick on hand-made runs and against direct simulation of the
real Drake loop."""

import numpy as np
import pytest
from pydrake.systems.framework import LeafSystem

from reachwatch.diagrams import make_closed_loop_diagram, simulate
from reachwatch.reach.outcomes import check_memoryless, path_labels, path_points
from reachwatch.taxi.fidelity import on_runway_starts
from reachwatch.training.dataset import (PATHS_STREAM, STATES_STREAM, DatasetSpec, build_dataset,
                                        dataset_folder, load_dataset)
from reachwatch.training.labels import (NO_RUN, SOURCE_BRT, SOURCE_PATH, SOURCE_ROLLOUT,
                                        LabelSpec, trajectory_samples)
from reachwatch.taxi import OffRunway
from tiny_run import taxi_application


def test_path_labels_tick_by_tick():
    ticks = np.arange(9) * 0.5                       # 0 .. 4 s
    # fails at 3.2 s, horizon 2 s: the ticks from 1.2 s on fail within it
    np.testing.assert_array_equal(path_labels(ticks[:7], 3.2, 4.0, 2.0),
                                  [0, 0, 0, 1, 1, 1, 1])
    # a failure exactly one horizon after a tick counts (as a run of the horizon would)
    assert path_labels([0.0, 1.0], 3.0, 3.0, 2.0).tolist() == [0, 1]
    # no failure in 4 s: the ticks up to 2 s are safe, the later ones cannot tell
    np.testing.assert_array_equal(path_labels(ticks, None, 4.0, 2.0), [0] * 5 + [-1] * 4)
    np.testing.assert_array_equal(path_labels(ticks, float("nan"), 4.0, 2.0),
                                  [0] * 5 + [-1] * 4)
    with pytest.raises(ValueError, match="horizon"):
        path_labels(ticks, None, 4.0, 0.0)
    with pytest.raises(ValueError, match="tick times"):
        path_labels([[0.0, 1.0]], None, 4.0, 1.0)


def test_path_points_cover_the_extension():
    assert path_points(8.0, 8.0, 8, 0.05).tolist() == list(range(0, 161, 8))
    assert path_points(8.0, 0.0, 8, 0.05).tolist() == [0]
    assert path_points(1.0, 1.0, 3, 0.05).tolist() == [0, 3, 6, 9, 12, 15, 18]


def test_trajectory_samples_keeps_settled_states_inside_the_box():
    starts = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    calls = []

    def run_paths(x):
        calls.append(len(x))
        nan = [np.nan, np.nan]
        return {"failed": np.array([False, True]), "ticks": np.array([30, 12]),
                "path_state": np.array([[[0.0, 0.0], [0.5, 0.5], [9.0, 9.0], [0.7, 0.7]],
                                        [[1.0, 1.0], [1.5, 1.5], nan, nan]]),
                "path_label": np.array([[0, 0, 0, -1], [1, 1, -1, -1]], np.int8)}

    inside = lambda x: np.all(x < 5, axis=1)      # noqa: E731 ([9, 9] is outside)
    states, labels, sources, info, runs = trajectory_samples(
        starts, LabelSpec("trajectory", max_rollouts=2), run_paths, inside)
    assert runs.tolist() == [0, 1, 0, 1]                  # each start, then its run's states
    assert calls == [2]                                   # the cap keeps the first 2 starts
    np.testing.assert_array_equal(states, [[0, 0], [1, 1], [0.5, 0.5], [1.5, 1.5]])
    assert labels.tolist() == [0, 1, 0, 1]
    assert sources.tolist() == [SOURCE_ROLLOUT] * 2 + [SOURCE_PATH] * 2
    assert info["path_samples"] == 2 and info["path_samples_left_out"] == 1
    assert info["rollout_frames"] == 42 and info["frames_per_label"] == 10.5


def test_trajectory_fields_leave_other_datasets_keys_alone(tmp_path, kmwh_day_brt):
    scenario, vf = kmwh_day_brt
    key = lambda labels: dataset_folder(tmp_path, scenario, vf, DatasetSpec(labels=labels), application=taxi_application())  # noqa: E731
    assert key(LabelSpec("rollout")) == key(LabelSpec("rollout", extend=3.0, stride=2))
    assert key(LabelSpec("trajectory")) != key(LabelSpec("trajectory", extend=3.0))
    assert key(LabelSpec("brt")) != key(LabelSpec("brt", paths=2))
    assert key(LabelSpec("brt", paths=2)) != key(LabelSpec("brt", paths=2, stride=4))
    with pytest.raises(ValueError, match="paths"):
        LabelSpec("brt", paths=-1).validate()
    with pytest.raises(ValueError, match="stride"):
        LabelSpec("trajectory", stride=0).validate()
    with pytest.raises(ValueError, match="extend"):
        LabelSpec("trajectory", extend=-1.0).validate()


class _Counter(LeafSystem):
    """A controller that keeps a tick count: it remembers more than the state."""

    def __init__(self):
        super().__init__()
        self.DeclareDiscreteState(1)


def test_a_controller_with_state_is_refused():
    from pydrake.systems.framework import DiagramBuilder
    builder = DiagramBuilder()
    builder.AddNamedSystem("controller", _Counter())
    diagram = builder.Build()
    with pytest.raises(ValueError, match="keeps no state.*has 1.*source: rollout"):
        check_memoryless(diagram.GetSubsystemByName("controller"))


def test_any_application_labels_the_states_its_runs_pass_through(tmp_path, monkeypatch):
    """The generic `Application.real_paths` (`reach.loop_runs.loop_paths`) on another
    plant (examples/cart): each label read along a run is the outcome of the cart's
    loop started at that state, checked by starting it there; a run that fails late
    labels its early states safe and its late ones anomalous."""
    from dataclasses import replace as dc_replace
    from pathlib import Path
    from reachwatch.pipeline.spec import load_run_spec
    from reachwatch.reach.application import load_application
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    spec = load_run_spec(data=text.replace("width: 160, height: 80", "width: 48, height: 24"))
    cart = load_application(spec.application)
    scenario = dc_replace(spec.scenario, environment=spec.train[0])
    grid = cart.grid(scenario, [5, 5])
    # straight on; turned hard (fails late); near a rail turned out (fails at once); on a rail
    starts = np.array([[0.0, 0.0], [0.0, 1.3], [0.35, 0.9], [0.5, 0.0]])
    horizon, extend = 0.5, 1.0
    paths = cart.real_paths(scenario, starts, grid=grid, horizon=horizon, extend=extend,
                            stride=1, cache_dir=tmp_path / "paths", progress=False).fields
    assert paths["path_state"].shape == (4, 11, 2)
    np.testing.assert_allclose(paths["path_state"][:, 0], starts)
    labels = paths["path_label"]
    assert (labels[0] == 0).all()
    assert labels[1, 0] == 0 and labels[1, -1] == -1 and (labels[1] == 1).any()
    assert labels[2, 0] == 1 and labels[3].tolist() == [1] + [-1] * 10
    alone = cart.real_outcomes(scenario, starts, grid=grid, duration=horizon,
                               cache_dir=tmp_path / "runs", progress=False)
    assert paths["failed"].tolist() == alone.failed.tolist() == [False, False, True, True]
    known = labels >= 0
    again = cart.real_outcomes(scenario, paths["path_state"][known], grid=grid,
                               duration=horizon, cache_dir=tmp_path / "runs", progress=False)
    np.testing.assert_array_equal(again.failed, labels[known] == 1)


def test_trajectory_labels_equal_direct_simulation_of_the_real_loop(tmp_path, kmwh_day_brt):
    """Each label of a trajectory-labelled dataset, the states the runs passed through
    included, is what the real Drake loop (TaxiNet on rendered images) does when
    simulated again from that state."""
    scenario, vf = kmwh_day_brt
    B, grid = scenario.environment.half_width, vf.grid
    # seed 258: two starts near the edge turning out fail after 0.45 and 0.75 s, so states
    # their runs pass through are anomalous too
    spec = DatasetSpec(samples=10, seed=258, height=20, width=36, chunk_size=8,
                       labels=LabelSpec("trajectory", extend=1.0, stride=5))
    data = load_dataset(build_dataset(tmp_path, scenario, vf, spec, progress=False, application=taxi_application()))
    info = data.manifest["labels"]
    along = data.sources == SOURCE_PATH
    assert data.sources[:10].tolist() == [SOURCE_ROLLOUT] * 10 and not along[:10].any()
    assert along[10:].all() and info["path_samples"] == along.sum() > 10
    assert np.all(grid.contains(np.asarray(data.states)))
    # each start is its own run; a state read along a run lies downtrack of its start
    assert data.runs[:10].tolist() == list(range(10)) and set(data.runs[10:]) <= set(range(10))
    assert np.all(np.diff(data.runs[10:]) >= 0)
    assert np.all(data.states[10:, 1] > data.states[data.runs[10:], 1])
    diagram = make_closed_loop_diagram(scenario)
    for x, label in zip(data.states, data.labels):
        run = simulate(diagram, initial_state=x, duration=1.0, period=0.05, failed=OffRunway(B))
        assert bool(label) == run.failed
    assert 0 < data.labels[along].sum() < along.sum()      # both kinds among the added states
    assert info["frames_per_label"] < 20                     # a rollout per label: 21 frames


def test_trajectory_labelled_run_checks_the_labels_read_along_runs(tmp_path):
    """``reachwatch run`` with trajectory labels: the datasets hold the states the runs
    passed through, the fidelity stage runs some of them again from scratch, the report
    shows that check, and Table 2 scores the uniform states alone too."""
    from reachwatch.pipeline.fidelity_sections import fidelity_section
    from reachwatch.pipeline.report import Page, labels_paragraph
    from reachwatch.pipeline.run import run_pipeline
    from reachwatch.pipeline.spec import load_run_spec
    text = """
name: tiny_trajectory
train: [{runway: KMWH, hour: 9.0, sky: clear}]
test: [{runway: KSFO, hour: 17.0, sky: clear}]
grid: [5, 3, 5]
horizon: 1.0
dataset: {samples: 10, height: 24, width: 40, chunk_size: 16,
          labels: {source: trajectory, extend: 0.5, stride: 5, paths: 1}}
detector:
  detector: {height: 24, width: 40, channels: [4, 8]}
  device: cpu
ensemble: {seeds: []}
fidelity: {starts: 3, max_box_exits: 1.0}
"""
    run = run_pipeline(load_run_spec(data=text), tmp_path, progress=False, log=lambda m: None,
                       until="evaluate")
    for env in ("KMWH_9h_clear", "KSFO_17h_clear"):
        data = load_dataset(tmp_path / run.outputs["dataset"]["folders"][env])
        assert data.manifest["label_counts"]["path"] == int(np.sum(data.sources == SOURCE_PATH)) > 0
        check = run.outputs["fidelity"][env]
        assert check["labels"]["source"] == "trajectory"
        # a fresh uniform start is labelled by its own run; the states read along runs
        # are what the loop does from them
        assert check["labels"]["agree"] == check["labels"]["n"] == 3
        assert check["path_labels"]["agree"] == check["path_labels"]["n"] == 3
        # their renders, counted apart from the check's own starts: none of these 1 s
        # runs leaves the runway, so each renders its 21 ticks
        assert check["path_labels"]["real_failures"] == 0
        assert check["path_labels"]["frames"] == 3 * 21
    rows = [r for r in run.outputs["evaluate"]["rows"] if r["environment"] == "KSFO_17h_clear"
            and r["method"] == "detector (real-loop trajectory + read-along labels)"]
    subsets = {r["states"]: r["n"] for r in rows if r["labels"] == "trajectory + read-along"}
    data = load_dataset(tmp_path / run.outputs["dataset"]["folders"]["KSFO_17h_clear"])
    assert subsets["all"] == len(data.labels) and subsets["uniform states"] == 10
    assert subsets["read along runs"] == len(data.labels) - 10
    assert {r["states"] for r in rows if r["labels"] == "brt"} == set(subsets)   # and the map's
    # the one extra run of `paths: 1` is run 10, after the 10 starts' own runs, from a
    # start of its own stream: none of the uniform samples
    assert data.runs.max() == 10 and data.manifest["labels"]["paths"]["runs"] == 1
    start = data.states[data.runs == 10][0]
    assert not np.isclose(data.states[:10], start).all(axis=1).any()
    assert ("besides them, the states that 1 more real run per environment pass through "
            "(from uniform on-runway states, 0.5 s past the horizon, every 5th tick)"
            in labels_paragraph(run.spec, run.outputs))
    page = Page("t")
    fidelity_section(page, run.spec, run.outputs["fidelity"],
                     run.outputs.get("dataset", {}).get("labels", {}), {})
    markdown = "\n".join(page.md)
    assert "labels read along runs (trajectory labels, or dataset.labels.paths), checked" in markdown
    assert "| KSFO_17h_clear | 3 | 100.0 [43.9, 100.0] |" in markdown
    frames = run.outputs["fidelity"]["KSFO_17h_clear"]["path_labels"]["frames"]
    row = next(r for r in markdown.splitlines() if r.startswith("| KSFO_17h_clear | 3 | 100.0"))
    assert row.endswith(f"| {frames} |")


def test_path_starts_are_on_the_runway_and_apart_from_the_samples():
    lo, hi = np.array([-12.0, 100.0, -0.5]), np.array([12.0, 250.0, 0.5])
    assert PATHS_STREAM != STATES_STREAM           # build_dataset's two streams of seed 3:
    starts = on_runway_starts((lo, hi), 200, [3, *PATHS_STREAM], half_width=10.0)
    assert np.all(np.abs(starts[:, 0]) < 10.0) and np.all((starts >= lo) & (starts <= hi))
    np.testing.assert_array_equal(starts, on_runway_starts((lo, hi), 200, [3, *PATHS_STREAM],
                                                           half_width=10.0))
    samples = lo + np.random.default_rng([3, *STATES_STREAM]).uniform(size=(200, 3)) * (hi - lo)
    assert not np.isin(starts, samples).any()


def test_brt_labels_with_paths_add_true_labels_along_real_runs(tmp_path, kmwh_day_brt):
    """``brt`` labels plus ``paths: 3``: the uniform samples keep the map's labels, and
    the states three real runs pass through are added with what the loop does from
    them, checked by simulating it again."""
    scenario, vf = kmwh_day_brt
    B, grid = scenario.environment.half_width, vf.grid
    spec = DatasetSpec(samples=10, seed=5, height=20, width=36, chunk_size=8,
                       labels=LabelSpec("brt", paths=3, extend=1.0, stride=5))
    data = load_dataset(build_dataset(tmp_path, scenario, vf, spec, progress=False, application=taxi_application()))
    along = data.sources == SOURCE_PATH
    assert data.sources[:10].tolist() == [SOURCE_BRT] * 10 and along[10:].all()
    np.testing.assert_array_equal(data.labels[:10], np.asarray(data.values[:10]) <= 0)
    info = data.manifest["labels"]["paths"]
    assert info["runs"] == 3 and info["samples"] == along.sum() > 3
    starts = on_runway_starts(grid, 3, [5, *PATHS_STREAM], half_width=B)
    np.testing.assert_allclose(data.states[10], starts[0])       # each run's start comes first
    assert data.runs[:10].tolist() == [NO_RUN] * 10             # uniform samples: on no run
    for run in range(3):
        np.testing.assert_allclose(data.states[along][data.runs[along] == run][0], starts[run])
    diagram = make_closed_loop_diagram(scenario)
    for x, label in zip(data.states[along], data.labels[along]):
        run = simulate(diagram, initial_state=x, duration=1.0, period=0.05, failed=OffRunway(B))
        assert bool(label) == run.failed


def test_hybrid_falls_back_to_trajectory_labels_where_its_audit_distrusts_the_map(
        tmp_path, kmwh_day_brt):
    """A map that calls every state safe is distrusted by the hybrid's audit against the
    real loop (two of seed 258's starts fail), and with ``distrusted: trajectory`` the
    dataset is exactly what the ``trajectory`` source makes from the same starts."""
    import dataclasses as dc
    scenario, vf = kmwh_day_brt
    blind = dc.replace(vf, values=np.abs(vf.values) + 5.0)

    def build(root, labels):
        spec = DatasetSpec(samples=10, seed=258, height=20, width=36, chunk_size=8, labels=labels)
        return load_dataset(build_dataset(root, scenario, blind, spec, progress=False, application=taxi_application()))

    want = build(tmp_path / "trajectory", LabelSpec("trajectory", extend=1.0, stride=5))
    got = build(tmp_path / "hybrid", LabelSpec("hybrid", audit=10, distrusted="trajectory",
                                               distrusted_starts=10, extend=1.0, stride=5))
    info = got.manifest["labels"]
    assert info["source"] == "hybrid" and info["labelled_by"] == "trajectory"
    assert not info["audit"]["map_trusted"] and info["audit"]["false_safe"] == 2
    assert info["audit_frames"] > 0 and info["path_samples"] == want.manifest["labels"]["path_samples"]
    for name in ("states", "labels", "sources", "runs"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert (got.sources == SOURCE_PATH).any() and got.labels.sum() > 0

    # other label settings make another dataset, from the same cached runs: its audit
    # and trajectory runs are found in the root's shared cache, nothing is rendered
    cache = tmp_path / "hybrid" / "rollouts"
    chunks = sorted(p.relative_to(cache) for p in cache.rglob("*.npz"))
    again = build(tmp_path / "hybrid", LabelSpec("hybrid", audit=10, band=0.5,
                                                 distrusted="trajectory", distrusted_starts=10,
                                                 extend=1.0, stride=5))
    assert again.folder != got.folder and chunks
    assert sorted(p.relative_to(cache) for p in cache.rglob("*.npz")) == chunks
    np.testing.assert_array_equal(again.labels, got.labels)
    # an audit allowed to go on (more_audit) stops at its first batch, which distrusts
    # the map: that batch is the shorter audit's, so again nothing is rendered
    longer = build(tmp_path / "hybrid", LabelSpec("hybrid", audit=10, more_audit=20,
                                                  distrusted="trajectory", distrusted_starts=10,
                                                  extend=1.0, stride=5))
    assert longer.folder not in (got.folder, again.folder)
    assert longer.manifest["labels"]["audit"]["batches"] == 1
    assert sorted(p.relative_to(cache) for p in cache.rglob("*.npz")) == chunks
    np.testing.assert_array_equal(longer.labels, got.labels)
