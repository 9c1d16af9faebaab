"""Throughput on a Dask cluster: grid states per second of the closed-loop sweep and
real-loop runs per second, inline (this process) and on clusters of 1 and of 2
single-thread ``dask worker`` processes (each in its own temporary directory, so no
worker shares the driver's files), with speed-up and efficiency (rate_N / (N x
rate_1)) measured in the same run and whether every cluster's results are identical to
the inline ones; then the scheduling overhead at many simulated workers on 127.0.0.1:
tasks that sleep a stand-in render cost per state, submitted through
`reachwatch.reach.outcomes.map_states`, overhead = (wall - ideal) / wall with ideal =
total task time / workers.

The simulated workers are ``--sim-workers`` threads over ``--sim-processes`` ``dask
worker`` processes (default 32 over 4: every worker imports drake and torch when it
unpickles its first chunk, ~1 GB and ~2 s of CPU each, too much 32 times on a small
machine; ``--sim-processes 32`` gives 32 single-thread workers where it fits). Beside
`map_states` it times the same tasks through bare ``client.map`` (Dask alone: no
window, no cache), the same cost in smaller chunks, and zero-cost tasks (the task
rate the driver and scheduler sustain), each on a cluster whose scheduler has each of
``--sim-saturations`` as its worker-saturation (default 1.0, as the cluster guide starts
it, and Dask's default 1.1, which queues tasks on busy worker threads). Every other
cluster here is started at 1.0.

``--workers`` sets the clusters' sizes (default 1 and 2; on a machine with more cores,
e.g. ``--workers 1 2 4 8``). A last row runs 2 workers whose renderers (Mesa's llvmpipe) each take every core,
``LP_NUM_THREADS`` = the CPU count, as they did before the driver shared the cores out
among the workers of a host (`reach.sweep.render_threads`), and the ratio of the two
(``--no-all-core`` leaves it out, e.g. where the renderer is not llvmpipe).

The VM's speed drifts, so the executors take turns within each round (inline, 1
worker, 2 workers, all-core renders, then the next round) and each ratio is the median over rounds of
that round's ratio. A worker builds its diagram on its first chunk (seconds): round 0
is a warm-up that includes it, reported apart and left out of the medians. After each
round, two pure-Python processes spin side by side against one alone: the share of two
cores the machine gives right then (1.00 on an idle two-core machine), the ceiling of
the 2-worker efficiency. The scheduler and every worker bind to 127.0.0.1 and are
stopped on the way out.

With ``--together N`` it measures this alone instead: N environments' sweeps (grid
``--shape``, chunks ``--chunk``) on one pool (``--together-executor``, default
``local:2``), one after another (each a batch of chunks of its own, as the sweep and
fidelity stages ran before) and together (`reachwatch.reach.chunk_jobs.run_together`, as
they run now: every environment's chunks in one window), the two taking turns in each
round; it prints the median walls, the median per-round ratio of one after another to
together (above 1: together is faster) and whether every table is identical to the
first round's one-after-another ones.

    python benchmarks/scale.py [--shape 9 5 9] [--starts 32] [--duration 1]
                               [--rounds 3] [--workers 1 2] [--no-all-core] [--sim-workers 32] [--sim-processes 4]
                               [--sim-cost 0.05] [--sim-chunk 8] [--sim-tasks 8]
                               [--sim-saturations 1.0 1.1]
    python benchmarks/scale.py --together 4 [--together-executor local:2]
                               [--shape 9 5 9] [--chunk 0] [--rounds 3]
"""

import argparse
import contextlib
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import load_scenario
from reachwatch.diagrams.render_stack import render_stack
from reachwatch.pipeline.executors import (SATURATION, SATURATION_VARIABLE, make_executor,
                                           scheduler_saturation)
from reachwatch.reach import InlineExecutor
from reachwatch.reach.chunk_jobs import run_together
from reachwatch.reach.executors import executor_threads
from reachwatch.reach.outcomes import default_chunk_size, map_states
from reachwatch.taxi import on_runway_starts, paper_grid, sweep_closed_loop
from reachwatch.taxi.fidelity import real_outcomes

