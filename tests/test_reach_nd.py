"""The generic reach layer on plants that are not the taxi: a 2-D double integrator
(swept as a Drake diagram) and a 4-D unicycle with speed as a state."""

import functools
import re

import numpy as np
import pytest
import torch
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem

from reachwatch.reach import (Dynamics, Grid, InlineExecutor, Probe, local_range, min_target_along_rollouts,
                              sign_agreement, solve_brt, sweep)

GAINS = (1.0, 0.6, 0.3)          # u = -k1 p - k2 v + bias: slightly unstable toward +p


class DoubleIntegrator(Dynamics):
    """p' = v, v' = u; failure |p| >= 1."""
    state_dim, control_dim = 2, 1

    def vector_field(self, x, u):
        return torch.stack([x[..., 1], u[..., 0]], dim=-1)

    def target(self, x):
        return 1.0 - x[..., 0].abs()

    def safe_box(self):
        return [-1.0, -np.inf], [1.0, np.inf]


class Unicycle(Dynamics):
    """x' = v cos th, y' = v sin th, th' = omega, v' = a; failure |y| >= 1 (a lane)."""
    state_dim, control_dim = 4, 2

    def vector_field(self, x, u):
        return torch.stack([x[..., 3] * torch.cos(x[..., 2]), x[..., 3] * torch.sin(x[..., 2]),
                            u[..., 0], u[..., 1]], dim=-1)

    def target(self, x):
        return 1.0 - x[..., 1].abs()


def test_dynamics_is_abstract():
    with pytest.raises(TypeError):
        Dynamics()


@pytest.mark.parametrize("accuracy, hold", [("semi_lagrangian", 0.05), ("high", None)])
def test_2d_brt_agrees_with_rollouts(accuracy, hold):
    g = Grid(lo=[-1.2, -2.0], hi=[1.2, 2.0], shape=[49, 41], names=("p", "v"))
    p, v = g.mesh()
    k1, k2, bias = GAINS
    table = -k1 * p - k2 * v + bias
    dyn = DoubleIntegrator()
    vf = solve_brt(g, dyn, table, horizon=3.0, accuracy=accuracy, device="cpu")
    lowest = min_target_along_rollouts(g, dyn, table, g.states(), horizon=3.0, hold=hold)
    assert 0.1 < vf.brt_fraction < 0.9
    assert sign_agreement(vf.values.ravel(), lowest) > 0.97
    assert vf.in_brt([[1.5, 0.0]])[0]                 # past the safe box: failure
    with pytest.raises(ValueError, match="p=0, v=5.*outside the grid"):
        vf.in_brt([[0.0, 5.0]])


def test_4d_brt_agrees_with_rollouts():
    g = Grid(lo=[0.0, -1.2, -0.8, 0.5], hi=[1.0, 1.2, 0.8, 1.5], shape=[2, 25, 17, 5],
             names=("x", "y", "th", "v"))
    _, y, th, v = g.mesh()
    table = np.stack([-1.2 * y - 1.0 * th + 0.5, -(v - 1.2)], axis=-1)   # biased steering
    dyn = Unicycle()
    vf = solve_brt(g, dyn, table, horizon=2.0, device="cpu")
    lowest = min_target_along_rollouts(g, dyn, table, g.states(), horizon=2.0, hold=0.05)
    assert 0.05 < vf.brt_fraction < 0.9
    assert sign_agreement(vf.values.ravel(), lowest) > 0.95


class _Plant(LeafSystem):
    """Double integrator as a Drake system: state [p, v], input u, output state."""

    def __init__(self):
        super().__init__()
        state = self.DeclareContinuousState(2)
        self.u = self.DeclareVectorInputPort("u", 1)
        self.DeclareStateOutputPort("state", state)

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector([x[1], self.u.Eval(context)[0]])


class _Controller(LeafSystem):
    def __init__(self, k1, k2, bias):
        super().__init__()
        self.gains = (k1, k2, bias)
        self.x = self.DeclareVectorInputPort("x", 2)
        self.DeclareVectorOutputPort("u", 1, self._calc)

    def _calc(self, context, output: BasicVector):
        p, v = self.x.Eval(context)
        k1, k2, bias = self.gains
        output.SetFromVector([-k1 * p - k2 * v + bias])


def make_double_integrator_loop(k1, k2, bias):
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem("plant", _Plant())
    controller = builder.AddNamedSystem("controller", _Controller(k1, k2, bias))
    builder.Connect(plant.get_output_port(), controller.get_input_port())
    builder.Connect(controller.get_output_port(), plant.get_input_port())
    return builder.Build()


