"""One fallback, one rule: a `Fallback` is read once from its name (the older steering
name ``taxinet`` too), and the Drake `FallbackSwitch` and the table rollouts of the
guarded loop (`taxi.taxi_guarded_rollouts`) apply the same speed and steering rules."""

import itertools
import re

import numpy as np
import pytest
import torch
from pydrake.systems.analysis import Simulator

from reachwatch.diagrams import load_scenario
from reachwatch.reach import Grid
from reachwatch.reach.dynamics import rk4_step
from reachwatch.reach.fingerprint import fingerprint
from reachwatch.reach.interpolate import GridInterpolator
from reachwatch.pipeline.keys import digest
from reachwatch.systems import STEERING, STRATEGIES, Fallback, FallbackSwitch, fallback_parts
from reachwatch.taxi import dynamics_for, taxi_guarded_rollouts

PERIOD = 0.05
OWN, TAKEN = 0.1, -0.2              # the controller's steering, the fallback's (rad)
MODES = list(itertools.product(STRATEGIES, STEERING))


def test_a_fallback_is_read_once_from_its_name():
    assert Fallback.parse("slow_down") == Fallback("slow_down", "controller")
    assert Fallback.parse("brake+dead_reckoning").steering == "dead_reckoning"
    for name in ("slow_down", "brake+oracle", "slow_down+dead_reckoning"):
        assert Fallback.parse(name).name == name
    # the older name of the controller's own steering reads as the same fallback
    assert (Fallback.parse("slow_down+taxinet") == Fallback.parse("slow_down+controller")
            == Fallback.parse("slow_down") == Fallback("slow_down", "taxinet"))
    assert fallback_parts("brake+taxinet") == ("brake", "controller")
    assert Fallback.parse("brake", brake_deceleration=4.0).brake_deceleration == 4.0
    for bad in ("stop", "slow_down+gps", "slow_down+"):
        with pytest.raises(ValueError, match=re.escape(f"fallback '{bad}': write a speed")):
            Fallback.parse(bad)
    with pytest.raises(ValueError, match="brake_deceleration must be a number > 0"):
        Fallback.parse("brake", brake_deceleration=0.0)
    with pytest.raises(ValueError, match="steering must be one of"):
        FallbackSwitch(nominal_speed=5.0, steering="gps")


def test_the_older_steering_name_keeps_the_run_files_keys():
    """A run file's ``monitor.steering: controller`` and ``taxinet`` (and the default)
    are one setting: the same fallback, the same stored field, the same cache keys."""
    monitors = [load_scenario(data=text).monitor for text in (
        "", "monitor: {steering: taxinet}\n", "monitor: {steering: controller}\n")]
    assert {m.steering for m in monitors} == {"taxinet"}
    assert {m.fallback for m in monitors} == {Fallback("slow_down", "controller")}
    assert len({fingerprint(m) for m in monitors}) == 1
    assert len({digest(m) for m in monitors}) == 1
    reckoned = monitors[0].with_fallback("brake+dead_reckoning")
    assert (reckoned.strategy, reckoned.steering) == ("brake", "dead_reckoning")
    assert monitors[0].with_fallback(reckoned.fallback).with_fallback("slow_down") == monitors[0]
    with pytest.raises(ValueError, match="monitor.steering must be one of"):
        load_scenario(data="monitor: {steering: gps}\n")



def test_the_guard_names_each_fallback_once_whatever_its_steering_is_called():
    """``guard.strategies`` spelled with ``+controller``, ``+taxinet`` or the strategy
    alone is one fallback: one name in the run spec (so one stage key, one report row,
    one set of real runs), and two spellings of it in one list are refused."""
    from tiny_run import TINY
    from reachwatch.diagrams import ScenarioError
    from reachwatch.pipeline.spec import load_run_spec
    spell = lambda names: load_run_spec(data=TINY.replace(  # noqa: E731
        "guard: {candidates: 2", f"guard: {{strategies: [{names}], candidates: 2"))
    specs = [spell(names) for names in ("slow_down, brake+dead_reckoning",
                                        "slow_down+controller, brake+dead_reckoning",
                                        "slow_down+taxinet, brake+dead_reckoning")]
    assert {tuple(s.guard.strategies) for s in specs} == {("slow_down", "brake+dead_reckoning")}
    assert len({digest(s.guard) for s in specs}) == 1
    with pytest.raises(ScenarioError, match="guard.strategies: each fallback once"):
        spell("slow_down, slow_down+controller")

