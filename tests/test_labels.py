"""Label sources: the BRT, the real loop from every state, and the hybrid that rolls
out only where the map is not trusted."""

import dataclasses as dc

import numpy as np
import pytest

from reachwatch.diagrams import make_closed_loop_diagram, simulate
from reachwatch.training.dataset import DatasetSpec, build_dataset, load_dataset
from reachwatch.training.labels import (SOURCE_BRT, SOURCE_ROLLOUT, LabelSpec, audited_band,
                                        assign_labels)
from reachwatch.taxi import OffRunway
from tiny_run import taxi_application


class FakeLoop:
    """The 'real' loop of a controller that steers as the grid says at its nodes and
    off the runway between them: it fails wherever ``truth`` says, and the grid's
    BRT (values) knows nothing of the states between nodes."""

    def __init__(self, truth):
        self.truth, self.calls = np.asarray(truth, bool), []

    def __call__(self, index):
        self.calls.append(list(index))
        return self.truth[index], 10 * len(index)


def _case():
    values = np.array([-1.0, 0.5, 5.0, 6.0, 1.5, 7.0, -2.0, 8.0, 9.0, 0.2])
    on_runway = np.array([False] + [True] * 9)
    return values, on_runway


def test_hybrid_keeps_brt_labels_where_the_audit_finds_the_map_right():
    values, on_runway = _case()
    truth = values <= 0.3                        # the BRT is right except inside its band
    loop = FakeLoop(truth)
    n, labels, sources, info = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, band=2.0), loop)
    assert info["audit"] == {"samples": 3, "real_failures": 0, "false_safe": 0,
                             "largest_error_m": 0.0, "map_trusted": True, "band": 2.0}
    # the audit (samples 1, 2, 3), then the safe ones within 2 m of the boundary (4, 9)
    assert loop.calls == [[1, 2, 3], [4, 9]]
    assert n == 10 and list(np.flatnonzero(sources == SOURCE_ROLLOUT)) == [1, 2, 3, 4, 9]
    np.testing.assert_array_equal(labels, truth)            # sample 9 (V = 0.2) was a miss
    assert info["rollout_disagrees_with_brt"] == 1 and info["rollout_frames"] == 50


def test_hybrid_rolls_out_every_safe_verdict_where_the_audit_finds_a_miss():
    """Between the nodes this controller steers off the runway: samples 3 and 7 fail
    although V > 2; the audit catches sample 3, and the hybrid then rolls out every
    sample the BRT calls safe, catching 7 too."""
    values, on_runway = _case()
    truth = (values <= 0) | np.isin(np.arange(10), [3, 7])
    loop = FakeLoop(truth)
    n, labels, sources, info = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, band=2.0), loop)
    assert info["audit"]["false_safe"] == 1 and not info["audit"]["map_trusted"]
    assert loop.calls == [[1, 2, 3], [4, 5, 7, 8, 9]]
    np.testing.assert_array_equal(labels, truth)
    assert list(sources) == [SOURCE_BRT if v <= 0 else SOURCE_ROLLOUT for v in values]
    # BRT labels alone would have missed both
    assert np.sum((values > 0) & truth) == 2


def test_hybrid_widens_its_band_to_the_errors_the_audit_measures():
    """The audit finds sample 2 (V = -2.5) wrong, unsafe by the map but survived: the
    map's errors reach 2.5 m from the boundary, so the band widens to 2 x 2.5 = 5 m
    (within max_band 6) and the map stays trusted: every on-runway sample with |V| < 5
    is rolled out (4, 6 and 9 after the audit), catching sample 6 (V = -2.0, survives)
    that the 2 m band would have kept. An error 3.5 m out would need a 7 m band, and a
    false-safe verdict anywhere in the audit distrusts the map whatever its distance."""
    values, on_runway = _case()
    values[2] = -2.5
    truth = values <= 0
    truth[[2, 6]] = False
    loop = FakeLoop(truth)
    spec = LabelSpec("hybrid", audit=3, band=2.0, band_factor=2.0, max_band=6.0)
    n, labels, sources, info = assign_labels(values, on_runway, spec, loop)
    assert info["audit"]["largest_error_m"] == 2.5 and info["audit"]["band"] == 5.0
    assert info["audit"]["map_trusted"] and loop.calls == [[1, 2, 3], [4, 6, 9]]
    np.testing.assert_array_equal(labels, truth)
    values[2] = -3.5
    n, labels, sources, info = assign_labels(values, on_runway, spec, FakeLoop(truth))
    assert not info["audit"]["map_trusted"] and info["audit"]["band"] == 2.0
    assert audited_band([-3.5, 1.0], [False, False], band=2.0, band_factor=2.0,
                        max_band=6.0) == (7.0, False, 3.5)
    # a false-safe verdict 0.5 m out: a 2 m band would do, but the map is not trusted
    assert audited_band([0.5, 3.0], [True, False], band=2.0, band_factor=2.0,
                        max_band=6.0) == (2.0, False, 0.5)
    with pytest.raises(ValueError, match="max_band .* must be at least band"):
        LabelSpec("hybrid", band=2.0, max_band=1.0).validate()


