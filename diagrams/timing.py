"""Online rate: closed-loop control ticks per wall second of two diagrams, timed so
that a drifting machine biases neither. On a shared VM the speed moves by ~10 % within
a second and ~30 % over minutes, so the two loops run side by side from the same start,
advanced in alternating blocks of a few ticks, and each is charged the wall time of
its own blocks."""

import time

import numpy as np

from .closed_loop import start_simulator


def _ticks(simulator, period):
    return int(np.floor(simulator.get_context().get_time() / period + 1e-9)) + 1


def paired_rates(reference, candidate, *, rounds: int, duration: float, period: float,
                 starts, block: float = 0.5):
    """Control ticks (one every ``period`` s) per wall second of ``reference`` and
    ``candidate`` (closed-loop diagrams exporting ``state``) in each of ``rounds`` rounds. In a round both run ``duration``
    s from the same start, ``starts[k % len(starts)]`` (states of the loop's plant),
    advanced ``block`` s at a time, in turn,
    the one going first alternating. Returns two arrays of ``rounds`` rates; their
    per-round ratio is the figure to report."""
    if rounds < 1 or duration <= 0 or block <= 0 or period <= 0:
        raise ValueError(f"paired_rates needs rounds >= 1, duration > 0 s, period > 0 s and "
                         f"block > 0 s, got {rounds}, {duration}, {period}, {block}")
    if starts is None or len(starts) < 1:
        raise ValueError("paired_rates needs at least one start")
    diagrams = (reference, candidate)
    contexts = [d.CreateDefaultContext() for d in diagrams]
    rates = np.zeros((2, rounds))
    for k in range(-1, rounds):                       # round -1: warm-up, not kept
        x0 = starts[max(k, 0) % len(starts)]
        sims = [start_simulator(d, initial_state=x0, context=c)[0]
                for d, c in zip(diagrams, contexts)]
        spent, t, i = [0.0, 0.0], 0.0, 0
        end = duration if k >= 0 else min(duration, block)
        while t < end - 1e-9:
            t = min(t + block, end)
            for j in ((0, 1) if i % 2 == 0 else (1, 0)):
                started = time.perf_counter()
                sims[j].AdvanceTo(t)
                spent[j] += time.perf_counter() - started
            i += 1
        if k >= 0:
            rates[:, k] = [_ticks(s, period) / w for s, w in zip(sims, spent)]
    return rates[0], rates[1]
