"""Control periods that do not divide the horizon or the rollouts' step: the real loop
simulates the last part of a period (a failure there counts, as in the BRT), and the
table rollouts take any period (1/30 s, 0.025 s)."""

import re

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold

from reachwatch.diagrams import simulate
from reachwatch.diagrams.closed_loop import export_loop_ports
from reachwatch.reach import Grid, min_target_along_rollouts
from reachwatch.reach.rollouts import rollout_steps
from test_reach_nd import DoubleIntegrator          # p' = v, v' = u; target 1 - |p|


class _Drift(LeafSystem):
    """p' = u, its state exported."""

    def __init__(self):
        super().__init__()
        self.DeclareContinuousState(1)
        self._u = self.DeclareVectorInputPort("u", 1)
        self.DeclareVectorOutputPort("state", 1, lambda context, out: out.SetFromVector(
            context.get_continuous_state_vector().CopyToVector()))

    def DoCalcTimeDerivatives(self, context, derivatives):
        derivatives.get_mutable_vector().SetFromVector(self._u.Eval(context))


def _drift_loop(speed, hold=None, offset=0.0, plant=None):
    """``speed`` into the drift (or ``plant``), held by a zero-order hold of period
    ``hold`` (from ``offset``) if given."""
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem("plant", plant or _Drift())
    source = builder.AddNamedSystem("controller", ConstantVectorSource([speed]))
    if hold is None:
        builder.Connect(source.get_output_port(), plant.get_input_port(0))
    else:
        held = builder.AddNamedSystem("hold", ZeroOrderHold(hold, 1, offset))
        builder.Connect(source.get_output_port(), held.get_input_port())
        builder.Connect(held.get_output_port(), plant.get_input_port(0))
    export_loop_ports(builder, state=plant.GetOutputPort("state"))
    return builder.Build()


def test_a_failure_after_the_last_tick_counts():
    """Period 0.3 s over 1 s: ticks at 0, 0.3, 0.6 and 0.9 s; the loop crosses 0.95 at
    0.95 s, after the last tick, and the run fails then (at the integrator's step that
    finds it)."""
    run = simulate(_drift_loop(1.0), initial_state=[0.0], duration=1.0, period=0.3,
                   failed=lambda x: np.asarray(x)[:, 0] >= 0.95)
    assert np.allclose(run.time, [0.0, 0.3, 0.6, 0.9])
    assert run.failed and 0.9 < run.failure_time <= 1.0
    safe = simulate(_drift_loop(1.0), initial_state=[0.0], duration=1.0, period=0.3,
                    failed=lambda x: np.asarray(x)[:, 0] >= 1.5)
    assert not safe.failed and np.allclose(safe.time, [0.0, 0.3, 0.6, 0.9])


@pytest.mark.parametrize("horizon, hold, samples", [
    (1.0, 0.025, 40), (1.0, 1 / 30, 30), (1.0, 0.3, 4), (1.0, 0.07, 15), (0.505, None, 0)])
def test_rollout_steps_cover_the_horizon_and_sample_on_ticks(horizon, hold, samples):
    steps = rollout_steps(horizon, 0.01, hold)
    sizes = np.array([size for size, _ in steps])
    starts = np.concatenate([[0.0], np.cumsum(sizes)[:-1]])
    sampled = starts[[sample for _, sample in steps]]
    assert sizes.sum() == pytest.approx(horizon, abs=1e-12) and sizes.max() <= 0.01 + 1e-12
    assert len(sampled) == samples
    if hold is not None:
        assert np.allclose(sampled, np.arange(samples) * hold, atol=1e-9)


def test_rollout_steps_of_dt_where_the_period_allows():
    """Where the horizon and the period are whole numbers of ``dt`` the steps are ``dt``
    itself, as they always were (the same figures, bit for bit)."""
    assert rollout_steps(8.0, 0.01, 0.05) == [(0.01, k % 5 == 0) for k in range(800)]
    assert rollout_steps(2.0, 0.01) == [(0.01, False)] * 200