def _switch_ticks(fallback, flags, nominal=5.0):
    """The FallbackSwitch alone, its inputs fixed per tick: the steering it applies at
    each tick and the speed it applies over that tick."""
    switch = FallbackSwitch(fallback=fallback, nominal_speed=nominal, period=PERIOD)
    simulator = Simulator(switch)
    context = simulator.get_mutable_context()
    switch.get_steering_angle_input_port().FixValue(context, [OWN])
    switch.get_fallback_steering_angle_input_port().FixValue(context, [TAKEN])
    steering, speed = [], []
    for k, flag in enumerate(flags):
        switch.get_anomaly_input_port().FixValue(context, [float(flag)])
        if k == 0:
            simulator.Initialize()
        steering.append(switch.get_steering_angle_output_port().Eval(context)[0])
        simulator.AdvanceTo((k + 1) * PERIOD)        # the update at k * PERIOD reads `flag`
        speed.append(switch.get_speed_output_port().Eval(context)[0])
    return np.array(steering), np.array(speed)


@pytest.mark.parametrize("strategy,steering", MODES)
def test_the_switch_applies_the_fallback_rules_tick_by_tick(strategy, steering):
    """Flag sequences in; the Drake switch's steering and speed per tick equal the
    `Fallback` rules applied to all sequences at once, as arrays (the table rollouts'
    way)."""
    flags = np.array([[1, 1, 1, 0, 1, 1, 0, 0, 1, 1, 1, 1],
                      [0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 0, 1],
                      [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]], bool)
    for params in (dict(), dict(brake_deceleration=20.0, resume_acceleration=2.0)):
        fallback = Fallback(strategy, steering, **params)
        v, rows = np.full(len(flags), 5.0), []
        for column in flags.T:
            v = fallback.next_speed(v, column, nominal=5.0, period=PERIOD)
            rows.append((fallback.steering_angle(column, np.full(len(flags), OWN),
                                                 np.full(len(flags), TAKEN)), v))
        for i, sequence in enumerate(flags):
            got_steering, got_speed = _switch_ticks(fallback, sequence)
            np.testing.assert_allclose(got_speed, [r[1][i] for r in rows], atol=1e-12)
            np.testing.assert_allclose(got_steering, [r[0][i] for r in rows], atol=1e-12)
            expected = np.where(sequence & (steering != "controller"), TAKEN, OWN)
            np.testing.assert_allclose(got_steering, expected)
        assert min(r[1][0] for r in rows) < 5.0 and rows[-1][1][2] == 5.0   # flags slow it


