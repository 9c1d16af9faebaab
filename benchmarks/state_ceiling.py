"""How far the true label follows from the exact state, as labelled runs grow: a
k-nearest-neighbour vote on each dataset's states (no images), cross-validated by run,
trained on a growing share of the runs. It measures the labels, not a detector: an
image shows less than the state, and a held-out detector has no labels of the
environment at all, so what this ceiling reaches at a given number of labels bounds what
more images of the same density could buy.

Datasets of one environment are pooled (their runs kept apart), so two builds with
other seeds add up. Only datasets that record their runs (``trajectory`` labels, a
hybrid's trajectory fallback, or ``paths``) can be split by run; samples on no run are
each their own. A state's neighbours are found after dividing each axis by ``--scale``
(for the taxi, px in m, py in m, theta in rad: 1 m, 10 m and 2 deg by default).

    python benchmarks/state_ceiling.py --datasets RUN/datasets/KSFO_21h_clear_* \\
        [--shares 0.25 0.5 1] [--folds 3] [--k 15] [--recall 0.95] [--seed 0]

Prints one line per environment: its states, runs and failing share, then for each
share of the training folds' runs the labels it trained on, the AUROC of the
out-of-fold votes and the accuracy at the oracle threshold reaching ``--recall``.
"""

import argparse
from collections import defaultdict

import numpy as np

from reachwatch.training.dataset import load_dataset
from reachwatch.training.labels import NO_RUN
from reachwatch.training.metrics import accuracy_at_recall, auroc


def run_ids(runs, offset: int) -> np.ndarray:
    """Each sample's run as a number unique across pooled datasets: ``runs`` shifted by
    ``offset``, and a sample on no run (`NO_RUN`) its own run."""
    runs = np.asarray(runs, np.int64)
    own = np.flatnonzero(runs == NO_RUN)
    out = runs + offset
    out[own] = offset + runs.max(initial=-1) + 1 + np.arange(len(own))
    return out


def knn_votes(x, y, runs, *, folds: int, share: float, k: int, rng) -> tuple:
    """Out-of-fold k-NN scores of ``y`` (bool) at states ``x`` (already scaled): the runs
    are split into ``folds`` at random, and each fold is scored by a vote
    (inverse-distance weighted) of its ``k`` nearest states among a random ``share`` of
    the other folds' runs. Returns ``(scores, mean number of training labels)``."""
    ids = np.unique(runs)
    fold_of = dict(zip(ids.tolist(), (rng.permutation(len(ids)) % folds).tolist()))
    fold = np.array([fold_of[r] for r in runs.tolist()])
    scores, used = np.zeros(len(y)), []
    for f in range(folds):
        test = fold == f
        others = ids[[fold_of[r] != f for r in ids.tolist()]]
        keep = rng.permutation(others)[:max(1, int(round(share * len(others))))]
        train = np.isin(runs, keep)
        used.append(int(train.sum()))
        dist = np.linalg.norm(x[test][:, None] - x[train][None], axis=2)
        near = np.argsort(dist, axis=1)[:, :k]
        weight = 1.0 / (np.take_along_axis(dist, near, 1) + 1e-9)
        scores[test] = (weight * y[train][near]).sum(1) / weight.sum(1)
    return scores, float(np.mean(used))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--datasets", nargs="+", required=True, help="dataset folders")
    p.add_argument("--shares", type=float, nargs="+", default=[0.25, 0.5, 1.0],
                   help="shares of the training folds' runs to train on")
    p.add_argument("--folds", type=int, default=3)
    p.add_argument("--k", type=int, default=15)
    p.add_argument("--recall", type=float, default=0.95)
    p.add_argument("--scale", type=float, nargs="+", default=[1.0, 10.0, float(np.deg2rad(2.0))],
                   help="per state axis: the distance that counts as 1")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    if args.folds < 2 or args.k < 1 or not all(0 < s <= 1 for s in args.shares):
        p.error("--folds must be >= 2, --k >= 1 and each share in (0, 1]")
    pooled = defaultdict(list)
    for folder in args.datasets:
        data = load_dataset(folder)
        if data.runs is None:
            p.error(f"{folder}: the dataset records no runs (build it with trajectory labels "
                    f"or paths)")
        pooled[data.manifest["environment"]].append(data)
    for env, sets in sorted(pooled.items()):
        x = np.concatenate([np.asarray(d.states, float) for d in sets])
        if x.shape[1] != len(args.scale):
            p.error(f"{env}: states have {x.shape[1]} axes, --scale gives {len(args.scale)}")
        y = np.concatenate([np.asarray(d.labels).astype(bool) for d in sets])
        runs, offset = [], 0
        for d in sets:
            runs.append(run_ids(d.runs, offset))
            offset = int(runs[-1].max()) + 1
        runs = np.concatenate(runs)
        line = (f"{env:24s} states {len(y):6d}  runs {len(np.unique(runs)):5d}  "
                f"failing {100 * y.mean():5.1f} %")
        for share in args.shares:
            rng = np.random.default_rng(args.seed)
            scores, used = knn_votes(x / args.scale, y, runs, folds=args.folds, share=share,
                                     k=args.k, rng=rng)
            line += (f" | {used:6.0f} labels: AUROC {100 * auroc(y, scores):5.1f}  "
                     f"acc@{100 * args.recall:g} {100 * accuracy_at_recall(y, scores, args.recall):5.1f}")
        print(line, flush=True)


if __name__ == "__main__":
    main()
