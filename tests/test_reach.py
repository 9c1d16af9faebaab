import concurrent.futures as cf
import functools
import re

import numpy as np
import pytest
import torch

from reachwatch.diagrams import (ESTIMATE_PORT, load_scenario, make_closed_loop_diagram,
                                 make_state_feedback_diagram, save_checkpoint, load_taxinet)
from reachwatch.reach.interpolate import GridInterpolator
from reachwatch.reach import (Grid, InlineExecutor, Probe, ValueFunction,
                              min_target_along_rollouts, sign_agreement, solve_brt, sweep)
from reachwatch.reach import Unfingerprintable, sweep_key
from reachwatch.taxi import TaxiDynamics, TaxiGridSpec, paper_grid, taxi_probe, taxi_sweep_key
from reachwatch.systems import PreprocessConfig, TaxiNet, TaxiNetConfig, build_taxinet

B = 10.0
FEEDBACK = Probe(plant="taxi_plant", control_port="p_controller.steering_angle",
                 extra_ports=("state_estimator.estimate",))


def _feedback_factory():
    return functools.partial(make_state_feedback_diagram, load_scenario(data=""))


# --- grid -------------------------------------------------------------------------

def test_paper_grid_preset():
    g = paper_grid(10.0)
    assert g.shape == (101, 101, 101)
    np.testing.assert_allclose(g.lo, [-11.0, 100.0, np.deg2rad(-28)])
    np.testing.assert_allclose(g.hi, [11.0, 250.0, np.deg2rad(28)])
    assert TaxiGridSpec().to_grid() == g


@pytest.mark.parametrize("kwargs, match", [
    (dict(lo=[1, 0, 0], hi=[0, 1, 1], shape=[3, 3, 3], names="abc"), "axis a: lower bound"),
    (dict(lo=[0, 0, 0], hi=[1, 1, np.inf], shape=[3, 3, 3]), "axis x2"),
    (dict(lo=[0, 0, 0], hi=[1, 1, 1], shape=[3, 1, 3]), "axis x1: needs at least 2"),
    (dict(lo=[0, 0], hi=[1, 1], shape=[3, 3, 3]), "as many lower bounds"),
])
def test_bad_grids_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Grid(**kwargs)


def test_interpolation_exact_for_linear_and_outside_named():
    g = Grid(lo=[-1, 0, -0.5], hi=[1, 2, 0.5], shape=[5, 4, 3], names=("px", "py", "theta"))
    px, py, th = g.mesh()
    values = 2 * px - 3 * py + 5 * th + 1
    x = np.array([[0.3, 1.1, 0.2], [-0.95, 1.99, -0.49]])
    np.testing.assert_allclose(g.interpolate(values, x), 2 * x[:, 0] - 3 * x[:, 1] + 5 * x[:, 2] + 1)
    with pytest.raises(ValueError, match="px=2, py=1, theta=0.*outside the grid"):
        g.interpolate(values, [2.0, 1.0, 0.0])
    assert np.isnan(g.interpolate(values, [[2.0, 1.0, 0.0]], outside="nan")[0])


# --- solver ------------------------------------------------------------------------

@pytest.mark.parametrize("accuracy", ["semi_lagrangian", "low", "high", "very_high"])
def test_constant_heading_brt_matches_analytic_within_a_cell(accuracy):
    """No steering: px(t) = px0 + v t sin(theta); V = min(B - |px0|, B - |px0 + vT sin theta|)."""
    T = 2.0
    g = paper_grid(B, (45, 5, 41))
    px, _, th = g.mesh()
    exact = np.minimum(B - np.abs(px), B - np.abs(px + 5.0 * T * np.sin(th)))
    vf = solve_brt(g, TaxiDynamics(half_width=B), np.zeros(g.shape), horizon=T,
                   accuracy=accuracy, device="cpu")
    wrong = (vf.values <= 0) != (exact <= 0)
    # every disagreement lies within one cell of the true boundary (|grad V| <= 1 + vT)
    cell = np.max(g.spacing * [1.0, 0.0, 5.0 * T])
    assert np.all(np.abs(exact[wrong]) <= cell)
    assert abs(vf.brt_fraction - np.mean(exact <= 0)) < 0.01
    inside = np.abs(px) < B - 1
    tol = 0.6 if accuracy == "semi_lagrangian" else 0.2
    assert np.abs(vf.values - exact)[inside & (exact > -1)].max() < tol


