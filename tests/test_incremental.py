"""Incremental training: which states are mined, and the error when none are."""

import re
from types import SimpleNamespace

import numpy as np
import pytest

from reachwatch.systems import CameraConfig, Environment
from reachwatch.pipeline.spec import IncrementalConfig
from reachwatch.taxi.incremental import fine_tune_taxinet, mine_anomalies


def _data(px, labels):
    px = np.asarray(px, float)
    return SimpleNamespace(states=np.column_stack([px, np.full_like(px, 150.0), np.zeros_like(px)]),
                           labels=np.asarray(labels, np.uint8))


def test_mined_states_are_anomalous_and_on_the_runway():
    kmwh, ksfo = Environment("KMWH", 9.0, "clear"), Environment("KSFO", 9.0, "clear")  # B 10, 25 m
    a = _data([-12.0, -9.0, 0.0, 5.0, 11.0], [1, 1, 0, 1, 1])
    b = _data([-20.0, 24.0, 26.0], [1, 0, 1])
    mined = mine_anomalies([(kmwh, a), (ksfo, b)], limit=100, rng=np.random.default_rng(0))
    assert [e.name for e, _ in mined] == ["KMWH_9h_clear", "KSFO_9h_clear"]
    np.testing.assert_array_equal(mined[0][1][:, 0], [-9.0, 5.0])
    np.testing.assert_array_equal(mined[1][1][:, 0], [-20.0])
    capped = mine_anomalies([(kmwh, a), (ksfo, b)], limit=2, rng=np.random.default_rng(0))
    assert [len(s) for _, s in capped] == [1, 1]


def test_fine_tune_without_mined_states_says_why(tmp_path):
    nothing = [(Environment(), np.zeros((0, 3)))]
    with pytest.raises(ValueError, match="no anomalous on-runway states"):
        from reachwatch.diagrams import REFERENCE_TAXINET
        fine_tune_taxinet(REFERENCE_TAXINET, nothing, IncrementalConfig(), CameraConfig(),
                          tmp_path / "t.pt")
    with pytest.raises(ValueError, match=re.escape("incremental.epochs must be a whole number in [1, 100000], got 0")):
        IncrementalConfig(epochs=0).validate()
