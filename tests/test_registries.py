"""A new fallback speed strategy or label source is one module that registers it: here
each is registered from this test module alone, used through the library's own entry
points (`Fallback.parse`, the array rule, the Drake switch; `LabelSpec`,
`label_samples`, the fidelity check's verdicts, ``--labels``), and removed after."""

import argparse
import re
import types

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from reachwatch.systems import STRATEGIES, STRATEGY_REGISTRY, Fallback, FallbackSwitch, \
    SpeedStrategy
from reachwatch.systems.registry import Registry
from reachwatch.training.labels import (LABEL_SOURCE_REGISTRY, LABEL_SOURCES, NO_RUN,
                                        SOURCE_BRT, SOURCE_PATH, SOURCE_ROLLOUT, LabelInputs,
                                        LabelSource, LabelSpec, Labelled, assign_labels,
                                        label_samples, label_source, label_verdicts,
                                        labels_every_state_by_its_run, trajectory_samples)

PERIOD = 0.05


def _coast_check(fallback):
    if fallback.resume_acceleration > 5.0:
        raise ValueError(f"coast: resume_acceleration must be at most 5 m/s^2, got "
                         f"{fallback.resume_acceleration:g}")


#: Speed decays by a fixed factor per flagged tick (no Fallback field read).
COAST = SpeedStrategy("coast", lambda speed, fallback, period: 0.5 * speed,
                      "halves the speed each flagged tick", check=_coast_check)


def test_a_registry_refuses_a_name_twice_and_undoes_a_with_block():
    registry = Registry("widget")
    entry = types.SimpleNamespace(name="one")
    registry.register(entry)
    with pytest.raises(ValueError, match=r"^widget 'one' is already registered$"):
        registry.register(types.SimpleNamespace(name="one"))
    for bad in ("", "Two", "a+b", 3):
        with pytest.raises(ValueError, match="name must be lower case"):
            registry.register(types.SimpleNamespace(name=bad))
    with pytest.raises(RuntimeError):
        with registry.registered(types.SimpleNamespace(name="two")):
            assert registry.names == ("one", "two") and "two" in registry.names
            raise RuntimeError
    assert registry.names == ("one",) and repr(registry.names) == "('one',)"
    assert "two" not in registry and [] not in registry       # unhashable: not a name
    with pytest.raises(ValueError, match="no widget 'two' is registered"):
        registry.unregister("two")
    # the built-ins cannot be registered twice either
    with pytest.raises(ValueError, match=r"^speed strategy 'brake' is already registered$"):
        STRATEGY_REGISTRY.register(SpeedStrategy("brake", lambda s, f, p: s))
    with pytest.raises(ValueError, match=r"^label source 'brt' is already registered$"):
        LABEL_SOURCE_REGISTRY.register(LABEL_SOURCE_REGISTRY.get("brt"))


def test_a_registered_speed_strategy_runs_through_fallback_and_the_switch():
    from tiny_run import TINY
    from reachwatch.pipeline.guard_commands import _fallback
    from reachwatch.pipeline.spec import load_run_spec
    assert STRATEGIES == ("slow_down", "brake")
    with pytest.raises(ValueError, match=re.escape("fallback 'coast': write a speed strategy "
                                                   "('slow_down', 'brake')")):
        Fallback.parse("coast")
    with STRATEGY_REGISTRY.registered(COAST):
        assert STRATEGIES == ("slow_down", "brake", "coast")
        fallback = Fallback.parse("coast+dead_reckoning", resume_acceleration=2.0)
        assert (fallback.strategy, fallback.steering, fallback.name) == \
            ("coast", "dead_reckoning", "coast+dead_reckoning")
        assert fallback.speed_strategy.describe() == "coast: halves the speed each flagged tick"
        with pytest.raises(ValueError, match="coast: resume_acceleration must be at most 5"):
            Fallback.parse("coast", resume_acceleration=9.0)
        # the run file's guard.strategies and guard --fallbacks read it by its name
        assert _fallback("coast+taxinet") == "coast"
        spec = load_run_spec(data=TINY.replace(
            "guard: {candidates: 2", "guard: {strategies: [coast+controller, brake], "
                                     "candidates: 2"))
        assert spec.guard.strategies == ["coast", "brake"]
        # the array rule: flagged halves the speed, clear climbs back at 2 m/s^2
        np.testing.assert_allclose(
            fallback.next_speed([4.0, 2.0, 4.99], [True, False, False], nominal=5.0,
                                period=PERIOD), [2.0, 2.1, 5.0])
        # the Drake switch: one flagged tick applies the same rule
        switch = FallbackSwitch(fallback="coast", nominal_speed=4.0, period=PERIOD,
                                resume_acceleration=1.0)
        simulator = Simulator(switch)
        context = simulator.get_mutable_context()
        switch.get_steering_angle_input_port().FixValue(context, [0.1])
        switch.get_anomaly_input_port().FixValue(context, [1.0])
        simulator.AdvanceTo(PERIOD)
        assert switch.get_speed_output_port().Eval(context)[0] == 2.0
    assert STRATEGIES == ("slow_down", "brake")
    with pytest.raises(ValueError, match="strategy must be one of \\('slow_down', 'brake'\\)"):
        Fallback("coast", resume_acceleration=1.0)
    with pytest.raises(argparse.ArgumentTypeError, match="fallback 'coast'"):
        _fallback("coast")