def test_table_rollouts_take_a_period_that_is_no_multiple_of_their_step():
    """A constant control of 1 from rest: p(t) = t^2 / 2, which RK4 integrates exactly,
    so the lowest target over 1 s is 0.5 whatever the period."""
    grid = Grid(lo=[-2.0, -2.0], hi=[2.0, 2.0], shape=[5, 5], names=("p", "v"))
    table = np.ones(grid.shape)
    for hold in (1 / 30, 0.025, None):
        lowest = min_target_along_rollouts(grid, DoubleIntegrator(), table, [[0.0, 0.0]], horizon=1.0,
                                           hold=hold)
        assert lowest[0] == pytest.approx(0.5, abs=1e-12)


NAN_LOOP = """
import sys
sys.path.insert(0, {tests!r})
from test_control_periods import _drift_loop
from reachwatch.diagrams import simulate
for hold, duration in ((None, 0.2), (0.05, 0.2), (0.05, 0.03)):
    try:            # the last: shorter than a period, all of it after the only tick
        simulate(_drift_loop(float("nan"), hold), initial_state=[0.0], duration=duration,
                 period=0.05, failed=lambda x: abs(x[:, 0]) > 10)
    except ValueError as e:
        print("refused:", e)
"""


def test_a_controller_that_outputs_nan_is_refused_not_stepped_forever():
    """A NaN command into a plant that does not check its inputs: Drake's
    error-controlled integrator would take zero-length steps forever; the run stops at
    the tick with one line instead. (In a process of its own, so that a regression
    fails in a minute rather than hanging the suite.)"""
    import subprocess
    import sys
    from pathlib import Path
    done = subprocess.run([sys.executable, "-c", NAN_LOOP.format(tests=str(Path(__file__).parent))],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    feedthrough, held, short = done.stdout.splitlines()
    assert feedthrough == ("refused: the loop: its system 'plant' gives the state derivative "
                           "[nan] at t = 0.000 s (state [0]), not finite: its input 'u' is "
                           "[nan]: does the controller output NaN or inf there?")
    for line in (held, short):
        assert line.startswith("refused: the loop: its hold 'hold' would take [nan] at "
                               "t = 0.000 s, not finite")


class _Root(_Drift):
    """p' = u + sqrt(0.3 - p): finite from a finite command until p passes 0.3."""

    def DoCalcTimeDerivatives(self, context, derivatives):
        p = context.get_continuous_state_vector().GetAtIndex(0)
        derivatives.get_mutable_vector().SetFromVector([self._u.Eval(context)[0]
                                                        + np.sqrt(0.3 - p)])


def _root_loop():
    diagram = _drift_loop(1.0, 0.05, plant=_Root())
    diagram.set_name("root")
    return diagram


ROOT_LOOP = """
import gc, sys, weakref
sys.path.insert(0, {tests!r})
from test_control_periods import _root_loop
from reachwatch.diagrams import simulate
loop = _root_loop()
try:
    simulate(loop, initial_state=[0.0], duration=1.0, period=0.05,
             failed=lambda x: abs(x[:, 0]) > 10)
except ValueError as e:
    print("refused:", e)
plant = weakref.ref(loop.GetSubsystemByName("plant"))
del loop
gc.collect()
print("freed:", plant() is None)
"""


def test_a_plant_whose_own_derivative_turns_nan_between_ticks_is_refused_not_stepped_forever():
    """A finite command into a plant whose derivative turns NaN past a state, between
    two control ticks (where the tick's check cannot see it): Drake's integrator would
    step forever at that time; the run stops there with one line naming the loop, the
    system, the time and the state, and the checked plant is freed with its loop. (In a
    process of its own, so that a regression fails in a minute rather than hanging.)"""
    import subprocess
    import sys
    from pathlib import Path
    done = subprocess.run([sys.executable, "-c", ROOT_LOOP.format(tests=str(Path(__file__).parent))],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    refused, freed = done.stdout.splitlines()
    assert re.fullmatch(r"refused: the loop 'root': its system 'plant' gives the state "
                        r"derivative \[nan\] at every trial step of the integrator from "
                        r"t = 0\.2\d+ s \(state \[0\.3\]\), not finite, from finite "
                        r"inputs: raise a ValueError of the plant's own in its "
                        r"DoCalcTimeDerivatives where its state or inputs leave what it can "
                        r"integrate", refused), refused
    assert freed == "freed: True"


class _Settle(LeafSystem):
    """p' = -1000 (p - 0.5), NaN below p = 0.4999 (a root of p - 0.4999, times 0): the
    run settles at 0.5 from 1, and a long trial step of the integrator overshoots into
    the NaN, which Drake throws away and tries shorter."""

    def __init__(self):
        super().__init__()
        self.DeclareContinuousState(1)
        self.DeclareVectorOutputPort("state", 1, lambda context, out: out.SetFromVector(
            context.get_continuous_state_vector().CopyToVector()))
        self.not_finite = 0

    def DoCalcTimeDerivatives(self, context, derivatives):
        p = context.get_continuous_state_vector().GetAtIndex(0)
        with np.errstate(invalid="ignore"):
            d = -1000.0 * (p - 0.5) + 0.0 * np.sqrt(p - 0.4999)
        self.not_finite += not np.isfinite(d)
        derivatives.get_mutable_vector().SetFromVector(np.array([d]))


def test_nan_trial_steps_the_integrator_gets_past_run_as_drake_runs_them():
    """The check counts a non-finite derivative against the run only where the
    integrator cannot get past it: a stiff plant whose long trial steps land in NaN,
    thrown away and tried shorter, runs to its end as Drake alone runs it, bit for bit."""
    from pydrake.systems.analysis import Simulator

    def loop():
        builder = DiagramBuilder()
        plant = builder.AddNamedSystem("plant", _Settle())
        export_loop_ports(builder, state=plant.GetOutputPort("state"))
        return builder.Build(), plant

    alone, plant = loop()
    simulator = Simulator(alone)
    simulator.get_mutable_context().SetContinuousState([1.0])
    simulator.Initialize()
    for tick in range(1, 21):                        # as `simulate` steps: tick by tick
        simulator.AdvanceTo(tick * 0.05)
    assert plant.not_finite > 10                     # Drake met NaN, and went on
    checked, plant = loop()
    run = simulate(checked, initial_state=[1.0], duration=1.0, period=0.05)
    assert plant.not_finite > 10 and len(run.time) == 21
    assert run.state[-1, 0] == simulator.get_context().get_continuous_state_vector()[0]


def test_a_loop_holding_at_another_period_than_the_control_period_is_refused():
    """A loop whose holds latch every 0.1 s run at a control period of 0.05 s: the tables
    and BRT take 0.05 s, the loop acts every 0.1 s; refused in one line, not judged at
    a period it does not run at. A loop without holds, or with one at the period, runs."""
    with pytest.raises(ValueError, match=r"^the loop '.*' holds its commands every 0.1 s, and "
                                         r"the control period \(scenario.controller.period\) "
                                         r"is 0.05 s"):
        simulate(_drift_loop(1.0, hold=0.1), initial_state=[0.0], duration=0.5, period=0.05)
    simulate(_drift_loop(1.0, hold=0.05), initial_state=[0.0], duration=0.5, period=0.05)
    simulate(_drift_loop(1.0), initial_state=[0.0], duration=0.5, period=0.05)
    with pytest.raises(ValueError, match=r"holds its commands every 0.05 s from 0.01 s, and the "
                                         r"control period .* is 0.05 s from 0 s"):
        simulate(_drift_loop(1.0, hold=0.05, offset=0.01), initial_state=[0.0],
                 duration=0.5, period=0.05)
    # a hold of images at another period (a discrete camera's) is no command hold
    from pydrake.common.value import AbstractValue
    from pydrake.systems.sensors import ImageRgba8U
    from pydrake.systems.primitives import ConstantValueSource

    def with_image_hold(hold, images):
        builder = DiagramBuilder()
        loop = builder.AddSystem(_drift_loop(1.0, hold=hold))
        frames = builder.AddSystem(ZeroOrderHold(images, AbstractValue.Make(ImageRgba8U())))
        camera = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(4, 4))))
        builder.Connect(camera.get_output_port(), frames.get_input_port())
        export_loop_ports(builder, state=loop.GetOutputPort("state"))
        return builder.Build()
    simulate(with_image_hold(0.05, 0.1), initial_state=[0.0], duration=0.5, period=0.05)
    simulate(with_image_hold(None, 0.1), initial_state=[0.0], duration=0.5, period=0.05)
    with pytest.raises(ValueError, match=r"holds its commands every 0.1 s"):  # all the same
        simulate(with_image_hold(0.1, 0.05), initial_state=[0.0], duration=0.5, period=0.05)
