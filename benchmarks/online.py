"""Online rate: closed-loop control ticks per wall second of TaxiNet alone vs the
guarded loop (TaxiNet + a monitor + fallback switch), same run, same 200x360 camera.
The monitors are single-image anomaly detectors and monitors over the image history
(`HistoryMonitor`, 48x80 frames, as the monitor study trains them, and an ensemble of
them: ``monitor.ensemble``); they have random
weights unless --detector is given (timing does not depend on the weights) and never
trigger the fallback (threshold 1), so both loops drive the same path.

The VM's speed moves by ~10 % within a second, so the two loops run side by side from
the same start, advanced in alternating 0.5 s blocks (`reachwatch.diagrams.paired_rates`),
and the ratio is the median over rounds of guarded ticks/s over alone ticks/s. The
first row times TaxiNet alone against a second copy of itself: the method's noise floor
(its ratio should read 1.00; on this VM it reads 0.97-1.05).

    python benchmarks/online.py [--detector PATH [PATH ...]] [--monitors all|detector|history]
                                [--duration 4] [--rounds 15] [--ensemble 5] [--breakdown]
                                [--interleave] [--one-way] [--encoder-process]

``--interleave`` times the rows round by round (each round one start, every row's pair
in turn, the order reversed every other round) instead of row after row, so that a
drift of the machine's speed over minutes falls on every row alike; give one checkpoint
twice (two paths) to see how far two identical monitors read apart.

Each round times its pair twice, TaxiNet alone as the reference and then as the
candidate, and reports the two runs' mean rates; ``--one-way`` times it once, TaxiNet
alone the reference (half the time; the benchmark's way before 2026-12-07, whose noise
floor read 1.02-1.07 in runs of many rows where two copies of TaxiNet alone timed both
ways round read 1.00: docs/results/monitor/2026-12-07.md).

``--encoder-process`` adds, after each monitor's row, the same monitor with its frame
work in a process of its own (``monitor.encoder_process``: `FrameWorker`), begun when
the tick's frame is rendered, beside TaxiNet.

``--breakdown`` (with a history monitor's ``--detector``) splits the guarded loop's extra
cost: a row with the monitor's frame work (its resize and encoder) skipped, which leaves
the loop's machinery (the monitor's head, the switch, a k-of-n filter); then the frame
work's and TaxiNet's own milliseconds a tick inside the guarded loop beside the same
calls on the same frame outside it.
"""

import argparse
import contextlib
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import (load_scenario, make_closed_loop_diagram, make_guarded_diagram,
                                 paired_rates, save_checkpoint, start_simulator)
from reachwatch.diagrams.checkpoints import checkpoint_kind
from reachwatch.diagrams.finite_derivatives import leaf_systems
from reachwatch.systems import (MAX_MEMBERS, DetectorConfig, HistoryMonitor,
                                HistoryMonitorConfig, HistoryRiskEnsemble, HistoryRiskModel,
                                TaxiNet, build_detector)
from reachwatch.taxi.application import NEAR_CENTRELINE


@contextlib.contextmanager
def patched(cls, name, make):
    """``cls.name`` replaced by ``make(original)`` while diagrams are built in the block
    (a LeafSystem binds its calc methods when it declares its ports, so the systems
    built inside keep the replacement)."""
    original = getattr(cls, name)
    setattr(cls, name, make(original))
    try:
        yield
    finally:
        setattr(cls, name, original)


def skip_frame_work(original):
    """`HistoryMonitor`'s row calc writing zeros: no resize, no encoder."""
    return lambda self, context, row: row.SetFromVector(np.zeros(row.size()))


def timed_after_image(spent, key):
    """A calc method that evaluates its system's image input first, untimed (the render,
    when this system asks first), then times the original calc into ``spent[key]``."""
    def make(original):
        def calc(self, context, output):
            self.get_color_image_input_port().Eval(context)
            started = time.perf_counter()
            original(self, context, output)
            spent[key].append(time.perf_counter() - started)
        return calc
    return make