def _banded_tables():
    """A grid over (px, py, theta), a controller steering by px, and a detector whose
    score depends on py alone: flagged in bands 1.5 m long, clear between them."""
    grid = Grid(lo=[-10.0, 0.0, -1.0], hi=[10.0, 40.0, 1.0], shape=(5, 81, 3))
    nodes = grid.states()
    steer = np.where(nodes[:, 0] > 0, 0.3, -0.05).reshape(grid.shape)
    band = (np.round(nodes[:, 1] / 0.5).astype(int) // 3) % 2 == 0
    return grid, steer, band.astype(float).reshape(grid.shape)


def _drake_switch_loop(fallback, grid, dynamics, steer, score, starts, horizon, substeps=2):
    """The sampled-data loop from each start, with a Drake FallbackSwitch per start
    deciding: its inputs read from the tables at each tick (the fallback steering
    mode's angle: ``TAKEN``), the plant integrated as the table rollouts do, a start
    ending when it leaves the runway. Returns per start: failed, distance, flagged
    ticks, ticks, last speed."""
    n = len(starts)
    switches = [FallbackSwitch(fallback=fallback, nominal_speed=dynamics.speed, period=PERIOD)
                for _ in range(n)]
    simulators = [Simulator(switch) for switch in switches]
    contexts = [simulator.get_mutable_context() for simulator in simulators]
    for switch, context in zip(switches, contexts):
        switch.get_fallback_steering_angle_input_port().FixValue(context, [TAKEN])
    x = torch.as_tensor(np.asarray(starts, float)).clone()
    steer_t, score_t = torch.as_tensor(steer), torch.as_tensor(score)
    failed, alive = np.zeros(n, bool), np.ones(n, bool)
    distance, flagged_ticks, ticks, v = np.zeros(n), np.zeros(n, int), np.zeros(n, int), \
        np.full(n, dynamics.speed)
    for k in range(int(round(horizon / PERIOD))):
        rows = np.flatnonzero(alive)
        interpolate = GridInterpolator(grid, x[rows])
        flagged, own = interpolate(score_t).numpy() >= 0.5, interpolate(steer_t).numpy()
        u = np.zeros(len(rows))
        for j, i in enumerate(rows):
            switch, context = switches[i], contexts[i]
            switch.get_steering_angle_input_port().FixValue(context, [own[j]])
            switch.get_anomaly_input_port().FixValue(context, [float(flagged[j])])
            if k == 0:
                simulators[i].Initialize()
            u[j] = switch.get_steering_angle_output_port().Eval(context)[0]
            simulators[i].AdvanceTo((k + 1) * PERIOD)    # the update at k * PERIOD
            v[i] = switch.get_speed_output_port().Eval(context)[0]
        ticks[rows] += 1
        flagged_ticks[rows] += flagged
        distance[rows] += v[rows] * PERIOD
        u_t, v_t, y = torch.as_tensor(u)[:, None], torch.as_tensor(v[rows]), x[rows]
        for _ in range(substeps):
            y = rk4_step(lambda z: dynamics.vector_field(z, u_t, speed=v_t), y, PERIOD / substeps)
        x[rows] = y
        out = (dynamics.target(x) <= 0).numpy() & alive
        failed |= out
        alive &= ~out
    return failed, distance, flagged_ticks, ticks, v


def test_the_table_rollouts_apply_the_drake_switchs_rule():
    """Each strategy x steering mode: the table rollouts from a few starts equal a loop
    in which the Drake switch itself picks the speed and the steering at every tick
    (same tables, same integration): same failures, distance, flagged ticks and final
    speed. The steering mode decides which starts fail here, so a rollout that
    steered by another rule would not match."""
    dynamics = dynamics_for(load_scenario(data=""))
    grid, steer, score = _banded_tables()
    starts = np.array([[8.0, 2.0, 0.1], [-3.0, 5.0, 0.0], [9.0, 1.0, 0.0]])
    policy = lambda estimate: np.full(len(estimate), TAKEN)          # noqa: E731
    estimate = np.zeros(grid.shape + (2,))
    failures = {steering: 0 for steering in STEERING}
    for (strategy, steering), params in itertools.product(
            MODES, (dict(), dict(brake_deceleration=4.0, resume_acceleration=2.0))):
        fallback = Fallback(strategy, steering, **params)
        rolled = taxi_guarded_rollouts(grid, dynamics, steer, score, threshold=0.5, starts=starts,
                                  horizon=1.5, period=PERIOD, policy=policy,
                                  estimate_table=estimate, strategy=strategy,
                                  steering=steering, **params)
        failed, distance, flagged, ticks, v = _drake_switch_loop(
            fallback, grid, dynamics, steer, score, starts, 1.5)
        where = f"{fallback.name} {params}"
        np.testing.assert_array_equal(rolled.failed, failed, err_msg=where)
        np.testing.assert_array_equal(rolled.flagged_ticks, flagged, err_msg=where)
        np.testing.assert_array_equal(rolled.ticks, ticks, err_msg=where)
        np.testing.assert_allclose(rolled.distance, distance, rtol=0, atol=1e-9, err_msg=where)
        np.testing.assert_array_equal(rolled.stopped, ~failed & (v <= 0), err_msg=where)
        assert rolled.flagged_ticks.min() > 0 and (rolled.flagged_ticks < rolled.ticks).all()
        failures[steering] += int(rolled.failed.sum())
    # the controller steers off the runway near its edge; the fallback's steering, taking
    # over while flagged, keeps those starts on
    assert failures["controller"] > 0 and failures["dead_reckoning"] == failures["oracle"] == 0


def test_guard_fallbacks_flag_names_each_fallback_once():
    """``guard --fallbacks`` keeps a fallback's one name, as the run file does: before,
    ``slow_down+taxinet`` stayed as spelled and keyed its runs apart from ``slow_down``."""
    import argparse
    from reachwatch.pipeline.guard_commands import _fallback
    assert {_fallback(n) for n in ("slow_down", "slow_down+taxinet", "slow_down+controller")} \
        == {"slow_down"}
    assert _fallback("brake+dead_reckoning") == "brake+dead_reckoning"
    with pytest.raises(argparse.ArgumentTypeError, match="fallback 'brak'"):
        _fallback("brak")