def _margin_labels(inputs: LabelInputs) -> Labelled:
    """A source labelling by the BRT with a 1 m margin: ``V(x) <= 1``."""
    states = np.asarray(inputs.states, float)
    values = inputs.values_at(states)
    n = len(states)
    return Labelled(states, values, (values <= 1.0).astype(np.uint8),
                    np.full(n, SOURCE_BRT, np.uint8), {"source": "margin"},
                    np.full(n, NO_RUN, np.int64))


MARGIN = LabelSource(name="margin", label=_margin_labels, text="V(x) <= 1 m",
                     verdicts=lambda record, band, values, failed: np.asarray(values) <= 1.0)


def _no_loop(*_):
    raise AssertionError("the margin source runs no real loop")


def _inputs(spec, states, run_loop=_no_loop, run_paths=_no_loop):
    return LabelInputs(states, spec, values_at=lambda x: x[:, 0] - 2.0,
                       not_failed=lambda x: x[:, 1] < 0.9, run_loop=run_loop,
                       run_paths=run_paths, inside=lambda x: x[:, 1] < 0.8)


def test_a_registered_label_source_labels_through_label_samples():
    from reachwatch.pipeline.evaluate_commands import label_source_name
    states = np.random.default_rng(3).uniform(0.0, 4.0, (12, 3))
    with pytest.raises(ValueError, match=re.escape("dataset.labels.source must be one of "
                                                   "('brt', 'rollout', 'hybrid', 'trajectory')")):
        LabelSpec(source="margin").validate()
    with LABEL_SOURCE_REGISTRY.registered(MARGIN):
        assert LABEL_SOURCES == ("brt", "rollout", "hybrid", "trajectory", "margin")
        spec = LabelSpec(source="margin").validate()
        assert not spec.reads_along and LabelSpec(source="margin", paths=2).reads_along
        assert label_source("margin").table_name == "margin"
        got = label_samples(_inputs(spec, states))
        np.testing.assert_array_equal(got.labels, states[:, 0] <= 3.0)
        assert got.info == {"source": "margin"} and (got.runs == NO_RUN).all()
        values = np.array([-1.0, 0.5, 2.0])
        np.testing.assert_array_equal(
            label_verdicts({"source": "margin"}, 2.0, values, [True, True, True]),
            [True, True, False])
        assert not labels_every_state_by_its_run({"source": "margin"})
        assert label_source_name("margin") == "margin"
    assert LABEL_SOURCES == ("brt", "rollout", "hybrid", "trajectory")
    with pytest.raises(ValueError, match="label source must be one of"):
        label_source("margin")


def test_the_built_in_sources_label_through_the_registry_as_before():
    """``label_samples`` gives what `assign_labels` and `trajectory_samples` give
    (the dataset builder's way before the registry), with fake loops: no rendering."""
    states = np.random.default_rng(4).uniform(0.0, 4.0, (40, 3))
    values = states[:, 0] - 2.0
    calls = []

    def run_loop(x):
        calls.append(len(x))
        return x[:, 2] > 2.0, 7 * len(x)

    def run_paths(starts):
        n = len(starts)
        paths = starts[:, None, :] + 0.05 * np.arange(3)[None, :, None]
        label = (np.arange(n)[:, None] + np.arange(3)[None]) % 3 - 1
        return {"failed": starts[:, 2] > 2.0, "path_state": paths, "path_label": label,
                "ticks": np.full(n, 5)}

    for source, extra in (("brt", {}), ("rollout", {"max_rollouts": 9}),
                          ("hybrid", {"audit": 5}),
                          ("hybrid", {"audit": 40, "distrusted": "trajectory",
                                      "distrusted_starts": 6}),
                          ("trajectory", {"max_rollouts": 8})):
        spec = LabelSpec(source=source, **extra).validate()
        got = label_samples(_inputs(spec, states, run_loop, run_paths))
        if source == "trajectory" or got.info.get("labelled_by") == "trajectory":
            first = states if source == "trajectory" else states[:6]
            want_states, labels, sources, info, runs = trajectory_samples(
                first, spec, run_paths, lambda x: x[:, 1] < 0.8)
            want = (want_states, want_states[:, 0] - 2.0, labels, sources, runs)
            assert SOURCE_PATH in got.sources and (got.runs != NO_RUN).all()
        else:
            n, labels, sources, info = assign_labels(
                values, states[:, 1] < 0.9, spec, lambda index: run_loop(states[index]))
            want = (states[:n], values[:n], labels, sources, np.full(n, NO_RUN))
            assert (source == "brt") == (SOURCE_ROLLOUT not in got.sources)
        for a, b in zip((got.states, got.values, got.labels, got.sources, got.runs), want):
            np.testing.assert_array_equal(a, b, err_msg=f"{source} {extra}")
    assert calls          # the fake loop ran: the rollout sources used it
