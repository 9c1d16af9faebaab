"""The batches of real-loop runs an `Application` gives the stages: outcomes from
starts (the real-loop check), recorded runs (what a monitor over the image history
trains on), missions of the loop alone or guarded (the monitor's guarded real loop),
and the states runs pass through (trajectory labels). `RealLoopHooks` is a base of
`Application`; each method's default runs `Application.loop_diagram` through the
generic runners of `reach.loop_runs`, cached by content, and an application overrides
any of them as it overrides the others."""

import dataclasses as dc
import functools


class RealLoopHooks:
    """The real loop's batches of runs (a base of `Application`)."""

    def real_outcomes(self, scenario, starts, *, grid, duration: float, cache_dir,
                      executor=None, progress: bool = True):
        """`reach.outcomes.Outcomes` of the real loop (`loop_diagram`, rendering at
        every tick) from each start for ``duration`` s: per start ``failed``,
        ``failure_time`` (s, NaN if none), ``left_box`` (along `open_axes` of ``grid``'s
        box), ``max_abs_theta`` (rad: the largest ``|heading|``, `heading_axis`; NaN
        without one) and ``ticks`` (frames rendered); cached by content under
        ``cache_dir``, keyed without the monitor (`without_monitor`). Default:
        `loop_rollouts`, which stops where `failed` holds, at the integrator step, and
        advances several runs together (`reach.loop_runs.LOCKSTEP`)."""
        from .application import ApplicationRef
        from .loop_runs import loop_rollouts
        from .outcomes import run_outcomes
        rollout = functools.partial(loop_rollouts, ApplicationRef(self._loaded_as()),
                                    self.without_monitor(scenario), float(duration), grid)
        return run_outcomes(rollout, starts, cache_dir=cache_dir, executor=executor,
                            progress=progress, label=scenario.environment.name)

    def recorded_runs(self, scenario, starts, *, duration: float, height: int, width: int,
                      cache_dir, executor=None, progress: bool = True,
                      scored: bool = False) -> dict:
        """The controller alone's real loop from each start for ``duration`` s (stopping
        at failure), every control tick recorded: what a monitor over the image history
        trains on. Per start: ``frames`` uint8 ``(T, height, width, 3)`` (the camera's
        image, resized), ``signals`` ``(T, m)`` (the online signals a history monitor may
        read: the controller's estimate when it has one, then its steering, as
        `reachwatch.diagrams.guarded.add_monitor_signals` orders them), ``state`` ``(T,
        n)``, ``ticks``, ``failed`` and ``failure_time`` (s, NaN for none); ``T`` is the
        horizon's tick count, rows past a run's end zeros / NaN. Cached by content under
        ``cache_dir`` (the scenario without its monitor, the horizon, the frame size and
        the starts). ``scored``: also ``score`` ``(T,)`` (NaN past a run's end), the
        detector of ``scenario.monitor`` along the same runs, as `score_runs` reads it,
        and ``engaged`` (as there), keyed by the detector but not its threshold or
        fallback: one run gives a monitor's frames and the detector's scores. Default:
        `loop_recordings`, which reads `camera_port` and `probe`'s control port (and
        `score_port`) inside `loop_diagram` and stops where `failed` holds."""
        from .application import ApplicationRef
        from .loop_runs import loop_recordings
        from .outcomes import map_states
        scenario = self._watching(scenario) if scored else self.without_monitor(scenario)
        rollout = functools.partial(loop_recordings, ApplicationRef(self._loaded_as()),
                                    scenario, float(duration), int(height), int(width),
                                    scored=scored)
        fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                                  progress=progress, unit="run",
                                  required=("failed", "frames") + (("score",) if scored else ()),
                                  label=f"recorded runs {scenario.environment.name}")
        return fields

    def missions(self, scenario, starts, *, fallback=None, duration: float, cache_dir,
                 executor=None, progress: bool = True, mission_limit=None):
        """`reach.liveness.MissionOutcomes` of the real loop from each start for
        ``duration`` s, stopping at failure: the controller alone (``fallback=None``) or
        guarded (`loop_diagram` with ``guarded``) by ``scenario.monitor``'s detector with
        the fallback named ``fallback`` (e.g. ``"brake"``). Cached by content under
        ``cache_dir``; the controller alone's runs are keyed without the monitor. Default:
        `loop_missions`, which stops where `failed` holds and reads the
        guarded loop's exported ``speed`` and ``anomaly``. ``mission_limit`` (the guard's
        check; None: none): the runs also go on past the horizon, for up to that many
        horizons, until they cover the distance the controller alone covers within it,
        and the same-distance fields are filled (`reach.liveness.SAME_DISTANCE_FIELDS`)."""
        from .application import ApplicationRef, without_run_settings
        from .liveness import MISSION_FIELDS, SAME_DISTANCE_FIELDS, MissionOutcomes
        from .loop_runs import loop_missions
        from .outcomes import map_states
        scenario = (without_run_settings(self.resolved(scenario)) if fallback
                    else self.without_monitor(scenario))
        limit = None if mission_limit is None else float(mission_limit)
        rollout = functools.partial(loop_missions, ApplicationRef(self._loaded_as()),
                                    scenario, fallback, float(duration), mission_limit=limit)
        fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                                  progress=progress, unit="run",
                                  required=MISSION_FIELDS + (SAME_DISTANCE_FIELDS
                                                             if limit is not None else ()),
                                  label=f"real loop {scenario.environment.name} "
                                        f"{fallback or 'alone'}")
        return MissionOutcomes.from_fields(fields)

    def without_monitor(self, scenario):
        """`resolved` ``scenario`` with the default monitor and no run settings
        (`without_run_settings`): the controller alone's loop never reads them, so its
        cached runs are keyed without them."""
        from reachwatch.diagrams import MonitorConfig

        from .application import without_run_settings
        return without_run_settings(dc.replace(self.resolved(scenario), monitor=MonitorConfig()))

    def real_paths(self, scenario, starts, *, grid, horizon: float, extend: float,
                   stride: int, cache_dir, executor=None, progress: bool = True):
        """Like `real_outcomes`, with the states each run passes through and their labels
        (``path_state``, ``path_label``): what trajectory labels read. Each run lasts
        ``horizon + extend`` s and keeps every ``stride``-th tick up to ``extend`` s;
        cached by content under ``cache_dir``, keyed without the monitor. Default:
        `reach.loop_runs.loop_paths`, which needs a controller that keeps no state of
        its own."""
        from .application import ApplicationRef
        from .loop_runs import loop_paths
        from .outcomes import run_outcomes
        scenario = self.without_monitor(scenario)
        rollout = functools.partial(loop_paths, ApplicationRef(self._loaded_as()), scenario,
                                    float(horizon), float(extend), int(stride), grid)
        return run_outcomes(rollout, starts, cache_dir=cache_dir, executor=executor,
                            progress=progress, label=f"{scenario.environment.name} paths")