def _p_table(grid, bias_deg=0.0):
    px, _, th = grid.mesh()
    return np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th) + bias_deg)


@pytest.mark.parametrize("accuracy, hold", [("very_high", None), ("semi_lagrangian", 0.05)])
def test_solver_agrees_with_rollouts_small_grid(accuracy, hold):
    g = paper_grid(B, (31, 5, 31))
    dyn = TaxiDynamics(half_width=B)
    table = _p_table(g, bias_deg=6.0)           # a biased controller: a lopsided BRT
    vf = solve_brt(g, dyn, table, horizon=4.0, accuracy=accuracy, device="cpu")
    lowest = min_target_along_rollouts(g, dyn, table, g.states(), horizon=4.0, hold=hold)
    assert 0.05 < vf.brt_fraction < 0.6
    assert sign_agreement(vf.values.ravel(), lowest) > 0.97


def test_solver_input_errors():
    from reachwatch.reach.solver import check_controls
    g = paper_grid(B, (5, 5, 5))
    dyn = TaxiDynamics(half_width=B)
    with pytest.raises(ValueError, match="does not match grid"):
        solve_brt(g, dyn, np.zeros((5, 5, 4)))
    with pytest.raises(ValueError, match="accuracy"):
        solve_brt(g, dyn, np.zeros(g.shape), accuracy="ultra")
    # a NaN or infinite control, and one past the plant's limits (degrees for radians:
    # tan read 10 rad as another command), name how many states and the first
    table = np.zeros(g.shape)
    table[1, 2, 3], table[4, 4, 4] = np.inf, np.nan
    first = ", ".join(f"{n}={v:.4g}" for n, v in zip(g.names, g.states([1 * 25 + 2 * 5 + 3])[0]))
    with pytest.raises(ValueError, match=re.escape(
            f"the swept control is NaN or infinite at 2 of 125 grid states, the first "
            f"[{first}] (control [inf])")):
        solve_brt(g, dyn, table)
    table[1, 2, 3], table[4, 4, 4] = 10.0, -np.pi / 2
    with pytest.raises(ValueError, match=re.escape(
            f"outside the plant's controls (-1.5708 < u0 < 1.5708) at 2 of 125 grid states, "
            f"the first [{first}] (control [10.0])")):
        solve_brt(g, dyn, table)
    with pytest.raises(ValueError, match=r"^KSFO_21h_clear: controller.steering_angle: the "
                                         r"swept control is outside"):
        check_controls(g, dyn, table, where="KSFO_21h_clear: controller.steering_angle")
    with pytest.raises(ValueError, match=r"^KSFO_21h_clear: controller.steering_angle: the "):
        solve_brt(g, dyn, table, where="KSFO_21h_clear: controller.steering_angle")
    table[1, 2, 3], table[4, 4, 4] = 1.5, -1.5
    solve_brt(g, dyn, table, horizon=0.2, device="cpu")     # within: solved

    class TwoControls(TaxiDynamics):                        # a limit for each component
        def control_limits(self):
            return [-1.0], [1.0]
    with pytest.raises(ValueError, match="TwoControls.control_limits gives 1 and 1 bounds "
                                         "for 2 control components"):
        check_controls(g, TwoControls(half_width=B), np.zeros(g.shape + (2,)))


