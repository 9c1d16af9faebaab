"""A controller without an ``estimate`` output: the default guard strategies lose the
fallbacks that dead-reckon from it (said in one line), and a run file that names one is
refused before anything is swept, naming the key."""

import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.pipeline.run import fit_guard
from reachwatch.pipeline.spec import load_run_spec
from tiny_run import TINY


class _SteeringOnly(LeafSystem):
    def __init__(self, estimate: bool, size: int = 2):
        super().__init__()
        self.DeclareAbstractInputPort("color_image", AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, lambda c, o: o.SetAtIndex(0, 0.0))
        if estimate:
            self.DeclareVectorOutputPort("estimate", size,
                                         lambda c, o: o.SetFromVector([0] * size))


def test_the_default_strategies_leave_out_dead_reckoning_without_an_estimate():
    spec, said = load_run_spec(data=TINY), []
    before = list(spec.guard.strategies)
    assert any("dead_reckoning" in name for name in before)
    fit_guard(spec, _SteeringOnly(estimate=False), said.append)
    assert spec.guard.strategies == [n for n in before if "dead_reckoning" not in n]
    assert len(said) == 1 and "no estimate output" in said[0]


def test_a_named_dead_reckoning_fallback_is_refused_without_an_estimate():
    spec = load_run_spec(data=TINY + "\n" + "guard: {strategies: [brake, slow_down+dead_reckoning]}\n"
                         if "guard:" not in TINY else TINY.replace(
                             "guard: {", "guard: {strategies: [brake, slow_down+dead_reckoning], "))
    with pytest.raises(ValueError, match=r"guard.strategies\[1\]: 'slow_down\+dead_reckoning'.*"
                                         r"no estimate output; leave it out"):
        fit_guard(spec, _SteeringOnly(estimate=False), lambda m: None)


def test_a_controller_with_an_estimate_keeps_every_strategy():
    spec = load_run_spec(data=TINY)
    before = list(spec.guard.strategies)
    fit_guard(spec, _SteeringOnly(estimate=True), lambda m: None)
    assert spec.guard.strategies == before


def test_an_estimate_of_another_size_than_the_application_carries_is_left_out_or_refused():
    """The taxi dead-reckons [px m, theta deg]: a controller estimating 3 numbers kept
    the default dead-reckoning fallback, and the guard stage failed after its sweep on
    arrays that do not broadcast."""
    spec, said = load_run_spec(data=TINY), []
    before = list(spec.guard.strategies)
    fit_guard(spec, _SteeringOnly(estimate=True, size=3), said.append)
    assert spec.guard.strategies == [n for n in before if "dead_reckoning" not in n]
    assert len(said) == 1 and ("dead-reckons from an estimate of 2 numbers (the "
                               "application's true_estimate)") in said[0] and "estimates 3" in said[0]
    named = load_run_spec(data=TINY.replace(
        "guard: {", "guard: {strategies: [brake, slow_down+dead_reckoning], "))
    with pytest.raises(ValueError, match=r"guard.strategies\[1\]: .* estimates 3; leave it out"):
        fit_guard(named, _SteeringOnly(estimate=True, size=3), lambda m: None)