def test_hybrid_rolls_out_unsafe_verdicts_near_the_boundary():
    """The map calls sample 6 unsafe (V = -2.0, on the band's edge) and sample 4 unsafe
    (V = -0.5) but the loop survives from both: the hybrid rolls out the on-runway
    unsafe verdicts within the band (4), keeps those further in (6) and never rolls out
    a state already off the runway (0)."""
    values, on_runway = _case()
    values[4] = -0.5
    truth = values <= 0
    truth[[4, 6]] = False
    loop = FakeLoop(truth)
    n, labels, sources, info = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, band=2.0), loop)
    assert info["audit"]["map_trusted"] and loop.calls == [[1, 2, 3], [4, 9]]
    assert labels[4] == 0 and sources[4] == SOURCE_ROLLOUT
    assert labels[6] == 1 and sources[6] == SOURCE_BRT and sources[0] == SOURCE_BRT


def test_rollout_budget_keeps_a_uniform_prefix_and_brt_source_runs_nothing():
    values, on_runway = _case()
    truth = values <= 0
    loop = FakeLoop(truth)
    n, labels, sources, info = assign_labels(values, on_runway, LabelSpec("rollout", max_rollouts=4), loop)
    assert n == 4 and info["samples_kept"] == 4 and loop.calls == [[0, 1, 2, 3]]
    assert np.all(sources == SOURCE_ROLLOUT) and len(labels) == 4
    loop = FakeLoop(truth)
    n, labels, sources, info = assign_labels(values, on_runway, LabelSpec("brt"), loop)
    assert n == 10 and loop.calls == [] and np.all(sources == SOURCE_BRT)
    with pytest.raises(ValueError, match="dataset.labels.source"):
        LabelSpec("oracle").validate()


def test_rollout_labels_equal_direct_simulation_of_the_real_loop(tmp_path, kmwh_day_brt):
    """A dataset labelled by rollouts: each label is what the real Drake loop (TaxiNet
    on rendered images) does from that state, checked by simulating it again."""
    scenario, vf = kmwh_day_brt
    B = scenario.environment.half_width
    spec = DatasetSpec(samples=10, seed=5, height=20, width=36, chunk_size=8,
                       labels=LabelSpec("rollout"))
    data = load_dataset(build_dataset(tmp_path, scenario, vf, spec, progress=False, application=taxi_application()))
    assert np.all(data.sources == SOURCE_ROLLOUT)
    assert data.manifest["labels"]["rollouts"] == 10
    diagram = make_closed_loop_diagram(scenario)
    for x, label in zip(data.states, data.labels):
        run = simulate(diagram, initial_state=x, duration=1.0, period=0.05, failed=OffRunway(B))
        assert bool(label) == run.failed
    assert 0 < data.labels.sum() < 10


def test_hybrid_falls_back_to_trajectory_labels_only_where_the_audit_distrusts_the_map():
    values, on_runway = _case()
    spec = LabelSpec("hybrid", audit=3, band=2.0, distrusted="trajectory")
    # distrusted (the audit finds sample 3 safe on the map and failing): nothing is rolled
    # out past the audit, and the caller is told to label by trajectories
    loop = FakeLoop((values <= 0) | np.isin(np.arange(10), [3, 7]))
    n, labels, sources, info = assign_labels(values, on_runway, spec, loop)
    assert (n, labels, sources) == (0, None, None) and loop.calls == [[1, 2, 3]]
    assert info["labelled_by"] == "trajectory" and info["audit_frames"] == 30
    assert info["audit"]["false_safe"] == 1 and not info["audit"]["map_trusted"]
    # trusted: exactly the plain hybrid's labels and rollouts
    truth = values <= 0.3
    plain, fallback = FakeLoop(truth), FakeLoop(truth)
    expected = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, band=2.0), plain)
    got = assign_labels(values, on_runway, spec, fallback)
    assert plain.calls == fallback.calls == [[1, 2, 3], [4, 9]]
    np.testing.assert_array_equal(got[1], expected[1])
    np.testing.assert_array_equal(got[2], expected[2])
    assert "labelled_by" not in got[3] and got[3]["audit"]["map_trusted"]
    assert spec.reads_along and not LabelSpec("hybrid").reads_along
    with pytest.raises(ValueError, match="distrusted must be one of"):
        LabelSpec("hybrid", distrusted="brt").validate()
    with pytest.raises(ValueError, match="distrusted_starts"):
        LabelSpec("hybrid", distrusted="trajectory", distrusted_starts=0).validate()