def test_value_function_round_trip_and_queries(tmp_path):
    g = paper_grid(B, (9, 3, 9))
    vf = solve_brt(g, TaxiDynamics(half_width=B), _p_table(g), horizon=1.0, device="cpu")
    path = vf.save(tmp_path / "v.npz")
    back = ValueFunction.load(path)
    np.testing.assert_allclose(back.values, vf.values, atol=1e-6)
    assert back.grid == g and back.in_brt([[10.5, 150.0, 0.0]])[0]
    assert not back.in_brt([[0.0, 150.0, 0.0]])[0]
    (tmp_path / "bad.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="not a readable value function"):
        ValueFunction.load(tmp_path / "bad.npz")


# --- sweep -------------------------------------------------------------------------

def test_the_brt_share_of_a_narrower_box_counts_its_own_nodes():
    """The share solved on a widened grid is not the paper box's: counted over the box's
    own nodes, read off the solution; a node beyond the grid solved on counts as in it."""
    grid = Grid(lo=[0.0], hi=[10.0], shape=[11])
    vf = ValueFunction(grid, grid.axes[0] - 5.0, 1.0, "test")       # in the BRT: x <= 5
    assert vf.brt_fraction == pytest.approx(6 / 11)
    assert vf.brt_fraction_of(Grid(lo=[5.0], hi=[10.0], shape=[6])) == pytest.approx(1 / 6)
    assert vf.brt_fraction_of(Grid(lo=[6.0], hi=[12.0], shape=[4])) == pytest.approx(1 / 4)


def test_sweep_of_a_user_diagram_matches_the_controller(tmp_path):
    g = paper_grid(B, (5, 3, 4))
    table = sweep(_feedback_factory(), g, key="feedback", cache_dir=tmp_path, probe=FEEDBACK,
                  chunk_size=7, executor=InlineExecutor(), progress=False)
    px, _, th = g.mesh()
    np.testing.assert_allclose(table[FEEDBACK.control_port][..., 0], _p_table(g),
                               atol=1e-12)
    np.testing.assert_allclose(table["state_estimator.estimate"][..., 1], np.rad2deg(th))


class _Interrupted(cf.Executor):
    """Runs ``limit`` chunks, then fails like a killed worker."""

    def __init__(self, limit):
        self.limit = limit

    def submit(self, fn, *args):
        future = cf.Future()
        if self.limit > 0:
            self.limit -= 1
            future.set_result(fn(*args))
        else:
            future.set_exception(RuntimeError("worker killed"))
        return future


def test_sweep_resumes_after_interruption(tmp_path):
    g = paper_grid(B, (6, 3, 5))
    kwargs = dict(key="k", probe=FEEDBACK, chunk_size=8, progress=False)
    with pytest.raises(RuntimeError, match="killed"):
        sweep(_feedback_factory(), g, cache_dir=tmp_path / "a",
              executor=_Interrupted(3), **kwargs)
    done = sorted((tmp_path / "a" / "k").glob("chunk_*.npz"))
    assert len(done) == 3
    (tmp_path / "a" / "k" / "chunk_000001.npz").write_bytes(b"truncated")   # a torn write
    calls = []

    class Counting(InlineExecutor):
        def submit(self, fn, *args):
            calls.append(args[4])
            return super().submit(fn, *args)

    resumed = sweep(_feedback_factory(), g, cache_dir=tmp_path / "a", executor=Counting(),
                    **kwargs)
    assert len(calls) == int(np.ceil(g.size / 8)) - 2       # only missing/corrupt chunks
    clean = sweep(_feedback_factory(), g, cache_dir=tmp_path / "b", executor=InlineExecutor(),
                  **kwargs)
    for port in FEEDBACK.ports:
        assert np.array_equal(resumed[port], clean[port])
    calls.clear()
    sweep(_feedback_factory(), g, cache_dir=tmp_path / "a", executor=Counting(), **kwargs)
    assert calls == []                                       # repeated sweep costs nothing


def test_a_sweep_asked_for_another_chunk_size_goes_on_in_the_caches(tmp_path):
    """A table does not depend on its chunking: a sweep of a cache filled in chunks of 8
    asked for chunks of 5 reads them (and resumes a missing one in 8), where it would
    have taken every file for damaged and computed the whole table again."""
    g = paper_grid(B, (6, 3, 5))
    kwargs = dict(key="k", probe=FEEDBACK, progress=False)
    first = sweep(_feedback_factory(), g, cache_dir=tmp_path, executor=InlineExecutor(),
                  chunk_size=8, **kwargs)
    (tmp_path / "k" / "chunk_000002.npz").unlink()
    calls = []

    class Counting(InlineExecutor):
        def submit(self, fn, *args):
            calls.append((args[4], args[5]))
            return super().submit(fn, *args)
    again = sweep(_feedback_factory(), g, cache_dir=tmp_path, executor=Counting(),
                  chunk_size=5, **kwargs)
    assert calls == [(16, 24)]
    for port in FEEDBACK.ports:
        assert np.array_equal(again[port], first[port])
    # its first chunk lost: the next one says the size
    (tmp_path / "k" / "chunk_000000.npz").unlink()
    calls.clear()
    sweep(_feedback_factory(), g, cache_dir=tmp_path, executor=Counting(), chunk_size=5,
          **kwargs)
    assert calls == [(0, 8)]


def test_sweep_key_changes_with_checkpoint_grid_and_environment(tmp_path):
    torch.manual_seed(0)
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        paths.append(save_checkpoint(
            tmp_path / f"c{seed}.pt", kind="taxinet",
            model=build_taxinet(TaxiNetConfig(), PreprocessConfig()),
            model_config=TaxiNetConfig(), preprocess_config=PreprocessConfig(),
            metadata={"image_size": [200, 360]}))
    s0 = load_scenario(data=f"controller: {{checkpoint: {paths[0]}}}\n")
    s1 = load_scenario(data=f"controller: {{checkpoint: {paths[1]}}}\n")
    s2 = load_scenario(data=f"controller: {{checkpoint: {paths[0]}}}\n"
                            "environment: {hour: 17.0}\n")
    g = paper_grid(B, (5, 5, 5))
    s3 = load_scenario(data=f"controller: {{checkpoint: {paths[0]}, px_gain: -0.8}}\n")
    keys = {taxi_sweep_key(s0, g), taxi_sweep_key(s1, g), taxi_sweep_key(s2, g),
            taxi_sweep_key(s3, g), taxi_sweep_key(s0, paper_grid(B, (5, 5, 7)))}
    assert len(keys) == 5 and taxi_sweep_key(s0, g) == taxi_sweep_key(s0, g)
    # what the table does not depend on leaves the key alone
    s4 = load_scenario(data=f"controller: {{checkpoint: {paths[0]}}}\n"
                            "initial_state: {px: 3.0}\nduration: 2.0\n")
    assert taxi_sweep_key(s4, g) == taxi_sweep_key(s0, g)
    # the checkpoint counts by content: retrained in place changes it, moved keeps it
    moved = tmp_path / "moved.pt"
    moved.write_bytes(paths[0].read_bytes())
    s5 = load_scenario(data=f"controller: {{checkpoint: {moved}}}\n")
    assert taxi_sweep_key(s5, g) == taxi_sweep_key(s0, g)
    moved.write_bytes(paths[1].read_bytes())
    assert taxi_sweep_key(s5, g) == taxi_sweep_key(s1, g) != taxi_sweep_key(s0, g)


def _gain_factory(gain):
    scenario = load_scenario(data=f"controller: {{px_gain: {gain}}}\n")
    return functools.partial(make_state_feedback_diagram, scenario)


def test_a_user_key_is_checked_not_trusted(tmp_path):
    """Sweeping twice under one key with another gain used to return the first table."""
    g = paper_grid(B, (3, 2, 3))
    first = sweep(_gain_factory(-0.74), g, key="mine", cache_dir=tmp_path, probe=FEEDBACK,
                  executor=InlineExecutor(), progress=False)
    with pytest.raises(ValueError, match="sweep key 'mine' names a cache .* filled from another"):
        sweep(_gain_factory(-2.0), g, key="mine", cache_dir=tmp_path, probe=FEEDBACK,
              executor=InlineExecutor(), progress=False)
    derived = [sweep(_gain_factory(k), g, cache_dir=tmp_path, probe=FEEDBACK,
                     executor=InlineExecutor(), progress=False) for k in (-0.74, -2.0)]
    assert derived[0].key != derived[1].key
    np.testing.assert_array_equal(derived[0][FEEDBACK.control_port],
                                  first[FEEDBACK.control_port])
    assert not np.array_equal(derived[0][FEEDBACK.control_port],
                              derived[1][FEEDBACK.control_port])
    # two sweeps given the key at once, both before either wrote fingerprint.json: the
    # second reads none of the first's chunks (each chunk carries its fingerprint)
    (tmp_path / "mine" / "fingerprint.json").unlink()
    other = sweep(_gain_factory(-2.0), g, key="mine", cache_dir=tmp_path, probe=FEEDBACK,
                  executor=InlineExecutor(), progress=False)
    np.testing.assert_array_equal(other[FEEDBACK.control_port],
                                  derived[1][FEEDBACK.control_port])
    gain = -0.74

    def closure():
        return _gain_factory(gain)()
    with pytest.raises(Unfingerprintable, match="closure"):
        sweep_key(closure, g, FEEDBACK)


def test_taxinet_sweep_equals_taxinet_on_rendered_image(tmp_path):
    """The sweep evaluates the same diagram the simulator runs."""
    scenario = load_scenario(data="")
    g = paper_grid(B, (2, 2, 2))
    table = sweep(functools.partial(make_closed_loop_diagram, scenario), g, probe=taxi_probe(scenario),
                  cache_dir=tmp_path, executor=InlineExecutor(), progress=False)
    from reachwatch.diagrams import StateRenderer
    model, pre, _ = load_taxinet()
    renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)
    images = np.stack([renderer.render(x) for x in g.states()])
    expected = TaxiNet(model=model, preprocess_config=pre).estimate(images)
    np.testing.assert_allclose(table[ESTIMATE_PORT].reshape(-1, 2), expected, atol=1e-4)


