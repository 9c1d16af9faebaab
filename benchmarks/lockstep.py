"""Control ticks per wall second of the rendered closed loop run one start at a time and
N starts in lockstep (reachwatch.diagrams.lockstep), against the wing camera rendering
the same frames alone, measured in the same run, with an identity check of the runs.

Every round times each mode once, in an order that rotates from round to round (a
shared VM's speed drifts): the camera alone (its colour port, one reused Context)
rendering the states the loop visits, the runs from every start one at a time
(`simulate` on one reused copy of the loop, as the real-loop rollouts did before lockstep), and
the same runs N at a time for each N. A tick is one rendered frame (one logged row of a
run), and a mode's rate counts every second of its runs, their starts included. Ratios
are to the render rate of the same round, and "x one" to the first one-at-a-time mode's
rate of the same round; the table gives medians and ranges over the rounds after a
warm-up round. With several ``--torch-threads`` each count is a mode of its own. Every
mode's runs are compared with the first one-at-a-time runs (time, state, estimate,
failure: equal, NaN equal to NaN).

``--engines-in-turn`` adds, for each N, N cameras (N render engines, as N copies of the
loop hold) rendering the same frames in turn: what rendering alone costs the way N runs
in lockstep render, without the loop.

``--controller-bound`` adds, for 1 and each N, N cameras rendering the same frames in
turn with TaxiNet's estimate after every N (on the first ``--torch-threads`` count),
TaxiNet reading the frames as the loops do (one: the camera's frame itself; N: the N
frames stacked into one batch, the network run on the batch as well): a loop's renders
and its controller without the Simulator, the ports and the plant. "/bound" is a
loop's rate over its bound's in the same round: near 1, the loop costs what its renders
and its controller cost; the bound's ratio to the render rate is then what the
controller leaves of the render rate. Not a strict ceiling: the modes run at different
moments of a drifting machine.

``--breakdown`` then times the parts of one more pass of each mode: the renders, TaxiNet
(preprocessing and network), the plant's derivatives (Python), the runs' starts, and
the rest (Drake's Simulator, port evaluation, the other Python systems, logging).

    python benchmarks/lockstep.py [--starts 8] [--duration 2] [--sizes 2 4 8]
                                  [--rounds 5] [--camera 200x360] [--torch-threads 0]
                                  [--breakdown] [--engines-in-turn] [--controller-bound]
"""

import argparse
import collections
import os
import tempfile
import time

import numpy as np
import torch

from reachwatch.diagrams import StateRenderer, load_scenario, make_closed_loop_diagram
from reachwatch.diagrams import closed_loop
from reachwatch.diagrams.lockstep import batch_systems, loop_copies, simulate_lockstep
from reachwatch.systems import TaxiNet, TaxiPlant
from reachwatch.taxi import OffRunway

from closed_loop import checkpoint_for   # the shipped or a seeded random TaxiNet

FIELDS = ("time", "state", "estimate", "failed", "failure_time")


def same_runs(a, b) -> bool:
    return all(np.array_equal(np.asarray(getattr(x, f)), np.asarray(getattr(y, f)),
                              equal_nan=True) for x, y in zip(a, b) for f in FIELDS)