def test_2d_sweep_of_a_drake_loop_matches_its_controller(tmp_path):
    g = Grid(lo=[-1.2, -2.0], hi=[1.2, 2.0], shape=[5, 4], names=("p", "v"))
    probe = Probe(plant="plant", control_port="controller.u")
    table = sweep(functools.partial(make_double_integrator_loop, *GAINS), g, probe=probe,
                  cache_dir=tmp_path, executor=InlineExecutor(), chunk_size=6, progress=False)
    p, v = g.mesh()
    k1, k2, bias = GAINS
    np.testing.assert_allclose(table["controller.u"][..., 0], -k1 * p - k2 * v + bias)
    assert table.key.startswith("make_double_integrator_loop_5x4_")
    with pytest.raises(ValueError, match="has 2 continuous states, the grid 3 axes"):
        sweep(functools.partial(make_double_integrator_loop, *GAINS),
              Grid(lo=[0, 0, 0], hi=[1, 1, 1], shape=[2, 2, 2]), probe=probe,
              cache_dir=tmp_path, executor=InlineExecutor(), progress=False)
    with pytest.raises(ValueError, match="subsystem 'controller' has no output port 'y'"):
        sweep(functools.partial(make_double_integrator_loop, *GAINS), g,
              probe=Probe(plant="plant", control_port="controller.y"), cache_dir=tmp_path,
              executor=InlineExecutor(), progress=False)


def test_leaving_the_box_is_clamped_or_a_failure_as_asked():
    """u = +1: v grows past the grid's v range within the horizon from v0 > 0. Clamped,
    that says nothing (p stays on the runway); with exit_fails on v it is a failure."""
    g = Grid(lo=[-1.2, -0.5], hi=[1.2, 0.5], shape=[25, 21], names=("p", "v"))
    table = np.ones(g.shape)
    clamped = solve_brt(g, DoubleIntegrator(), table, horizon=0.5, device="cpu")
    strict = solve_brt(g, DoubleIntegrator(), table, horizon=0.5, exit_fails=[1], device="cpu")
    inside, leaving = [0.0, -0.4], [0.0, 0.2]
    assert not clamped.in_brt([inside, leaving]).any()
    assert strict.in_brt([inside, leaving]).tolist() == [False, True]
    assert strict.metadata["exit_fails"] == [1]
    with pytest.raises(ValueError, match=r"exit_fails names axes \[2\]; the grid has axes 0..1"):
        solve_brt(g, DoubleIntegrator(), table, horizon=0.5, exit_fails=[2], device="cpu")
    with pytest.raises(ValueError, match="exit_fails needs accuracy 'semi_lagrangian'"):
        solve_brt(g, DoubleIntegrator(), table, horizon=0.5, exit_fails=[1], accuracy="low",
                  device="cpu")


class Integrator(Dynamics):
    """x' = u; failure |x| >= 1."""
    state_dim, control_dim = 1, 1

    def vector_field(self, x, u):
        return u

    def target(self, x):
        return 1.0 - x[..., 0].abs()


@pytest.mark.parametrize("periods_per_step", [1, 10])
def test_robust_brt_known_answer(periods_per_step):
    """Nominal output 0 (stand still), but anywhere in [-1, 1]: over 0.5 s the worst
    output carries every state 0.5 closer to the nearer edge, so V = 0.5 - |x| instead
    of 1 - |x|, whether the worst choice is held per period or per 0.5 s step."""
    g = Grid(lo=[-1.5], hi=[1.5], shape=[61], names=("x",))
    still = np.zeros(g.shape)
    kw = dict(horizon=0.5, period=0.05, periods_per_step=periods_per_step, device="cpu",
              dtype=torch.float64)
    nominal = solve_brt(g, Integrator(), still, **kw)
    robust = solve_brt(g, Integrator(), still, control_bounds=(still - 1, still + 1), **kw)
    x = g.states()[:, 0]
    inside = np.abs(x) <= 0.9 + 1e-9
    np.testing.assert_allclose(nominal.values[inside], 1 - np.abs(x[inside]), atol=1e-9)
    np.testing.assert_allclose(robust.values[inside], 0.5 - np.abs(x[inside]), atol=1e-9)
    assert robust.metadata["robust"] and not nominal.metadata["robust"]
    # bounds that hold only the table change nothing
    same = solve_brt(g, Integrator(), still, control_bounds=(still, still), **kw)
    np.testing.assert_array_equal(same.values, nominal.values)