def test_sweep_on_dask_local_cluster(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    g = paper_grid(B, (4, 3, 3))
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address="127.0.0.1:0") as cluster, \
            distributed.Client(cluster) as client:
        table = sweep(_feedback_factory(), g, key="dask", cache_dir=tmp_path, probe=FEEDBACK,
                      chunk_size=10, executor=client.get_executor(), progress=False)
    np.testing.assert_allclose(table[FEEDBACK.control_port][..., 0], _p_table(g),
                               atol=1e-12)


@pytest.mark.parametrize("scheme, order", [("weno5", 5), ("first_order", 1)])
def test_upwind_derivatives_converge_at_their_order(scheme, order):
    from reachwatch.reach.levelset import upwind_derivative
    errors = []
    for n in (41, 81):
        x = torch.linspace(0, 2, n, dtype=torch.float64)
        v = torch.sin(3 * x)
        for velocity in (1.0, -1.0):
            d = upwind_derivative(v, 0, float(x[1] - x[0]), torch.full_like(v, velocity), scheme)
            errors.append((d - 3 * torch.cos(3 * x)).abs()[3:-3].max().item())
    rate = np.log2(max(errors[:2]) / max(errors[2:]))
    assert rate > order - 0.5


# --- N-dimensional grids, strict queries, exact horizons -----------------------------

