"""Solve time of the paper-size BRT (101^3 grid, 8 s) on a synthetic control table,
ours (torch) beside hj_reachability (JAX, accuracy very_high) on the same problem in
the same run, each with its sign agreement against RK4 rollouts.

The synthetic table is the P-controller on the true state plus a downtrack-periodic
steering error (a stand-in for perception errors): phi_deg = -0.74 px - 0.44 theta_deg
+ 6 sin(py / 15 m). hj_reachability is optional (``pip install 'reachwatch[bench]'``).

    python benchmarks/hjb.py [--shape 101 101 101] [--rollouts 20000]
"""

import argparse
import time

import numpy as np

from reachwatch.reach import min_target_along_rollouts, sign_agreement, solve_brt
from reachwatch.taxi import TaxiDynamics, paper_grid

B, HORIZON = 10.0, 8.0


def synthetic_table(grid):
    px, py, th = grid.mesh()
    return np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th) + 6.0 * np.sin(py / 15.0))


def solve_hj_reachability(grid, table, accuracy="very_high"):
    """The same closed-loop problem in hj_reachability, or None when not installed."""
    try:
        import hj_reachability as hj
        import jax.numpy as jnp
        from jax.scipy.ndimage import map_coordinates
    except ImportError:
        return None
    lo, spacing = jnp.asarray(grid.lo), jnp.asarray(grid.spacing)
    phi_table = jnp.asarray(table)

    class ClosedLoop(hj.dynamics.Dynamics):
        def __init__(self):
            super().__init__("max", "min", None, None)

        def field(self, state):
            coords = (state - lo) / spacing
            phi = map_coordinates(phi_table, [c[None] for c in coords], order=1, mode="nearest")[0]
            return jnp.array([5.0 * jnp.sin(state[2]), 5.0 * jnp.cos(state[2]), jnp.tan(phi)])

        def __call__(self, state, control, disturbance, time):
            return self.field(state)

        def optimal_control_and_disturbance(self, state, time, grad_value):
            return jnp.zeros(1), jnp.zeros(1)

        def hamiltonian(self, state, time, value, grad_value):
            return grad_value @ self.field(state)

        def partial_max_magnitudes(self, state, time, value, grad_value_box):
            return jnp.abs(self.field(state))

    hj_grid = hj.Grid.from_lattice_parameters_and_boundary_conditions(
        hj.sets.Box(jnp.asarray(grid.lo), jnp.asarray(grid.hi)), grid.shape)
    target = B - jnp.abs(hj_grid.states[..., 0])
    settings = hj.SolverSettings.with_accuracy(
        accuracy, value_postprocessor=lambda t, v: jnp.minimum(v, target))
    start = time.perf_counter()
    values = hj.solve(settings, ClosedLoop(), hj_grid, jnp.array([0.0, -HORIZON]), target,
                      progress_bar=False)[-1]
    values.block_until_ready()
    return np.asarray(values), time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", type=int, nargs=3, default=[101, 101, 101])
    parser.add_argument("--rollouts", type=int, default=20000,
                        help="random grid nodes integrated for the agreement figures")
    parser.add_argument("--skip-hj", action="store_true")
    args = parser.parse_args()
    grid = paper_grid(B, tuple(args.shape))
    table = synthetic_table(grid)
    dynamics = TaxiDynamics(half_width=B)
    nodes = np.random.default_rng(0).choice(grid.size, min(args.rollouts, grid.size),
                                            replace=False)
    starts = grid.states(nodes)
    truth = {"continuous": min_target_along_rollouts(grid, dynamics, table, starts,
                                                     horizon=HORIZON),
             "held 0.05 s": min_target_along_rollouts(grid, dynamics, table, starts,
                                                      horizon=HORIZON, hold=0.05)}
    print(f"HJB benchmark: grid {args.shape} ({grid.size} nodes), horizon {HORIZON:g} s, "
          f"agreement on {len(nodes)} random nodes vs RK4 rollouts (dt 0.01 s) with the "
          f"control continuous / held for 0.05 s")
    print(f"{'solver':<38} {'seconds':>8} {'BRT %':>7} {'agree cont.':>12} {'agree held':>11}")
    rows = []
    for accuracy in ("semi_lagrangian", "very_high"):
        start = time.perf_counter()
        vf = solve_brt(grid, dynamics, table, horizon=HORIZON, accuracy=accuracy, device="cpu")
        rows.append((f"reachwatch {accuracy} (torch cpu)", time.perf_counter() - start,
                     vf.values))
    if not args.skip_hj:
        result = solve_hj_reachability(grid, table)
        if result is None:
            print("(hj_reachability not installed: pip install 'reachwatch[bench]')")
        else:
            rows.append(("hj_reachability very_high (jax cpu)", result[1], result[0]))
    for name, seconds, values in rows:
        flat = values.reshape(-1)[nodes]
        print(f"{name:<38} {seconds:8.1f} {100 * np.mean(values <= 0):7.2f} "
              f"{100 * sign_agreement(flat, truth['continuous']):11.2f}% "
              f"{100 * sign_agreement(flat, truth['held 0.05 s']):10.2f}%")
    # ratios of times measured in this run: very_high against semi_lagrangian always,
    # and hj_reachability against both where it ran
    print(f"semi_lagrangian is {rows[1][1] / rows[0][1]:.1f}x as fast as very_high")
    if len(rows) == 3:
        print(f"speed-up vs hj_reachability very_high: semi_lagrangian "
              f"{rows[2][1] / rows[0][1]:.1f}x, very_high {rows[2][1] / rows[1][1]:.1f}x")


if __name__ == "__main__":
    main()