class Parts:
    """Wall time per part while installed: wraps TaxiNet, the plant and run starts."""

    def __init__(self):
        self.spent = collections.Counter()
        self._saved = []

    def _wrap(self, owner, name, part):
        original = getattr(owner, name)
        spent = self.spent

        def timed(*args, **kwargs):
            started = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                spent[part] += time.perf_counter() - started
        self._saved.append((owner, name, original))
        setattr(owner, name, timed)

    def __enter__(self):
        self._wrap(TaxiNet, "_frame", "render")            # the first Eval of a tick renders
        self._wrap(TaxiNet, "estimate", "taxinet")
        self._wrap(TaxiNet, "prepare_batch", "taxinet batch")
        self._wrap(TaxiPlant, "DoCalcTimeDerivatives", "plant derivatives")
        self._wrap(closed_loop, "start_simulator", "run starts")
        return self

    def __exit__(self, *exc):
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)

    def per_tick(self, wall, ticks) -> dict:
        """ms per tick of each part; TaxiNet's batches without their renders."""
        s = dict(self.spent)
        taxinet = s.get("taxinet", 0.0) + s.get("taxinet batch", 0.0)
        if "taxinet batch" in s:
            taxinet -= s["render"]                    # prepare_batch's own renders
        parts = {"render": s.get("render", 0.0), "TaxiNet": taxinet,
                 "plant derivatives": s.get("plant derivatives", 0.0),
                 "run starts": s.get("run starts", 0.0)}
        parts["rest"] = wall - sum(parts.values())
        return {k: 1e3 * v / ticks for k, v in parts.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--starts", type=int, default=8, help="runs per mode and round")
    parser.add_argument("--duration", type=float, default=2.0, help="seconds per run")
    parser.add_argument("--sizes", type=int, nargs="+", default=[2, 4, 8],
                        help="runs in lockstep (N) to time beside one at a time")
    parser.add_argument("--rounds", type=int, default=5, help="measured rounds")
    parser.add_argument("--camera", default="200x360", help="HxW")
    parser.add_argument("--torch-threads", type=int, nargs="+", default=[0],
                        help="torch.set_num_threads for the loops, each count a mode of its own "
                             "(0: torch's default)")
    parser.add_argument("--breakdown", action="store_true",
                        help="also time the parts of one more pass of each mode")
    parser.add_argument("--engines-in-turn", action="store_true",
                        help="also time N cameras (render engines) rendering the same frames "
                             "in turn, frame i on camera i mod N, as N runs in lockstep do")
    parser.add_argument("--controller-bound", action="store_true",
                        help="also time the camera rendering the same frames with TaxiNet's "
                             "estimate after each: the ceiling of a loop's ratio")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    default_threads = torch.get_num_threads()
    threads = [t or default_threads for t in args.torch_threads]
    height, width = (int(v) for v in args.camera.lower().split("x"))
    rng = np.random.default_rng(args.seed)
    starts = np.column_stack([rng.uniform(-3, 3, args.starts), rng.uniform(100, 200, args.starts),
                              np.deg2rad(rng.uniform(-5, 5, args.starts))])
    with tempfile.TemporaryDirectory() as folder:
        scenario = load_scenario(data=(
            f"camera: {{width: {width}, height: {height}}}\n"
            f"controller: {{checkpoint: {checkpoint_for(height, width, folder)}}}\n"))
        B, period = scenario.environment.half_width, scenario.controller.period
        built = time.perf_counter()
        loops = loop_copies(lambda: make_closed_loop_diagram(scenario), max(args.sizes + [1]))
        built = time.perf_counter() - built
        renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)

        def runs(n, t=default_threads):
            torch.set_num_threads(t)
            return simulate_lockstep(loops[:n], initial_states=starts, duration=args.duration,
                                     period=period, failed=OffRunway(B))

        reference = runs(1)
        visited = np.concatenate([run.state for run in reference])
        ticks = len(visited)

        def render_alone():
            for x in visited:
                renderer.render(x)

        modes = {"render alone": render_alone}
        if args.engines_in_turn:
            cameras = [renderer] + [StateRenderer(environment=scenario.environment,
                                                  camera=scenario.camera)
                                    for _ in range(max(args.sizes) - 1)]

            def render_in_turn(n):
                for i, x in enumerate(visited):
                    cameras[i % n].render(x)

            modes.update({f"render, {n} in turn": (lambda n=n: render_in_turn(n))
                          for n in args.sizes})
        bounds = {}                   # a loop's mode -> the mode of its controller bound
        if args.controller_bound:
            taxinet = next(s for s in batch_systems(loops[0][0]) if isinstance(s, TaxiNet))
            frames = []                  # per camera: its plant's Context and its colour port
            for r in [renderer] + [StateRenderer(environment=scenario.environment,
                                                 camera=scenario.camera)
                                   for _ in range(max(args.sizes) - 1)]:
                context = r.diagram.CreateDefaultContext()
                frames.append((r.world.plant.GetMyMutableContextFromRoot(context),
                               r.world.camera.color_image_output_port(),
                               r.world.camera.GetMyContextFromRoot(context)))

            def render_then_controller(n):
                # as the loops feed TaxiNet: one at a time the camera's RGBA frame itself
                # (not `render`'s RGB copy, which the reference pays and a loop does not);
                # N at a time N cameras' frames, stacked into one batch (the loops'
                # `prepare_batch` batches the preprocessing alone and runs the network
                # frame by frame: here the network runs on the batch too)
                torch.set_num_threads(threads[0])
                for i in range(0, ticks, n):
                    views = []
                    for (plant, port, context), x in zip(frames, visited[i:i + n]):
                        plant.SetContinuousState(x)
                        views.append(port.Eval(context).data)
                    taxinet.estimate(views[0][None] if n == 1 else np.stack(views))

            for n in [1] + args.sizes:
                modes[f"render {n}, then TaxiNet"] = lambda n=n: render_then_controller(n)
            tag = "" if threads == [default_threads] else f", {threads[0]} thr"
            bounds[f"one at a time{tag}"] = "render 1, then TaxiNet"
            bounds.update({f"lockstep {n}{tag}": f"render {n}, then TaxiNet"
                           for n in args.sizes})
        for t in threads:
            tag = "" if threads == [default_threads] else f", {t} thr"
            modes[f"one at a time{tag}"] = lambda t=t: runs(1, t)
            modes.update({f"lockstep {n}{tag}": (lambda n=n, t=t: runs(n, t))
                          for n in args.sizes})
        print(f"lockstep benchmark: {scenario.environment.name}, {height}x{width}, "
              f"{args.starts} starts x {args.duration:g} s ({ticks} rendered ticks per mode), "
              f"{os.cpu_count()} CPUs, torch threads {threads} (default {default_threads}); "
              f"{len(loops)} copies of the loop built in {built:.1f} s; "
              f"{args.rounds} rounds after a warm-up, order rotating")
        names = list(modes)
        rates = {name: [] for name in names}
        identical = {name: True for name in names}
        for k in range(-1, args.rounds):                 # round -1: warm-up, not kept
            order = names[k % len(names):] + names[:k % len(names)] if k >= 0 else names
            for name in order:
                started = time.perf_counter()
                result = modes[name]()
                rate = ticks / (time.perf_counter() - started)
                if result is not None:
                    identical[name] &= same_runs(result, reference)
                if k >= 0:
                    rates[name].append(rate)
        render = np.array(rates["render alone"])
        print(f"{'mode':<22} {'ticks/s':>8} {'range':>13} {'/render':>8} {'range':>11} "
              f"{'x one':>6} " + (f"{'/bound':>6} " if args.controller_bound else "") +
              " identical")
        one = np.array(rates[next(n for n in names if n.startswith("one at a time"))])
        for name in names:
            r = np.array(rates[name])
            ratio, speedup = r / render, r / one
            print(f"{name:<22} {np.median(r):8.1f} {r.min():6.1f}-{r.max():<6.1f} "
                  f"{np.median(ratio):8.2f} {ratio.min():5.2f}-{ratio.max():<5.2f} "
                  f"{np.median(speedup):6.2f} " +
                  (f"{np.median(r / np.array(rates[bounds[name]])):6.2f} " if name in bounds
                   else f"{'':6} " if args.controller_bound else "") +
                  f" {'' if name.startswith('render') else identical[name]}")
        print(f"load average {os.getloadavg()[0]:.1f}")
        if args.breakdown:
            print("breakdown, ms per tick (one more pass of each mode):")
            for name in [n for n in names if not n.startswith("render")]:
                with Parts() as parts:
                    started = time.perf_counter()
                    modes[name]()
                    wall = time.perf_counter() - started
                split = parts.per_tick(wall, ticks)
                print(f"  {name:<22} {1e3 * wall / ticks:6.2f} = " + ", ".join(
                    f"{part} {ms:.2f}" for part, ms in split.items()))


if __name__ == "__main__":
    main()