HOST = "127.0.0.1"
#: single-thread numerics in every worker (and inline, with --inline-threads 1)
SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def _stop(process, grace: float = 10.0):
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(grace)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@contextlib.contextmanager
def dask_cluster(root: Path, processes: int, threads: int = 1, timeout: float = 180.0,
                 env: dict = None):
    """A ``dask scheduler`` (worker-saturation `SATURATION` unless ``env`` says
    otherwise) and ``processes`` ``dask worker`` subprocesses of
    ``threads`` threads each (no nanny), all on 127.0.0.1, each worker with its own
    working and local directory under ``root``; yields ``(address, seconds to start)``
    and stops them all on the way out."""
    root.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    file = root / "scheduler.json"
    env = {**os.environ, **SINGLE_THREAD, SATURATION_VARIABLE: repr(SATURATION), **(env or {})}
    children = []
    try:
        log = open(root / "scheduler.log", "wb")
        children.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", HOST,
             "--port", "0", "--no-dashboard", "--scheduler-file", str(file)],
            cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT))
        address = None
        while address is None:
            if children[0].poll() is not None:
                raise RuntimeError(f"dask scheduler exited; see {root / 'scheduler.log'}")
            if time.perf_counter() - started > timeout:
                raise RuntimeError("dask scheduler did not start in time")
            try:
                address = json.loads(file.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.2)
        for i in range(processes):
            folder = root / f"worker{i}"
            folder.mkdir()
            children.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address, "--host", HOST,
                 "--nthreads", str(threads), "--no-nanny", "--no-dashboard",
                 "--memory-limit", "0", "--local-directory", str(folder), "--name", f"w{i}"],
                cwd=folder, env=env, stdout=open(folder / "worker.log", "wb"),
                stderr=subprocess.STDOUT))
        from dask.distributed import Client
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(processes, timeout=timeout)
        yield address, time.perf_counter() - started
    finally:
        for child in reversed(children):
            _stop(child)


SPIN = ("import time\nn, end = 0, time.perf_counter() + {s}\n"
        "while time.perf_counter() < end:\n    n += 1\nprint(n)")


def spin(processes: int, seconds: float = 1.0) -> float:
    """Loop iterations per second summed over ``processes`` pure-Python processes
    spinning at once: the CPU this machine gives that many, whatever else runs on it."""
    children = [subprocess.Popen([sys.executable, "-c", SPIN.format(s=seconds)],
                                 stdout=subprocess.PIPE, text=True) for _ in range(processes)]
    return sum(int(child.communicate()[0]) for child in children) / seconds


def same(a: dict, b: dict) -> bool:
    """Every array equal (NaN equal to NaN in float arrays)."""
    return a.keys() == b.keys() and all(
        np.array_equal(a[k], b[k], equal_nan=np.asarray(a[k]).dtype.kind == "f") for k in a)


