"""Many runs of one closed loop advanced together, a control tick at a time.

`simulate_lockstep` keeps up to ``len(loops)`` runs in flight, one per copy of the
loop (a diagram and its Context). At every tick it steps each run's Simulator to the
tick (`LoopRun.advance`), lets every system that has a batch entry point compute its
outputs for all the runs at once, then reads each run's ports (`LoopRun.sample`); a
finished run's copy takes the next start. The cameras render the runs' frames one
after another and the controller sees them as a batch.

Each run needs a diagram of its own, not only a Context: Drake's VTK render engine
keeps one clone per Context, and clones of one engine disturb each other's textured
renders once a Context is reset for a new run (measured: wrong frames from the second
run on). `loop_copies` builds them.

A system's batch entry point is a method ``prepare_batch(pairs)``. ``pairs`` lists
``(system, context)`` of several runs at the same tick: the same system in each copy of
the loop, with its Context there. It computes the outputs those Contexts will be asked
for, so that each run's own evaluation returns them instead of computing again
(`reachwatch.systems.TaxiNet` has one); it must return exactly what one run at a time
computes. When the runs end (or fail), it is called once more with every Context None:
drop what was prepared, compute nothing. A system without one computes one run at a
time when its ports are evaluated. Every run's `Trajectory` equals the one `simulate` returns from the same
start."""

from typing import Callable, Optional, Sequence

import numpy as np
from pydrake.systems.framework import Diagram

from .closed_loop import LoopRun, Trajectory, simulate

#: The name of a system's optional batch entry point.
BATCH_ENTRY = "prepare_batch"


def batch_systems(diagram: Diagram) -> list:
    """The systems of ``diagram`` (nested diagrams included) with a batch entry point,
    in a fixed order: copies of one loop list their counterparts at the same places."""
    found = []
    for system in diagram.GetSystems():
        if callable(getattr(system, BATCH_ENTRY, None)):
            found.append(system)
        if isinstance(system, Diagram):
            found.extend(batch_systems(system))
    return found


def loop_copies(make: Callable[[], Diagram], count: int) -> list:
    """``count`` copies ``(diagram, context)`` of the loop ``make()`` builds."""
    if count < 1:
        raise ValueError(f"lockstep needs at least one copy of the loop, got {count}")
    copies = []
    for _ in range(int(count)):
        diagram = make()
        copies.append((diagram, diagram.CreateDefaultContext()))
    return copies


def _counterparts(loops) -> list:
    """Per batch-capable system of the first copy, that system in every copy."""
    per_copy = [batch_systems(diagram) for diagram, _ in loops]
    shape = [(type(s).__name__, s.get_name()) for s in per_copy[0]]
    for systems in per_copy[1:]:
        if [(type(s).__name__, s.get_name()) for s in systems] != shape:
            raise ValueError(f"lockstep: the copies of the loop differ in their batch-capable "
                             f"systems ({shape} against "
                             f"{[(type(s).__name__, s.get_name()) for s in systems]}); build "
                             f"every copy with the same function")
    return [list(column) for column in zip(*per_copy)]


def simulate_lockstep(loops: Sequence, *, initial_states, duration: float, period: float,
                      failed=None, stop_on_failure: bool = True,
                      stop_when: Optional[Callable[[int], Callable]] = None,
                      record=None) -> list:
    """`simulate` from each of ``initial_states``, ``len(loops)`` runs at a time in
    lockstep. ``loops``: copies ``(diagram, context)`` of one closed loop (`loop_copies`),
    reused in turn. Returns one `Trajectory` per start, in order, each equal to
    ``simulate(diagram, initial_state=initial_states[i], ...)``; with one copy it is that
    call, start after start. ``stop_when``, when given, is a function of the start's
    index returning that run's ``stop_when`` (or None), so that one run's stop test may
    keep state of its own. Other arguments are `simulate`'s."""
    starts = [np.asarray(x, float) for x in initial_states]
    if len(loops) < 1:
        raise ValueError("simulate_lockstep needs at least one copy of the loop")
    settings = dict(duration=duration, period=period, failed=failed,
                    stop_on_failure=stop_on_failure, record=record)
    if len(loops) == 1:                         # one at a time: `simulate` itself
        diagram, context = loops[0]
        return [simulate(diagram, initial_state=x, context=context,
                         stop_when=None if stop_when is None else stop_when(i), **settings)
                for i, x in enumerate(starts)]
    columns = _counterparts(loops)
    results = [None] * len(starts)
    slots = [None] * len(loops)                 # (start index, LoopRun) per copy
    following = iter(range(len(starts)))

    def begin(slot):
        """The next start's run on copy ``slot``, at its first tick (time 0, always
        logged); None when no start is left."""
        i = next(following, None)
        if i is None:
            return None
        diagram, context = loops[slot]
        run = LoopRun(diagram, initial_state=starts[i], context=context,
                      stop_when=None if stop_when is None else stop_when(i), **settings)
        run.advance()
        return i, run

    try:
        while True:
            for slot, held in enumerate(slots):
                if held is None or not held[1].advance():
                    if held is not None:
                        results[held[0]] = held[1].trajectory()
                    slots[slot] = begin(slot)
            ready = [slot for slot, held in enumerate(slots) if held is not None]
            if not ready:
                break
            for column in columns:
                pairs = [(column[slot], column[slot].GetMyContextFromRoot(slots[slot][1].context))
                         for slot in ready]
                getattr(column[0], BATCH_ENTRY)(pairs)
            for slot in ready:
                slots[slot][1].sample()
    except BaseException:
        try:                # nothing prepared outlives the runs; the runs' error is the one
            _release(columns)
        except Exception:   # noqa: BLE001 (a hook failing on its release hides no error)
            pass
        raise
    _release(columns)
    return results


def _release(columns) -> None:
    """Every batch entry point called with every Context None: drop what it prepared."""
    for column in columns:
        getattr(column[0], BATCH_ENTRY)([(system, None) for system in column])


__all__ = ["BATCH_ENTRY", "Trajectory", "batch_systems", "loop_copies", "simulate_lockstep"]