def breakdown(nominal, scenario, args):
    """The `--breakdown` rows: the machinery row, then the frame work's and TaxiNet's
    milliseconds a tick inside the guarded loop against the same calls outside it."""
    with patched(HistoryMonitor, "_calc_row", skip_frame_work):
        machinery = make_guarded_diagram(scenario)
    alone, guard = paired_rates(nominal, machinery, rounds=args.rounds, duration=args.duration,
                                period=0.05, starts=NEAR_CENTRELINE)
    ratio = guard / alone
    print(f"{'given, its frame work skipped':<38} {np.median(alone):10.1f} "
          f"{np.median(guard):12.1f} {np.median(1e3 / guard - 1e3 / alone):9.2f} "
          f"{np.median(ratio):6.2f} {ratio.min():5.2f}-{ratio.max():.2f}")
    spent = {"frame work": [], "TaxiNet": []}
    with patched(HistoryMonitor, "_calc_row", timed_after_image(spent, "frame work")), \
            patched(TaxiNet, "_calc_estimate", timed_after_image(spent, "TaxiNet")):
        timed = make_guarded_diagram(scenario)
    context = timed.CreateDefaultContext()
    paired_rates(nominal, timed, rounds=args.rounds, duration=args.duration, period=0.05,
                 starts=NEAR_CENTRELINE)
    inside = {key: 1e3 * np.median(values) for key, values in spent.items()}
    # outside the loop: each system alone, on a frame the camera rendered, 200 times
    simulator, _ = start_simulator(timed, initial_state=NEAR_CENTRELINE[0], context=context)
    simulator.AdvanceTo(1.0)
    outside = {}
    for system, key, port in [(s, k, p) for s in leaf_systems(timed)
                              for cls, k, p in ((HistoryMonitor, "frame work", "frame_features"),
                                                (TaxiNet, "TaxiNet", "estimate"))
                              if isinstance(s, cls)]:
        frame = system.get_color_image_input_port().Eval(system.GetMyContextFromRoot(context))
        own = system.CreateDefaultContext()
        fixed = system.get_color_image_input_port().FixValue(own, frame)
        signals = getattr(system, "get_signals_input_port", lambda: None)()
        if signals is not None:
            signals.FixValue(own, np.zeros(signals.size()))
        spent[key].clear()
        for _ in range(200):
            fixed.GetMutableData()                      # invalidates what reads the image
            system.GetOutputPort(port).Eval(own)
        outside[key] = 1e3 * np.median(spent[key])
    for key in inside:
        print(f"  {key} a tick: {inside[key]:.2f} ms in the guarded loop, "
              f"{outside[key]:.2f} ms outside it (the same frame, 200 times)")