@pytest.mark.parametrize("shape", [(7, 5), (4, 3, 5, 3)])
def test_interpolation_exact_for_linear_in_2d_and_4d(shape):
    n = len(shape)
    g = Grid(lo=-np.arange(1, n + 1), hi=np.arange(1, n + 1) * 2.0, shape=shape)
    coeffs = np.arange(1, n + 1) * 0.5
    values = sum(c * m for c, m in zip(coeffs, g.mesh())) + 3.0
    x = np.random.default_rng(0).uniform(g.lo, g.hi, size=(20, n))
    np.testing.assert_allclose(g.interpolate(values, x), x @ coeffs + 3.0)
    interpolate = GridInterpolator(g, torch.as_tensor(x))
    np.testing.assert_allclose(interpolate(torch.as_tensor(values)).numpy(), x @ coeffs + 3.0)


def test_queries_reject_nan_states_and_unknown_modes():
    g = paper_grid(B, (5, 3, 5))
    values = np.ones(g.shape)
    for mode in ("raise", "clamp", "nan"):
        with pytest.raises(ValueError, match="not finite"):
            g.interpolate(values, [[np.nan, 150.0, 0.0]], outside=mode)
    with pytest.raises(ValueError, match="outside must be one of"):
        g.interpolate(values, [[0.0, 150.0, 0.0]], outside="extrapolate")


def test_in_brt_never_calls_an_unknown_state_safe():
    g = paper_grid(B, (9, 3, 9))
    vf = solve_brt(g, TaxiDynamics(half_width=B), _p_table(g), horizon=1.0, device="cpu")
    past_edge = [[B + 5.0, 150.0, 0.0]]                 # 5 m off the runway: a failure
    steep = [[0.0, 150.0, np.deg2rad(60.0)]]            # on the runway, outside the box
    for mode in ("raise", "clamp", "unsafe"):
        assert vf.in_brt(past_edge, outside=mode)[0]
        with pytest.raises(ValueError, match="not finite"):
            vf.in_brt([[np.nan, 150.0, 0.0]], outside=mode)
    with pytest.raises(ValueError, match="outside the grid.*not a known failure"):
        vf.in_brt(steep)
    assert vf.in_brt(steep, outside="unsafe")[0]
    for mode in ("nan", "ignore"):
        with pytest.raises(ValueError, match="outside must be one of"):
            vf.in_brt(past_edge, outside=mode)
    # in the box, in_brt is the interpolated sign
    x = g.states()[::7]
    np.testing.assert_array_equal(vf.in_brt(x), vf.at(x) <= 0)