def test_a_longer_audit_runs_in_batches_and_stops_where_the_map_is_caught():
    """``more_audit``: a map whose one false-safe verdict (sample 7) lies past the
    first batch is trusted by an audit of 3 and caught by one going on to 9, batch by
    batch; the batches are the same index lists whatever ``more_audit`` is (so each
    one's cached runs serve a longer audit), and a caught map stops the audit."""
    values = np.full(12, 5.0)                    # all safe by the map, outside the band
    on_runway = np.ones(12, bool)
    truth = np.arange(12) == 7
    short = FakeLoop(truth)
    got = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, band=2.0), short)
    assert short.calls == [[0, 1, 2]] and got[3]["audit"]["map_trusted"]
    assert got[1][7] == 0                        # the short audit's label is wrong
    long = FakeLoop(truth)
    got = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, more_audit=9, band=2.0), long)
    assert long.calls == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]]  # 3 batches, the rest
    assert got[3]["audit"] == {"samples": 9, "real_failures": 1, "false_safe": 1,
                               "largest_error_m": 5.0, "map_trusted": False, "band": 2.0,
                               "batches": 3}
    np.testing.assert_array_equal(got[1], truth)
    # trusted all the way: the last batch is cut at more_audit; the band's rollouts follow
    right = FakeLoop(np.zeros(12, bool))
    got = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, more_audit=7, band=2.0), right)
    assert right.calls == [[0, 1, 2], [3, 4, 5], [6]]
    assert got[3]["audit"]["map_trusted"] and got[3]["audit"]["samples"] == 7
    # caught in the first batch: the audit stops there
    early = FakeLoop(np.arange(12) == 1)
    got = assign_labels(values, on_runway, LabelSpec("hybrid", audit=3, more_audit=9, band=2.0), early)
    assert early.calls[0] == [0, 1, 2] and got[3]["audit"]["batches"] == 1
    assert got[3]["audit"]["samples"] == 3


def test_more_audit_is_validated_and_keys_only_when_set():
    for bad in (dict(audit=3, more_audit=3), dict(audit=0, more_audit=5), dict(more_audit=-1)):
        with pytest.raises(ValueError, match="more_audit"):
            LabelSpec("hybrid", **bad).validate()
    fields = {f.name for f in dc.fields(LabelSpec)}
    assert set(LabelSpec("hybrid").key()) == fields - {"more_audit"}
    assert LabelSpec("hybrid", more_audit=100).key()["more_audit"] == 100
    assert DatasetSpec().key()["labels"] == LabelSpec().key()


def test_the_log_line_says_how_each_dataset_was_labelled():
    from reachwatch.training.dataset import label_summary
    trusted = {"samples": 1000, "labels": {
        "source": "hybrid", "rollout_frames": 16016,
        "audit": {"samples": 100, "false_safe": 0, "map_trusted": True, "band": 0.1}}}
    assert label_summary(trusted) == ("hybrid: map trusted after 100 audit runs, band 0.10 m; "
                                      "1000 labels, 16016 frames (16.0 per label)")
    fallback = {"samples": 1418, "labels": {
        "source": "hybrid", "rollout_frames": 25811, "audit_frames": 14782,
        "labelled_by": "trajectory",
        "audit": {"samples": 100, "false_safe": 1, "map_trusted": False, "band": 0.1}}}
    assert label_summary(fallback) == (
        "hybrid: map distrusted after 100 audit runs (1 false-safe), trajectory labels; "
        "1418 labels, 40593 frames (28.6 per label)")
    assert label_summary({"samples": 600, "labels": {"source": "brt"}}) == \
        "brt; 600 labels, 0 frames (0.0 per label)"
