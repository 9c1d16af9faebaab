"""What the check of a loop's state derivatives costs (`reachwatch.diagrams.finite_derivatives`,
which `start_simulator` installs on every Python plant): ticks per second of the same
runs with the check and without it, in alternating rounds, on the cheapest loop (the
taxi on its true state: no camera) and on the TaxiNet loop at 64x128 (a render and
TaxiNet with random weights each tick). Prints the median ratio over rounds and its
range; 1.00 costs nothing.

    python benchmarks/derivative_check.py [--rounds 8] [--runs 3] [--duration 8]
"""

import argparse
import contextlib
import tempfile
import time
from unittest import mock

import numpy as np

from reachwatch.diagrams import (load_scenario, make_closed_loop_diagram,
                                 make_state_feedback_diagram, simulate)
from reachwatch.diagrams.finite_derivatives import DerivativeChecks

from closed_loop import checkpoint_for


def ticks_per_second(diagram, period, starts, duration, checked: bool) -> float:
    """Ticks a second of runs of ``diagram`` from ``starts``, with the check or without."""
    unchecked = mock.patch("reachwatch.diagrams.closed_loop.check_finite_derivatives",
                           lambda diagram: DerivativeChecks([]))
    context = diagram.CreateDefaultContext()
    with (contextlib.nullcontext() if checked else unchecked):
        start, ticks = time.perf_counter(), 0
        for x0 in starts:
            run = simulate(diagram, initial_state=x0, duration=duration, period=period,
                           context=context)
            ticks += len(run.time) - 1
    return ticks / (time.perf_counter() - start)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=8,
                        help="alternating rounds of both (the order swaps each round)")
    parser.add_argument("--runs", type=int, default=3, help="runs a round")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds a run")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    starts = [[rng.uniform(-2, 2), rng.uniform(100, 150), np.deg2rad(rng.uniform(-5, 5))]
              for _ in range(args.runs)]
    print(f"derivative check benchmark: KMWH 9h clear, {args.rounds} rounds of {args.runs} "
          f"runs of {args.duration:g} s, with the check and without in turn")
    print(f"{'loop':<28} {'ticks/s without':>16} {'with':>8} {'ratio':>6} {'range':>11}")
    with tempfile.TemporaryDirectory() as folder:
        scenario = load_scenario(data=(
            f"camera: {{width: 128, height: 64}}\n"
            f"controller: {{checkpoint: {checkpoint_for(64, 128, folder)}}}\n"))
        period = scenario.controller.period
        for name, diagram in (("true state (no camera)", make_state_feedback_diagram(scenario)),
                              ("TaxiNet at 64x128", make_closed_loop_diagram(scenario))):
            rates = {True: [], False: []}
            for r in range(args.rounds):
                for checked in ((True, False) if r % 2 else (False, True)):
                    rates[checked].append(ticks_per_second(diagram, period, starts,
                                                           args.duration, checked))
            ratios = np.array(rates[True]) / np.array(rates[False])
            print(f"{name:<28} {np.median(rates[False]):16.1f} {np.median(rates[True]):8.1f} "
                  f"{np.median(ratios):6.3f} {ratios.min():5.2f}-{ratios.max():.2f}")


if __name__ == "__main__":
    main()