def test_horizon_is_solved_exactly_and_recorded():
    g = paper_grid(B, (41, 3, 41))
    dyn = TaxiDynamics(half_width=B)
    px, _, th = g.mesh()
    brts = {}
    for T in (0.3, 0.4, 0.33):
        vf = solve_brt(g, dyn, np.zeros(g.shape), horizon=T, device="cpu")
        assert vf.horizon == T and vf.metadata["solved_horizon"] == T
        end = px + 5.0 * T * np.sin(th)
        exact = np.minimum(B - np.abs(px), B - np.abs(end))
        stays = np.abs(end) <= B + 1                 # straight lines that stay in the box: exact
        np.testing.assert_allclose(vf.values[stays], exact[stays], atol=1e-4)
        brts[T] = vf
    assert brts[0.3].metadata["periods"] == 6 and brts[0.3].metadata["tail"] == 0
    assert brts[0.33].metadata["periods"] == 6 and abs(brts[0.33].metadata["tail"] - 0.03) < 1e-9
    assert not np.array_equal(brts[0.3].values, brts[0.4].values)


@pytest.mark.parametrize("kwargs, match", [
    (dict(horizon=np.inf), "horizon must be a finite"), (dict(horizon=0), "horizon"),
    (dict(period=-0.05), "period must be"), (dict(period=0), "period must be"),
    (dict(cfl=0, accuracy="low"), "cfl must be"), (dict(cfl=1.5, accuracy="low"), "cfl must be"),
    (dict(periods_per_step=0), "periods_per_step must be"),
    (dict(periods_per_step=1.5), "periods_per_step must be a finite whole"),
])
def test_solver_parameters_are_checked(kwargs, match):
    g = paper_grid(B, (5, 3, 5))
    with pytest.raises(ValueError, match=match):
        solve_brt(g, TaxiDynamics(half_width=B), np.zeros(g.shape), device="cpu", **kwargs)


def test_a_cache_filled_under_another_software_stack_is_not_reused(monkeypatch):
    """Fingerprints (and so sweep and real-loop cache keys) carry the versions of
    reachwatch, drake (its renderer), torch, torchvision, numpy, scipy and OpenCV."""
    import sys

    from reachwatch.reach.outcomes import outcomes_key
    fp = sys.modules["reachwatch.reach.fingerprint"]      # the module (the package exports
    # a function of the same name)
    assert set(fp.STACK) == {"reachwatch", "drake", "torch", "torchvision", "numpy", "scipy",
                             "opencv"} and fp.STACK["drake"] and fp.STACK["opencv"]
    grid = Grid(lo=[0.0, 0.0], hi=[1.0, 1.0], shape=[3, 3])
    probe = Probe(plant="plant", control_port="controller.u")
    factory = functools.partial(dict, a=1)
    rollout = functools.partial(dict, b=2)
    before = (fp.fingerprint(factory), sweep_key(factory, grid, probe),
              outcomes_key(rollout, np.zeros((2, 2))))
    monkeypatch.setattr(fp, "STACK", {**fp.STACK, "drake": "0.0.0"})
    after = (fp.fingerprint(factory), sweep_key(factory, grid, probe),
             outcomes_key(rollout, np.zeros((2, 2))))
    assert all(a != b for a, b in zip(before, after))