def stand_in(cost: float, states) -> dict:
    """A chunk of a stand-in render cost: ``cost`` s per state, no CPU."""
    time.sleep(cost * len(states))
    return {"failed": np.zeros(len(states), bool), "sum": states.sum(axis=1)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", type=int, nargs=3, default=[9, 5, 9],
                        help="sweep grid shape (px, py, theta)")
    parser.add_argument("--chunk", type=int, default=0,
                        help="sweep chunk size in states (0: the grid split into 16 chunks)")
    parser.add_argument("--starts", type=int, default=32, help="real-loop starts per round")
    parser.add_argument("--duration", type=float, default=1.0, help="real-loop seconds per start")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds (medians), after a warm-up")
    parser.add_argument("--inline-threads", type=int, default=1,
                        help="torch threads of the inline runs (workers run 1; 0: torch's default)")
    parser.add_argument("--environment", default="runway: KMWH, hour: 9.0, sky: clear",
                        help="the environment block, YAML flow style without braces")
    parser.add_argument("--sim-workers", type=int, default=32,
                        help="simulated workers (worker threads) of the overhead measurement; 0: skip it")
    parser.add_argument("--sim-processes", type=int, default=4,
                        help="dask worker processes that hold them (--sim-workers 32 --sim-processes "
                             "32: 32 single-thread workers; each imports drake and torch)")
    parser.add_argument("--sim-cost", type=float, default=0.05, help="stand-in render cost, s per state")
    parser.add_argument("--sim-chunk", type=int, default=8, help="states per task")
    parser.add_argument("--sim-tasks", type=int, default=8, help="tasks per simulated worker")
    parser.add_argument("--sim-saturations", type=float, nargs="+", default=[1.0, 1.1],
                        help="the schedulers' worker-saturation, a cluster each (1.0: the "
                             "cluster guide's; 1.1: Dask's default)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                        help="the clusters' sizes in single-thread workers (1 must be among them: "
                             "efficiency is against it)")
    parser.add_argument("--no-all-core", action="store_true",
                        help="leave out the row of 2 workers whose renderers take every core")
    parser.add_argument("--skip-real", action="store_true",
                        help="only the overhead measurement")
    parser.add_argument("--together", type=int, default=0, metavar="N",
                        help="only this: N environments swept one after another vs together "
                             "on one pool, and the ratio (0: skip)")
    parser.add_argument("--together-executor", default="local:2",
                        help="the pool of --together (an --executor value: local:N, dask://...)")
    args = parser.parse_args()
    if args.together < 0 or (args.together and args.rounds < 1):
        parser.error("--together must be >= 0, and with it --rounds >= 1")
    if 1 not in args.workers or min(args.workers) < 1 or len(set(args.workers)) != len(args.workers):
        parser.error(f"--workers needs 1 and other distinct sizes >= 1, got {args.workers}")
    if args.sim_workers and args.sim_workers % args.sim_processes:
        parser.error("--sim-workers must be a multiple of --sim-processes")
    if args.inline_threads:
        torch.set_num_threads(args.inline_threads)
    with tempfile.TemporaryDirectory(prefix="scale_") as folder:
        root = Path(folder)
        if args.together:
            return together_ratio(args, root)
        if not args.skip_real:
            throughput(args, root)
        if args.sim_workers:
            overhead(args, root / "sim")


#: The row of two workers whose renderers each take every core (``LP_NUM_THREADS`` =
#: the CPU count), beside the default that shares the cores out; the width of the
#: table's first column.
ALL_CORE = "2 workers, all-core renders"
WIDTH = len(ALL_CORE)


