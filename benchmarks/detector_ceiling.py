"""How well the run's detector settings can do on one environment when they need not
generalise: trained and tested on that environment's own images.

A held-out environment's figures mix two limits: what the detector can learn from an
image at all (is the state, and so the label, visible in it at this size and network?)
and how far what it learned elsewhere carries over. This benchmark separates them. It
renders one larger BRT-labelled dataset of the environment (same labels, image size and
box as the run's datasets; cached by content, so a second call renders nothing), keeps
its last ``--test-share`` as a test split, and trains the run file's detector on growing
shares of the rest. Each line gives, on the test split: AUROC, the recall and accuracy
at the threshold the training run chose (its own validation split, the run file's
``target_recall``), and the accuracy an oracle threshold reaching 95 % recall on the test
split allows. The run's own detector, trained on the other environments, is scored on
the same split first, for comparison.

    python benchmarks/detector_ceiling.py --run out/demo [--environment KSFO_21h_overcast]
        [--samples 6000] [--test-share 0.25] [--sizes 0.25,0.5,1] [--epochs N] [--seed 0]
        [--work RUN/ceiling] [--visited RUNS]

The labels are the BRT's, as in the run's datasets: the figures say how well the
detector learns the map, not whether the map is right (see the run's fidelity section).

``--visited RUNS`` asks the same of the states the loop visits, the ones an online
monitor scores: the dataset is ``trajectory``-labelled instead (RUNS real runs from
uniform states, and the states each passes through, labelled by the run: true labels),
its last ``--test-share`` of runs is the test split (a run's states are near-copies, so
no run is on both sides), and each line adds the AUROC of the failures that come within
2, 4 and 8 s of the image against the safe states: how far ahead the detector sees.
"""

import argparse
import dataclasses as dc
import json
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import load_detector
from reachwatch.pipeline.keys import digest
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.stages import Run
from reachwatch.reach.value_function import ValueFunction
from reachwatch.reach.outcomes import path_points
from reachwatch.taxi.fidelity import real_paths
from reachwatch.training.dataset import build_dataset, load_dataset, runs_cache
from reachwatch.training.detector_train import detector_scores, train_detector
from reachwatch.training.metrics import accuracy_at_recall, auroc, binary_metrics

ORACLE_RECALL = 0.95
#: With --visited: the AUROC of the failures within each of these many seconds.
AHEAD_S = (2.0, 4.0, 8.0)


def rows_of(data, rows):
    """The `LabelledData` of ``rows`` only (images stay memory-mapped)."""
    return dc.replace(data, images=data.images[rows], states=data.states[rows],
                      values=data.values[rows], labels=data.labels[rows],
                      estimates=data.estimates[rows], ensemble=data.ensemble[rows],
                      sources=None if data.sources is None else data.sources[rows],
                      runs=None if data.runs is None else data.runs[rows])


def figures(labels, scores, threshold, time_to_failure=None):
    """Test-split figures of one detector at its own ``threshold``; with
    ``time_to_failure`` (s, per sample; NaN where it does not fail) also the AUROC of
    the failures within each of `AHEAD_S` against the safe samples."""
    at = binary_metrics(labels, scores >= threshold)
    out = {"auroc": auroc(labels, scores), "threshold": float(threshold),
           "recall": at.recall, "accuracy": at.accuracy,
           "flagged": float(np.mean(scores >= threshold)),
           "accuracy_at_95_recall": accuracy_at_recall(labels, scores, ORACLE_RECALL)}
    if time_to_failure is not None:
        safe = labels == 0
        for ahead in AHEAD_S:
            soon = (labels == 1) & (time_to_failure <= ahead + 1e-9)
            keep = safe | soon
            out[f"auroc_within_{ahead:g}s"] = auroc(soon[keep], scores[keep])
    return out


def line(name, n_train, f):
    ahead = "".join(f"  {a:g} s {100 * f[f'auroc_within_{a:g}s']:5.1f}" for a in AHEAD_S
                    if f"auroc_within_{a:g}s" in f)
    return (f"{name:<34} train {n_train:>6}  AUROC {100 * f['auroc']:5.1f}  recall "
            f"{100 * f['recall']:5.1f}  accuracy {100 * f['accuracy']:5.1f}  flagged "
            f"{100 * f['flagged']:5.1f}  accuracy at 95 % recall {100 * f['accuracy_at_95_recall']:5.1f}"
            + (f"  AUROC of failures within{ahead}" if ahead else ""))


