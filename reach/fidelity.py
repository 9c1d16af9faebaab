"""How far a BRT's verdicts can be trusted: its verdicts compared with what the real
loop did from the same starts, with 95 % confidence intervals.

"False-safe" (the BRT called a start safe, the loop failed) is the error a safety tool
must not make; "false-unsafe" the costly but harmless one. Rates are over all checked
starts; intervals are Wilson score intervals (they stay inside [0, 1] and keep their
coverage at 0 or n successes, where the normal approximation collapses to a point)."""

import dataclasses as dc
import math

import numpy as np

#: z for a two-sided 95 % interval.
Z95 = 1.959963984540054


def wilson_interval(successes: int, trials: int, z: float = Z95):
    """The Wilson score interval ``(lo, hi)`` of a binomial proportion."""
    if isinstance(successes, bool) or isinstance(trials, bool):
        raise ValueError("successes and trials are counts, not booleans")
    successes, trials = int(successes), int(trials)
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials >= 1, got "
                         f"{successes} of {trials}")
    p, n = successes / trials, trials
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    # No successes (or no failures): the bound is 0 (or 1) exactly, not 1e-17 off it.
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == trials else min(1.0, centre + half)
    return lo, hi


@dc.dataclass
class Fidelity:
    """Counts of a check of BRT verdicts against real runs from ``n`` starts.
    ``box_exits``: runs that left the solved grid box within the horizon (where the
    solver's table says nothing about the loop); ``exits_missed``: false-safe runs
    among them."""
    n: int
    real_failures: int
    predicted_failures: int
    agree: int
    false_safe: int
    false_unsafe: int
    box_exits: int = 0
    exits_missed: int = 0

    def rate(self, name: str):
        """``(fraction, lo, hi)`` of a count field over ``n``, with its Wilson interval."""
        count = getattr(self, name)
        return (count / self.n, *wilson_interval(count, self.n))

    def summary(self) -> str:
        parts = []
        for name, label in (("agree", "agreement"), ("false_safe", "false-safe"),
                            ("false_unsafe", "false-unsafe"), ("box_exits", "left the box")):
            rate, lo, hi = self.rate(name)
            parts.append(f"{label} {100 * rate:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}] "
                         f"({getattr(self, name)})")
        return (f"{self.n} starts, {self.real_failures} real failures, "
                f"{self.predicted_failures} predicted: " + "; ".join(parts) +
                f"; false-safe among box exits: {self.exits_missed}")

    def as_dict(self) -> dict:
        out = dc.asdict(self)
        for name in ("agree", "false_safe", "false_unsafe", "box_exits"):
            rate, lo, hi = self.rate(name)
            out[f"{name}_rate"], out[f"{name}_ci95"] = rate, [lo, hi]
        return out


def compare_verdicts(predicted, failed, left_box=None) -> Fidelity:
    """`Fidelity` of BRT verdicts ``predicted`` (True = in the BRT) against real
    outcomes ``failed``, optionally with which runs ``left_box``."""
    predicted, failed = np.asarray(predicted, bool), np.asarray(failed, bool)
    if predicted.shape != failed.shape or predicted.ndim != 1 or len(predicted) == 0:
        raise ValueError(f"predicted and failed must be equal non-empty 1-D arrays, got "
                         f"{predicted.shape} and {failed.shape}")
    left = np.zeros_like(failed) if left_box is None else np.asarray(left_box, bool)
    if left.shape != failed.shape:
        raise ValueError(f"left_box must match failed's shape {failed.shape}, got {left.shape}")
    false_safe = failed & ~predicted
    return Fidelity(n=len(failed), real_failures=int(failed.sum()),
                    predicted_failures=int(predicted.sum()), agree=int((failed == predicted).sum()),
                    false_safe=int(false_safe.sum()), false_unsafe=int((predicted & ~failed).sum()),
                    box_exits=int(left.sum()), exits_missed=int((false_safe & left).sum()))


def left_box(states, grid, *, axes=None) -> bool:
    """Whether a trajectory ``(T, n)`` leaves ``grid``'s box on any of ``axes``
    (default all)."""
    states = np.asarray(states, float)
    axes = range(grid.ndim) if axes is None else axes
    return bool(any(np.any((states[:, a] < grid.lo[a] - 1e-9) | (states[:, a] > grid.hi[a] + 1e-9))
                    for a in axes))


def select_map(fidelities, *, costs=None, false_safe_weight: float = 2.0) -> int:
    """Index of the map to keep among candidates for one environment (refinement levels,
    robust variants), from each one's `Fidelity` on the *same* selection runs, which
    must not be the runs it is then judged on: the fewest weighted errors
    ``false_unsafe + false_safe_weight * false_safe`` (a false-safe verdict costs more),
    ties going to fewer false-safe verdicts, then to the lower cost (e.g. renders; the
    earlier candidate without ``costs``)."""
    fidelities = list(fidelities)
    if not fidelities:
        raise ValueError("select_map needs at least one candidate")
    if not all(isinstance(f, Fidelity) for f in fidelities):
        raise ValueError("select_map takes Fidelity records (compare_verdicts)")
    if len({f.n for f in fidelities}) != 1:
        raise ValueError(f"the candidates must be scored on the same selection runs, got "
                         f"{sorted({f.n for f in fidelities})} starts")
    costs = [0.0] * len(fidelities) if costs is None else [float(c) for c in costs]
    if len(costs) != len(fidelities):
        raise ValueError(f"{len(costs)} costs for {len(fidelities)} candidates")
    if not np.isfinite(false_safe_weight) or false_safe_weight < 1:
        raise ValueError(f"false_safe_weight must be a finite number >= 1, got "
                         f"{false_safe_weight!r}")
    keys = [(f.false_unsafe + false_safe_weight * f.false_safe, f.false_safe, c, i)
            for i, (f, c) in enumerate(zip(fidelities, costs))]
    return min(keys)[-1]