def test_an_edit_to_the_loops_code_is_another_key(monkeypatch):
    """Fingerprints carry the source of the packages every loop is built from: an edit
    to the switch, a monitor or the plant (not the factory's own module) changes sweep
    and real-loop keys."""
    import sys

    from reachwatch.reach.fingerprint import modules_source_digest
    from reachwatch.reach.outcomes import outcomes_key
    fp = sys.modules["reachwatch.reach.fingerprint"]
    for module in ("reachwatch.systems.switch", "reachwatch.systems.history_monitor",
                   "reachwatch.systems.flag_filter", "reachwatch.diagrams.guarded",
                   "reachwatch.reach.loop_runs", "reachwatch.taxi.fidelity"):
        assert module.rpartition(".")[0] in fp.LOOP_CODE
    assert fp.loop_code_digest() == modules_source_digest(*fp.LOOP_CODE)
    rollout = functools.partial(dict, b=2)
    before = (fp.fingerprint(rollout), outcomes_key(rollout, np.zeros((2, 2))))
    monkeypatch.setattr(fp, "loop_code_digest", lambda: "0" * 64)
    after = (fp.fingerprint(rollout), outcomes_key(rollout, np.zeros((2, 2))))
    assert all(a != b for a, b in zip(before, after))


def test_a_source_file_edited_under_a_running_process_is_refused_not_keyed(tmp_path,
                                                                           monkeypatch):
    """Keys carry a digest of the source on disk: a module this process imported whose
    file changed after the process started would key its results with code it does not
    run, so the digest is refused in one line, the cached loop digest too; a module not
    imported yet runs what is on disk and is digested as it is."""
    import importlib
    import os
    import sys
    import time

    fp = sys.modules["reachwatch.reach.fingerprint"]
    package = tmp_path / "edited_pkg"
    package.mkdir()
    for name, text in (("__init__.py", ""), ("imported.py", "X = 1\n"), ("later.py", "Y = 1\n")):
        (package / name).write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    now = time.time_ns()
    for name in ("__init__.py", "imported.py", "later.py"):       # written before the start
        os.utime(package / name, ns=(now - 100 * 10**9,) * 2)
    monkeypatch.setattr(fp, "PROCESS_START_NS", now - 50 * 10**9)
    monkeypatch.setattr(fp, "LOOP_CODE", ("edited_pkg",))
    monkeypatch.setattr(fp, "_FUTURE_DATED", {})
    fp._loop_code_digest.cache_clear()
    later = now - 10**9                                          # after the start, not ahead
    try:
        importlib.import_module("edited_pkg.imported")
        os.utime(package / "later.py", ns=(later, later))    # not imported: no refusal
        digest = fp.modules_source_digest("edited_pkg")
        assert fp.loop_code_digest() == digest
        os.utime(package / "imported.py", ns=(later, later))
        for make in (lambda: fp.modules_source_digest("edited_pkg"), fp.loop_code_digest):
            with pytest.raises(fp.SourceChanged, match=r"^edited_pkg\.imported \(.*imported\.py\) "
                               r"changed on disk after this process started.*start it again"):
                make()
        fp.check_source_unchanged("json")       # other names: edited_pkg not checked here
        # dated in the future (a clock ahead where it was written): taken as imported
        # when first seen, so a restart helps; a later change of its time is a change
        ahead = time.time_ns() + 3600 * 10**9
        os.utime(package / "imported.py", ns=(ahead, ahead))
        fp.check_source_unchanged("edited_pkg")
        with monkeypatch.context() as later_on:             # the clock passes its date
            later_on.setattr(fp.time, "time_ns", lambda: ahead + 60 * 10**9)
            fp.check_source_unchanged("edited_pkg")
        os.utime(package / "imported.py", ns=(ahead + 10**9, ahead + 10**9))
        with pytest.raises(fp.SourceChanged, match=r"^edited_pkg\.imported"):
            fp.check_source_unchanged("edited_pkg")
    finally:
        fp._loop_code_digest.cache_clear()
        for name in ("edited_pkg.imported", "edited_pkg"):
            sys.modules.pop(name, None)


def test_a_worker_must_share_all_of_reachwatchs_source_and_the_keys_versions(monkeypatch):
    """What a worker is compared on (`process_identity`) changes with an edit anywhere
    in reachwatch (the training modules a dataset's key carries, which a worker runs to
    render a dataset's chunks, as well as the loop's packages), and carries the versions
    the keys carry."""
    import sys

    from reachwatch.pipeline import executors
    from reachwatch.reach.fingerprint import modules_source_digest
    fp = sys.modules["reachwatch.reach.fingerprint"]
    before = executors.process_identity()
    assert before["versions"] == fp.STACK
    for edited in ("reachwatch.training.dataset_images", "reachwatch.systems.taxinet"):
        monkeypatch.setattr(fp, "modules_source_digest", lambda *names, edited=edited: (
            modules_source_digest(*names) + ("+" if edited.rpartition(".")[0] in names
                                             else "")))
        fp._library_code_digest.cache_clear()
        try:
            assert executors.process_identity()["code"] != before["code"], edited
        finally:
            monkeypatch.undo()
            fp._library_code_digest.cache_clear()
    assert executors.process_identity() == before