def time_to_failure(data, scenario, value_function, runs_count):
    """Seconds from each sample of a ``trajectory`` dataset to its run's failure (NaN:
    no failure), from the dataset's cached runs (nothing is simulated again)."""
    labels = data.manifest["spec"]["labels"]
    out = real_paths(scenario, np.asarray(data.states[:runs_count]), grid=value_function.grid,
                     horizon=value_function.horizon, extend=labels["extend"],
                     stride=labels["stride"], cache_dir=runs_cache(data.folder),
                     progress=False).fields
    ticks = path_points(value_function.horizon, labels["extend"], labels["stride"],
                        scenario.controller.period) * scenario.controller.period
    result = np.full(len(data.labels), np.nan)
    for i, (state, run) in enumerate(zip(np.asarray(data.states), data.runs)):
        along = np.flatnonzero(np.all(out["path_state"][run] == state, axis=1))
        if len(along) == 0:
            raise ValueError(f"sample {i} lies on none of its run's states: the dataset's "
                             f"cached runs do not match it")
        result[i] = out["failure_time"][run] - ticks[along[0]]
    return result


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, type=Path,
                        help="a run directory with finished solve and train stages")
    parser.add_argument("--environment", help="an environment the run solved (default: its "
                        "first held-out one)")
    parser.add_argument("--samples", type=int, default=6000, help="images rendered (default 6000)")
    parser.add_argument("--test-share", type=float, default=0.25,
                        help="share of them kept for testing (default 0.25)")
    parser.add_argument("--sizes", default="0.25,0.5,1",
                        help="shares of the rest to train on, comma-separated (default 0.25,0.5,1)")
    parser.add_argument("--epochs", type=int, help="training epochs (default: the run file's)")
    parser.add_argument("--seed", type=int, default=0, help="dataset and training seed")
    parser.add_argument("--work", type=Path, help="dataset and checkpoint folder "
                        "(default RUN/ceiling)")
    parser.add_argument("--json", type=Path, help="also write every figure here")
    parser.add_argument("--visited", type=int, default=0, metavar="RUNS",
                        help="score the states RUNS real runs visit (trajectory labels, "
                        "split by run) instead of --samples uniform states (default 0: off)")
    args = parser.parse_args()
    if args.visited and args.visited < 8:
        parser.error(f"--visited needs at least 8 runs, got {args.visited}")
    if not args.visited and args.samples < 40:
        parser.error(f"--samples must be at least 40, got {args.samples}")
    if not 0 < args.test_share < 1:
        parser.error(f"--test-share must be between 0 and 1, got {args.test_share}")
    try:
        sizes = [float(s) for s in args.sizes.split(",")]
    except ValueError:
        parser.error(f"--sizes must be comma-separated numbers, got '{args.sizes}'")
    if not all(0 < s <= 1 for s in sizes):
        parser.error(f"--sizes must lie in (0, 1], got {sizes}")
    spec = load_run_spec(args.run / "run.yaml")
    run = Run(spec, args.run, progress=True)
    solved = {e.name: e for e in run.environments()}
    name = args.environment or spec.held_out_environments()[0].name
    if name not in solved:
        parser.error(f"the run has no environment '{name}'; it has {sorted(solved)}")
    env = solved[name]
    records = {}
    for stage in (f"solve_{name}", "train"):
        path = args.run / "stages" / f"{stage}.json"
        if not path.is_file():
            parser.error(f"{args.run} has no finished {stage} stage ({path} is missing)")
        records[stage] = json.loads(path.read_text())["outputs"]
    value_function = ValueFunction.load(args.run / records[f"solve_{name}"]["value"])
    box = None
    if run.solved_grid_for(env) != run.grid_for(env):     # label the paper's box, as the run
        box = run.grid_for(env).lo.tolist(), run.grid_for(env).hi.tolist()
    work = args.work or args.run / "ceiling"
    dataset_spec = dc.replace(spec.dataset, samples=args.visited or args.samples, seed=args.seed)
    if args.visited:
        dataset_spec = dc.replace(dataset_spec, labels=dc.replace(
            spec.dataset.labels, source="trajectory", paths=0, max_rollouts=0))
    started = time.time()
    data = load_dataset(build_dataset(work / "datasets", run.scenario_for(env), value_function,
                                      dataset_spec, box=box, application=run.application))
    print(f"detector ceiling: {name}, {len(data.labels)} images "
          + (f"along {args.visited} real runs " if args.visited else "") +
          f"({100 * data.labels.mean():.1f} % anomalous), rendered or reused in "
          f"{time.time() - started:.0f} s")
    if args.visited:       # whole runs: the last test share of them is the test split
        n_test = max(1, int(round(args.test_share * args.visited)))
        first_test = args.visited - n_test
        order = np.argsort(data.runs, kind="stable")
        train_rows = lambda count: order[data.runs[order] < count]   # noqa: E731
        test_rows = np.flatnonzero(data.runs >= first_test)
        ahead = time_to_failure(data, run.scenario_for(env), value_function, args.visited)[test_rows]
    else:
        n_test = max(1, int(round(args.test_share * args.samples)))
        first_test = args.samples - n_test
        train_rows = lambda count: np.arange(count)                   # noqa: E731
        test_rows, ahead = np.arange(first_test, args.samples), None
    test = rows_of(data, test_rows)
    results = {"environment": name, "samples": len(data.labels), "test": len(test_rows),
               "test_runs" if args.visited else "test_samples": n_test}

    model, detector_config, metadata = load_detector(args.run / records["train"]["detector"])
    scores = detector_scores(model, detector_config, test.images)
    results["run detector"] = figures(test.labels, scores, records["train"]["threshold"], ahead)
    print(line("run's detector (other environments)", int(metadata.get("samples", 0)),
               results["run detector"]), flush=True)

    config = spec.detector if args.epochs is None else dc.replace(spec.detector, epochs=args.epochs)
    config = dc.replace(config, seed=args.seed).validate()
    for share in sizes:
        count = max(4 if args.visited else 10, int(round(share * first_test)))
        rows = train_rows(count)
        train = rows_of(data, rows)
        path = work / f"detector_{digest(dc.asdict(config), data.folder.name, count)}.pt"
        started = time.time()
        if path.exists():
            threshold = load_detector(path)[2]["threshold"]
        else:
            threshold = train_detector([train], config, path)["threshold"]
        model, detector_config, _ = load_detector(path)
        f = figures(test.labels, detector_scores(model, detector_config, test.images), threshold,
                    ahead)
        results[f"trained here, {len(rows)}"] = f
        name_here = f"trained here, {count} runs" if args.visited else "trained here"
        print(line(f"{name_here} ({time.time() - started:.0f} s)", len(rows), f), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