def timed_rows(nominal, loops, args):
    """``[(alone, guarded)]`` rates of each of ``loops`` against ``nominal``
    (`paired_rates`), ``args.rounds`` rounds each: row after row, or with
    ``args.interleave`` round by round (every row's pair in turn, from the round's one
    start, the order reversed every other round). Each round times its pair both ways
    round, ``nominal`` as the reference and then as the candidate, and gives the two
    runs' mean rates; with ``args.one_way``, once, ``nominal`` the reference."""
    def pair(loop, starts, rounds):
        alone, guard = paired_rates(nominal, loop, rounds=rounds, duration=args.duration,
                                    period=0.05, starts=starts)
        if not args.one_way:
            guard_2, alone_2 = paired_rates(loop, nominal, rounds=rounds,
                                            duration=args.duration, period=0.05,
                                            starts=starts)
            alone, guard = (alone + alone_2) / 2, (guard + guard_2) / 2
        return alone, guard
    if not args.interleave:
        return [pair(loop, NEAR_CENTRELINE, args.rounds) for loop in loops]
    rates = [([], []) for _ in loops]
    for k in range(args.rounds):
        order = list(range(len(loops)))[::1 if k % 2 == 0 else -1]
        start = [NEAR_CENTRELINE[k % len(NEAR_CENTRELINE)]]
        for i in order:
            alone, guard = pair(loops[i], start, 1)
            rates[i][0].append(alone[0])
            rates[i][1].append(guard[0])
    return [(np.array(a), np.array(g)) for a, g in rates]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--detector", nargs="+", default=[],
                        help="trained detector or history-monitor checkpoints (a row each)")
    parser.add_argument("--monitors", choices=("all", "detector", "history"), default="all",
                        help="which untrained monitors to time (without --detector)")
    parser.add_argument("--duration", type=float, default=4.0, help="seconds simulated per round")
    parser.add_argument("--rounds", type=int, default=15, help="rounds (median ratio)")
    parser.add_argument("--ensemble", type=int, default=5,
                        help="members of the ensemble row (monitor.ensemble)")
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="torch.set_num_threads for the run (0: torch's default); a "
                             "history monitor runs its network on one thread whatever this says")
    parser.add_argument("--interleave", action="store_true",
                        help="time the rows round by round instead of row after row")
    parser.add_argument("--one-way", action="store_true",
                        help="time each pair once, TaxiNet alone the reference, instead of "
                             "both ways round (each loop as the reference in turn)")
    parser.add_argument("--encoder-process", action="store_true",
                        help="after each monitor's row, the same with its frame work in a "
                             "process of its own (monitor.encoder_process)")
    parser.add_argument("--breakdown", action="store_true",
                        help="with a history monitor's --detector: its frame work skipped, "
                             "and its and TaxiNet's cost inside and outside the loop")
    args = parser.parse_args()
    if args.breakdown and (len(args.detector) != 1 or
                           checkpoint_kind(args.detector[0]) != "history_monitor"):
        parser.error("--breakdown times a given history monitor: pass --detector with "
                     "one history monitor's checkpoint")
    if not 2 <= args.ensemble <= MAX_MEMBERS:
        parser.error(f"--ensemble takes 2 to {MAX_MEMBERS} members, got {args.ensemble}")
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    print(f"online benchmark: KMWH 9h clear, 200x360, {args.rounds} rounds of "
          f"{args.duration:g} s, both loops side by side in alternating 0.5 s blocks; "
          f"medians over rounds; {torch.get_num_threads()} torch threads, 1 in a history "
          f"monitor (paper: 33 Hz alone vs 25 Hz guarded)")
    print(f"{'detector':<38} {'alone /s':>10} {'guarded /s':>12} {'+ms/tick':>9} {'ratio':>6} "
          f"{'range':>9}")
    with tempfile.TemporaryDirectory() as folder:
        configs = ([("given", args.detector[0])] if len(args.detector) == 1 else
                   [(f"given {i + 1}: {Path(p).name}", p) for i, p in enumerate(args.detector)])
        for name, config in [] if args.monitors == "history" else [("small_cnn 96x160 (default)", DetectorConfig()),
                             ("small_cnn 96x160 stem_stride 2", DetectorConfig(stem_stride=2)),
                             ("small_cnn 48x80", DetectorConfig(height=48, width=80)),
                             ("efficientnet_b0 224x224 (paper)", DetectorConfig.paper())]:
            if args.detector:
                break
            torch.manual_seed(0)
            path = Path(folder) / (f"{config.arch}_{config.height}x{config.width}_"
                                   f"{config.stem_stride}.pt")
            save_checkpoint(path, kind="detector", model=build_detector(config),
                            model_config=config, preprocess_config=None,
                            metadata={"image_size": [200, 360], "threshold": 0.5})
            configs.append((name, path))
        one = HistoryMonitorConfig(frames=1)
        for name, config, members in [] if args.detector or args.monitors == "detector" else [
                ("history: single frame, 48x80", one, 1),
                (f"history: ensemble of {args.ensemble} single frames", one, args.ensemble),
                ("history: stacked 8 frames, 48x80", HistoryMonitorConfig(frames=8, stride=4), 1),
                ("history: GRU 16 + signals, 48x80", HistoryMonitorConfig(
                    frames=16, temporal="gru", signals=3), 1)]:
            torch.manual_seed(0)
            path = Path(folder) / f"history_{config.temporal}_{config.frames}_{members}.pt"
            models = [HistoryRiskModel(config).eval() for _ in range(members)]
            model = models[0] if members == 1 else HistoryRiskEnsemble.of(models)
            save_checkpoint(path, kind="history_monitor", model=model,
                            model_config=config, preprocess_config=None,
                            metadata={"calibration": [1.0, 0.0], "threshold": 0.5})
            configs.append((name, path))
        nominal = make_closed_loop_diagram(load_scenario(data=""))
        # First row: TaxiNet alone against a second copy of itself, the method's noise floor.
        candidates = [("TaxiNet alone again (noise floor)", None, False)]
        for name, path in configs:
            candidates.append((name, path, False))
            if args.encoder_process:
                candidates.append(("  the same, in its own process", path, True))
        loops = [(name, make_closed_loop_diagram(load_scenario(data="")) if path is None else
                  make_guarded_diagram(load_scenario(
                      data=f"monitor: {{detector: {path}, threshold: 1.0, "
                           f"encoder_process: {str(own).lower()}}}\n")))
                 for name, path, own in candidates]
        for _, loop in loops:           # the own processes ready before any round
            for system in leaf_systems(loop):
                worker = getattr(system, "frame_worker", None)
                if worker is not None and not worker.start(wait=300):
                    raise SystemExit(f"{system.get_name()}: its encoder's process did not start")
        for name, (alone, guard) in zip([n for n, _ in loops],
                                        timed_rows(nominal, [g for _, g in loops], args)):
            ratio = guard / alone
            extra_ms = float(np.median(1e3 / guard - 1e3 / alone))
            print(f"{name:<38} {np.median(alone):10.1f} {np.median(guard):12.1f} "
                  f"{extra_ms:9.2f} {np.median(ratio):6.2f} {ratio.min():5.2f}-{ratio.max():.2f}")
        if args.breakdown:
            breakdown(nominal, load_scenario(
                data=f"monitor: {{detector: {args.detector[0]}, threshold: 1.0}}\n"), args)


if __name__ == "__main__":
    main()