def throughput(args, root: Path):
    scenario = load_scenario(data=f"environment: {{{args.environment}}}\n")
    B = scenario.environment.half_width
    grid = paper_grid(B, tuple(args.shape))
    chunk = args.chunk or -(-grid.size // 16)
    starts = on_runway_starts(grid, args.starts, 0, half_width=B)
    workers = {"inline": None}
    workers.update({f"{n} worker{'s' * (n > 1)}": n for n in sorted(args.workers)})
    if not args.no_all_core:
        workers[ALL_CORE] = 2
    names = list(workers)
    with contextlib.ExitStack() as stack:
        executors, start_s = {"inline": InlineExecutor()}, {}
        for name in names[1:]:
            # the last: workers whose renderer takes every core, as before the driver
            # shared them out (`reach.sweep.render_threads`)
            env = {"LP_NUM_THREADS": str(os.cpu_count())} if name == ALL_CORE else None
            address, start_s[name] = stack.enter_context(
                dask_cluster(root / name.replace(" ", "_").replace(",", ""), workers[name],
                             env=env))
            executor, close = make_executor(f"dask://{address.split('://', 1)[1]}")
            stack.callback(close)
            executors[name] = executor
        sweep_rate = {n: [] for n in names}
        loop_rate = {n: [] for n in names}
        identical = {n: True for n in names}
        results = {n: [] for n in names}
        ceiling = []
        for round_ in range(args.rounds + 1):          # round 0: warm-up, diagrams built
            turn = round_ % len(names)
            for name in names[turn:] + names[:turn]:   # each goes first in turn
                cache = root / "cache" / f"{names.index(name)}_{round_}"   # fresh each time
                t = time.perf_counter()
                table = sweep_closed_loop(scenario, grid, cache_dir=cache, chunk_size=chunk,
                                          executor=executors[name], progress=False)
                sweep_rate[name].append(grid.size / (time.perf_counter() - t))
                t = time.perf_counter()
                runs = real_outcomes(scenario, starts, grid=grid, duration=args.duration,
                                     cache_dir=cache, executor=executors[name], progress=False)
                loop_rate[name].append(len(starts) / (time.perf_counter() - t))
                tables = {p: table[p] for p in table.tables}
                results[name].append((tables, runs.fields))
            ceiling.append(spin(2) / (2 * spin(1)))
        for name in names:          # against inline's warm-up round
            first = results["inline"][0]
            identical[name] = all(same(t, first[0]) and same(f, first[1]) for t, f in results[name])
    ticks = int(results["inline"][0][1]["ticks"].sum())
    print(f"scale benchmark: {args.environment}, 200x360; sweep grid {args.shape} ({grid.size} "
          f"states, chunks of {chunk}); real loop {len(starts)} on-runway starts x "
          f"{args.duration:g} s ({ticks} rendered ticks, chunks of "
          f"{default_chunk_size(len(starts))}); {os.cpu_count()} CPUs, renderer "
          f"{', '.join(sorted(render_stack()['libraries'])) or 'unknown'}; "
          f"inline {torch.get_num_threads()} torch thread(s), workers 1 each; medians of "
          f"{args.rounds} interleaved rounds after a warm-up round")
    print("clusters started in: " + ", ".join(f"{n} {s:.1f} s" for n, s in start_s.items()))
    print(f"{'executor':<{WIDTH}} {'sweep st/s':>10} {'warm-up':>8} {'speedup':>8} {'effic.':>7}  "
          f"{'loop runs/s':>11} {'warm-up':>8} {'speedup':>8} {'effic.':>7}  identical")
    for name in names:
        cells = []
        for rates in (sweep_rate, loop_rate):
            timed = np.array(rates[name][1:])
            if workers[name]:
                ratio = np.median(timed / np.array(rates["1 worker"][1:]))
                base = np.median(timed / np.array(rates["inline"][1:]))
                eff = ratio / workers[name]
                cells.append(f"{np.median(timed):10.1f} {rates[name][0]:8.1f} {base:7.2f}x "
                             f"{eff:7.2f}")
            else:
                cells.append(f"{np.median(timed):10.1f} {rates[name][0]:8.1f} {'1.00x':>8} "
                             f"{'':>7}")
        print(f"{name:<{WIDTH}} {cells[0]}  {cells[1]}  {identical[name]}")
    for rates, what in ((sweep_rate, "sweep"), (loop_rate, "real loop")):
        if ALL_CORE not in rates or "2 workers" not in rates:
            break
        shared = np.median(np.array(rates["2 workers"][1:]) / np.array(rates[ALL_CORE][1:]))
        print(f"2 workers, render threads shared out / all-core renders ({what}): {shared:.2f}")
    print(f"machine ceiling: 2 spinning processes ran {np.median(ceiling[1:]):.2f} of twice one "
          f"(median of rounds; range {min(ceiling):.2f}-{max(ceiling):.2f}; 1.00 = two free "
          f"cores), load average {os.getloadavg()[0]:.1f}")
    print("speedup: over inline; efficiency: rate_N / (N x rate of 1 worker), both the median "
          "of per-round ratios; warm-up: round 0's rate, diagram builds included")


#: The environments of ``--together`` (cycled, a later lap at other hours).
TOGETHER_ENVIRONMENTS = [("KMWH", 9.0), ("KSFO", 17.0), ("KATL", 12.0), ("KMWH", 17.0),
                         ("KSFO", 9.0), ("KATL", 17.0)]


def together_ratio(args, root: Path):
    """``--together N``: the environments' sweeps on one pool, one after another and
    together (`run_together`), taking turns in each round after a warm-up round."""
    names = []
    for k in range(args.together):
        runway, hour = TOGETHER_ENVIRONMENTS[k % len(TOGETHER_ENVIRONMENTS)]
        names.append(f"runway: {runway}, hour: {hour + k // len(TOGETHER_ENVIRONMENTS):g}, "
                     f"sky: clear")
    scenarios = [load_scenario(data=f"environment: {{{name}}}\n") for name in names]
    grids = [paper_grid(s.environment.half_width, tuple(args.shape)) for s in scenarios]
    chunk = args.chunk or -(-grids[0].size // 16)
    modes = ["one after another", "together"]
    walls, identical, first = {m: [] for m in modes}, {m: True for m in modes}, None
    executor, close = make_executor(args.together_executor)
    try:
        threads = executor_threads(executor)
        for round_ in range(args.rounds + 1):          # round 0: warm-up, diagrams built
            for mode in modes[round_ % 2:] + modes[:round_ % 2]:   # each goes first in turn
                cache = root / "together" / f"{mode.replace(' ', '_')}_{round_}"
                sweeps = [functools.partial(sweep_closed_loop, s, g, cache_dir=cache,
                                            chunk_size=chunk, executor=executor, progress=False)
                          for s, g in zip(scenarios, grids)]
                t = time.perf_counter()
                if mode == "together":
                    tables = run_together([(s.environment.name, fn) for s, fn in
                                           zip(scenarios, sweeps)], executor,
                                          what="sweep of environment")
                else:
                    tables = [fn() for fn in sweeps]
                walls[mode].append(time.perf_counter() - t)
                tables = [{p: table[p] for p in table.tables} for table in tables]
                first = first or tables
                identical[mode] &= all(same(a, b) for a, b in zip(tables, first))
    finally:
        close()
    timed = {m: np.array(walls[m][1:]) for m in modes}
    print(f"together benchmark: {args.together} environments ({'; '.join(names)}), 200x360; "
          f"sweep grid {args.shape} each ({grids[0].size} states, {-(-grids[0].size // chunk)} "
          f"chunks of {chunk}) on {args.together_executor} ({threads} thread(s)); "
          f"{os.cpu_count()} CPUs; medians of {args.rounds} interleaved round(s) after a "
          f"warm-up round")
    for mode in modes:
        print(f"{mode:<18} wall {np.median(timed[mode]):7.1f} s  warm-up {walls[mode][0]:7.1f} s"
              f"  identical {identical[mode]}")
    ratio = np.median(timed["one after another"] / timed["together"])
    print(f"one after another / together: {ratio:.2f} (median of per-round ratios; above 1: "
          f"together is faster), load average {os.getloadavg()[0]:.1f}")


def overhead(args, root: Path):
    """Sleep tasks through `map_states` on ``--sim-workers`` worker threads: the stand-in
    cost in chunks of ``--sim-chunk`` states, the same in chunks a quarter that size,
    and zero-cost tasks (the rate of tasks the driver and scheduler sustain); on a
    cluster whose scheduler has each of ``--sim-saturations`` (the rounds take turns)."""
    n, per = args.sim_workers, args.sim_workers // args.sim_processes
    tasks = n * args.sim_tasks
    configs = [(args.sim_cost, args.sim_chunk, False), (args.sim_cost, args.sim_chunk, True),
               (args.sim_cost, max(1, args.sim_chunk // 4), False), (0.0, args.sim_chunk, False)]
    batches = [np.random.default_rng(0).uniform(size=(tasks * chunk, 3)) for _, chunk, _ in configs]
    t = time.perf_counter()      # the driver's own cost per chunk: key, cache write, assembly
    map_states(functools.partial(stand_in, 0.0), batches[0], cache_dir=root / "cache" / "inline",
               chunk_size=args.sim_chunk, progress=False, required=("failed",))
    driver_ms = (time.perf_counter() - t) / tasks * 1000
    saturations = args.sim_saturations
    runs = [(s, c) for s in saturations for c in configs]
    walls, ok = {r: [] for r in runs}, {r: True for r in runs}
    with contextlib.ExitStack() as stack:
        clusters = {}
        for s in saturations:
            address, start_s = stack.enter_context(dask_cluster(
                root / f"saturation_{s:g}", args.sim_processes, per,
                env={SATURATION_VARIABLE: repr(float(s))}))
            from dask.distributed import Client
            executor, close = make_executor(f"dask://{address.split('://', 1)[1]}")
            stack.callback(close)
            client = stack.enter_context(Client(address))
            told = scheduler_saturation(client)
            if told != float(s):
                raise RuntimeError(f"the scheduler started with {SATURATION_VARIABLE}={s:g} "
                                   f"reports {told}")
            clusters[s] = (executor, client, start_s)
        for round_ in range(args.rounds + 1):      # round 0: warm-up (imports on the workers)
            for s in saturations:
                executor, client, _ = clusters[s]
                for (cost, chunk, bare), states in zip(configs, batches):
                    fn = functools.partial(stand_in, cost)
                    t = time.perf_counter()
                    if bare:     # Dask alone: every task submitted at once, no cache, no window
                        parts = client.gather(client.map(
                            fn, [states[i:i + chunk] for i in range(0, len(states), chunk)],
                            pure=False))
                        fields = {"sum": np.concatenate([p["sum"] for p in parts])}
                    else:
                        fields, _, _ = map_states(
                            fn, states, chunk_size=chunk, executor=executor,
                            cache_dir=root / "cache" / f"{s:g}_{round_}_{cost}_{chunk}",
                            progress=False, required=("failed",))
                    walls[s, (cost, chunk, bare)].append(time.perf_counter() - t)
                    ok[s, (cost, chunk, bare)] &= np.array_equal(fields["sum"], states.sum(axis=1))
    starts = ", ".join(f"{s:g}: {clusters[s][2]:.1f} s" for s in saturations)
    print(f"\nscheduling overhead: {n} simulated workers ({args.sim_processes} dask worker "
          f"processes x {per} thread(s), 127.0.0.1; a cluster per scheduler worker-saturation, "
          f"started in {starts}); {tasks} tasks "
          f"({args.sim_tasks} per worker) that sleep a stand-in render cost per state, through "
          f"map_states (the driver writes every chunk's cache) or bare client.map; medians of "
          f"{args.rounds} interleaved rounds after a warm-up "
          f"({walls[saturations[0], configs[0]][0]:.1f} s: imports on the workers)")
    print(f"{'saturation':>10} {'through':<18} {'ms/state':>8} {'states/task':>11} {'task s':>7} "
          f"{'ideal s':>8} {'wall s':>7} {'overhead':>8} {'tasks/s':>8}  results right")
    for s, ((cost, chunk, bare), states) in ((s, c) for s in saturations
                                              for c in zip(configs, batches)):
        wall = float(np.median(walls[s, (cost, chunk, bare)][1:]))
        ideal = len(states) * cost / n
        print(f"{s:10g} {'client.map (bare)' if bare else 'map_states':<18} {cost * 1000:8g} "
              f"{chunk:11d} {cost * chunk:7.2f} {ideal:8.2f} {wall:7.2f} "
              f"{(wall - ideal) / wall:8.1%} {tasks / wall:8.0f}  {ok[s, (cost, chunk, bare)]}")
    print("overhead = (wall - ideal) / wall, ideal = total sleep / workers; saturation: the "
          "scheduler's worker-saturation (tasks it sends a worker per thread; Dask's default "
          "is 1.1, the cluster guide starts it at 1.0)")
    print(f"the driver's own work per chunk (inline, zero-cost tasks): {driver_ms:.2f} ms")


if __name__ == "__main__":
    main()