def test_robust_brt_with_local_range_only_grows_the_brt_and_checks_its_bounds():
    g = Grid(lo=[-1.2, -2.0], hi=[1.2, 2.0], shape=[25, 21], names=("p", "v"))
    p, v = g.mesh()
    k1, k2, bias = GAINS
    table = -k1 * p - k2 * v + bias + 0.4 * np.sign(np.sin(7 * p))     # jumps between nodes
    lo, hi = local_range(g, table, min_spread=0.5)
    wide = (hi - lo) > 0
    assert 0 < wide.mean() < 1 and np.all(lo[~wide] == table[~wide])
    nominal = solve_brt(g, DoubleIntegrator(), table, horizon=2.0, device="cpu")
    robust = solve_brt(g, DoubleIntegrator(), table, horizon=2.0, device="cpu",
                       control_bounds=(lo, hi))
    assert np.all(robust.values <= nominal.values + 1e-6)
    assert robust.brt_fraction > nominal.brt_fraction
    with pytest.raises(ValueError, match="hi shaped"):
        solve_brt(g, DoubleIntegrator(), table, control_bounds=(lo, hi[:-1]))
    with pytest.raises(ValueError, match="2 entries lie outside"):
        bad = lo.copy()
        bad[0, :2] = table[0, :2] + 1
        solve_brt(g, DoubleIntegrator(), table, control_bounds=(bad, hi))
    with pytest.raises(ValueError, match="needs accuracy 'semi_lagrangian'"):
        solve_brt(g, DoubleIntegrator(), table, accuracy="low", control_bounds=(lo, hi))


def test_local_range_known_answer():
    g = Grid(lo=[0.0], hi=[4.0], shape=[5], names=("x",))
    table = np.array([0.0, 0.0, 1.0, 0.0, 0.0])
    lo, hi = local_range(g, table)
    np.testing.assert_array_equal(lo, [0, 0, 0, 0, 0])
    np.testing.assert_array_equal(hi, [0, 1, 1, 1, 0])
    # with a trailing component: a node counts as wide when any component is
    two = np.stack([table, [0.0, 0.0, 0.0, 0.0, 3.0]], axis=-1)
    lo, hi = local_range(g, two, min_spread=2.0)
    # nodes 3-4 are wide through the second component (3 > 2), so both components take
    # their range there; node 2 is narrow (spreads 1 and 0) and keeps the table
    np.testing.assert_array_equal(hi[:, 0], [0, 0, 1, 1, 0])
    np.testing.assert_array_equal(hi[:, 1], [0, 0, 0, 3, 3])
    np.testing.assert_array_equal(lo, np.stack([[0, 0, 1, 0, 0], [0] * 5], axis=-1))
    with pytest.raises(ValueError, match="does not match the grid"):
        local_range(g, table[:4])
    for size in (1, 2, 4):
        with pytest.raises(ValueError, match="size must be an odd whole number"):
            local_range(g, table, size=size)
    lo, hi = local_range(g, table, size=5)          # the whole 5-node grid from the middle
    np.testing.assert_array_equal(hi, [1, 1, 1, 1, 1])


class NanBeyond(DoubleIntegrator):
    """The double integrator whose target, or whose flow, is NaN past p = 0.5."""

    def __init__(self, part):
        self.part = part

    def vector_field(self, x, u):
        f = super().vector_field(x, u)
        if self.part == "flow":
            f = torch.where((x[..., :1] > 0.5), torch.full_like(f, float("nan")), f)
        return f

    def target(self, x):
        t = super().target(x)
        return torch.where(x[..., 0] > 0.5, torch.full_like(t, float("nan")), t) \
            if self.part == "target" else t


@pytest.mark.parametrize("part, what", [("target", "target"),
                                        ("flow", "vector_field (or target along the flow)")])
@pytest.mark.parametrize("accuracy", ["semi_lagrangian", "low"])
def test_a_plant_that_is_nan_somewhere_is_refused_naming_the_state(part, what, accuracy):
    """Before: a NaN target read as safe (V <= 0 is false), and a NaN foot point indexed
    the grid at INT64_MIN (an IndexError with a traceback)."""
    if accuracy == "low" and part == "flow":
        what = "vector_field"
    g = Grid(lo=[-1.0, -1.0], hi=[1.0, 1.0], shape=[9, 5], names=("p", "v"))
    with pytest.raises(ValueError, match=rf"KSFO: NanBeyond.{re.escape(what)} is NaN or "
                                         rf"infinite from \d+ of 45 grid states, the first "
                                         rf"\[p=0.\d+, v=-?[\d.]+\]: look at the plant"):
        solve_brt(g, NanBeyond(part), np.zeros(g.shape), horizon=0.2, accuracy=accuracy,
                  period=0.05, where="KSFO")