def test_editing_a_helper_beside_a_factory_changes_its_key(tmp_path, monkeypatch):
    """A factory's key covers the module that defines it: a helper it calls from the
    same module (not the factory's own lines) changes the key when edited."""
    import importlib
    import sys
    fp = sys.modules["reachwatch.reach.fingerprint"]
    monkeypatch.syspath_prepend(str(tmp_path))
    path = tmp_path / "helper_probe_module.py"
    keys = []
    for gain in (1.0, 2.0):
        path.write_text(f"def helper(x):\n    return {gain} * x\n\n\n"
                        f"def factory(x):\n    return helper(x)\n")
        sys.modules.pop("helper_probe_module", None)
        importlib.invalidate_caches()
        module = importlib.import_module("helper_probe_module")
        keys.append(fp.fingerprint(functools.partial(module.factory, 3.0)))
    sys.modules.pop("helper_probe_module", None)
    assert keys[0] != keys[1]


def test_a_module_source_digest_follows_every_file_of_a_package(tmp_path, monkeypatch):
    """`modules_source_digest`: a package stands for every file under its folder."""
    import importlib
    import sys
    import time
    from reachwatch.reach.fingerprint import modules_source_digest
    package = tmp_path / "digest_probe_package"
    (package / "inner").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "inner" / "helper.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    # the package's files were written in this process: as if it started after them
    monkeypatch.setattr(sys.modules["reachwatch.reach.fingerprint"], "PROCESS_START_NS",
                        time.time_ns() + 10**9)
    first = modules_source_digest("digest_probe_package")
    assert first == modules_source_digest("digest_probe_package")
    (package / "inner" / "helper.py").write_text("X = 2\n")
    assert modules_source_digest("digest_probe_package") != first
    sys.modules.pop("digest_probe_package", None)


def test_a_cache_filled_under_another_render_stack_is_not_reused(monkeypatch):
    """Fingerprints carry the render stack: the probe scene's pixels and the GL
    libraries that drew them (another driver may draw one scene otherwise)."""
    import sys

    from reachwatch.diagrams import render_stack as stack_module
    fp = sys.modules["reachwatch.reach.fingerprint"]
    stack = stack_module.render_stack()
    assert len(stack["probe"]) == 32 and stack == stack_module.render_stack()
    size = stack_module.PROBE_SIZE         # the probe draws something: lit, shaded shapes
    image = np.frombuffer(stack_module._probe_image(), np.uint8).reshape(size, size, 4)
    drawn = np.abs(image[..., :3].astype(int) - image[0, 0, :3]).sum(-1) > 30
    assert 0.05 < drawn.mean() < 0.95 and len(np.unique(image[drawn][:, :3], axis=0)) > 20
    factory = functools.partial(dict, a=1)
    before = fp.fingerprint(factory)
    assert before == fp.fingerprint(factory)
    for other in ({**stack, "probe": "0" * 32},
                  {**stack, "libraries": {"libnvidia-eglcore.so.550.54": "0" * 16}}):
        monkeypatch.setattr(stack_module, "render_stack", lambda other=other: other)
        assert fp.fingerprint(factory) != before


def test_the_render_stack_is_the_same_in_a_process_that_rendered_a_scene_first(tmp_path):
    """Keys must not depend on what a process rendered before its first fingerprint:
    a fresh process that renders the taxi's scene first finds this process's stack."""
    import json
    import subprocess
    import sys

    from reachwatch.diagrams import render_stack as stack_module
    script = ("import json\n"
              "from reachwatch.diagrams import StateRenderer, load_scenario\n"
              "from reachwatch.diagrams.render_stack import render_stack\n"
              "scenario = load_scenario(data='camera: {height: 24, width: 40}\\n')\n"
              "StateRenderer(environment=scenario.environment, camera=scenario.camera)"
              ".render([0.0, 100.0, 0.0])\n"
              "print(json.dumps(render_stack()))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout.splitlines()[-1]) == stack_module.render_stack()
