"""Recorded real-loop runs of the taxi for a monitor over the image history: at every
control tick the camera frame (resized to the monitor's input), the online signals a
monitor may read (the controller's estimate and steering, in the order
`reachwatch.diagrams.guarded.add_monitor_signals` gives them) and the state, with the
run's failure time. They are the generic recorded runs (`reach.loop_runs.loop_recordings`)
of the taxi's loop; time-to-failure labels come from them by
`reachwatch.reach.outcomes.time_to_failure`."""

from reachwatch.reach.application import ApplicationRef
from reachwatch.reach.loop_runs import loop_recordings


def record_runs(scenario, duration: float, height: int, width: int, states, *,
                scored: bool = False) -> dict:
    """The taxi's real closed loop of ``scenario`` (as given) from each start for
    ``duration`` s (stopping where it leaves the runway), every control tick recorded:
    per start ``frames`` uint8 ``(T, height, width, 3)``, ``signals`` ``(T, m)``,
    ``state`` ``(T, 3)`` (zeros / NaN after the run ended), ``ticks``, ``failed`` and
    ``failure_time`` (s, NaN for none); ``T`` is the horizon's tick count. ``scored``:
    also ``score`` ``(T,)`` and ``engaged``, the detector of ``scenario.monitor`` along
    the same runs (`reach.loop_runs.loop_recordings`)."""
    from .application import TAXI_APPLICATION
    return loop_recordings(ApplicationRef(TAXI_APPLICATION), scenario, duration, height,
                           width, states, scored=scored)
