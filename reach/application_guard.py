"""The guard stage's part of an `Application` (``reachwatch guard`` and the run's guard
stage): its fallbacks rolled out in the guarded sweep's tables, the checks before
anything is swept, the detector's score along real runs and its variation between
the tables' nodes, and the guarded loop's runs. `GuardHooks` is a base of
`Application`, which defines the rest (`dynamics`, `probe`, `starts`, the real loop);
an application overrides any of these as it overrides the others."""

import dataclasses as dc
import functools

import numpy as np


class GuardHooks:
    """What the guard stage asks of an application (a base of `Application`)."""

    #: The port of the detector's score among the guarded sweep's tables.
    score_port = "anomaly_detector.score"
    #: ``true_estimate(states) -> (n, k)`` (a staticmethod): what the controller
    #: estimates, at its true value (the ``oracle`` steering of a fallback, and the
    #: truth of the prediction-error baseline, `training.baselines.EstimateError`);
    #: None: that steering is refused and there is no such baseline.
    true_estimate = None
    #: ``(k,)`` the units the controller's estimation errors are measured in (the
    #: prediction-error and ensemble baselines divide by them); empty: 1 each.
    estimate_scale = ()
    #: How a table of a run (``reachwatch simulate``'s ``.csv``) heads the controller's
    #: estimate's components, with their units (the taxi's: ``("px_hat_m",
    #: "theta_hat_deg")``); () = ``estimate_0``, ``estimate_1``, ...
    estimate_columns = ()
    #: ``carry_estimate(estimate, steering, speed, period) -> estimate`` (a
    #: staticmethod): an estimate carried forward by the plant's kinematics over a period
    #: (the ``dead_reckoning`` steering); None: that steering is refused.
    carry_estimate = None

    def stopping_time(self, scenario, deceleration: float) -> float:
        """Seconds braking at ``deceleration`` m/s^2 takes to stop the plant: how long
        ahead of a failure a monitor must warn for the braking fallback to prevent it
        (the monitor study's lead). Default: the controller's speed over the
        deceleration, for a plant whose speed follows its command at once; a plant whose
        speed lags its command, or that may run faster, says its own."""
        return scenario.controller.speed / deceleration

    def fallback_policy(self, scenario):
        """What a fallback that takes over the steering (``oracle``, ``dead_reckoning``)
        steers with: a function of ``(n, k)`` estimates to steering (rad); None (the
        default) = no such fallback."""
        return None

    def fallback_rollouts(self, scenario, grid, tables, horizon, fallbacks, **settings) -> dict:
        """{`reach.liveness.UNGUARDED` | fallback name: `reach.liveness.MissionOutcomes`}
        of the loop rolled out in the guarded sweep's ``tables`` (`sweep` with
        ``guarded``) from every node of ``grid`` or from ``starts``: the generic
        `reach.guarded_rollouts.fallback_rollouts` with the application's `dynamics`
        (which must take a ``speed``: `rolls_out_fallbacks`), its probe's control port,
        `score_port`, the controller's ``estimate`` port when it has one, and
        `fallback_policy`, `true_estimate` and `carry_estimate`. ``settings``:
        ``threshold`` (None: ``scenario.monitor``'s), ``starts``, ``mission_limit``,
        ``scores`` (instead of the swept ones), ``alone`` (the controller alone's
        outcomes, when already rolled out), ``score_noise`` and ``seed`` (the detector's
        variation between nodes, `reach.score_noise.ScoreNoise`)."""
        from reachwatch.diagrams.controller import ESTIMATE_OUTPUT
        from .guarded_rollouts import fallback_rollouts
        control_port = self.probe(scenario, guarded=True).control_port
        return fallback_rollouts(
            tables, grid, horizon, fallbacks, dynamics=self.dynamics(scenario),
            period=scenario.controller.period, monitor=scenario.monitor,
            control_port=control_port, score_port=self.score_port,
            estimate_port=f"{control_port.partition('.')[0]}.{ESTIMATE_OUTPUT}",
            policy=self.fallback_policy(scenario), truth=self.true_estimate,
            carry=self.carry_estimate, **settings)

    def rolls_out_fallbacks(self, scenario) -> bool:
        """Whether the guard stage can roll the fallbacks out in the swept tables: the
        application defines its own `fallback_rollouts`, or its `dynamics` take a
        ``speed`` (`reach.guarded_rollouts.takes_speed`). Else the stage is skipped."""
        from .guarded_rollouts import takes_speed
        return (type(self).fallback_rollouts is not GuardHooks.fallback_rollouts
                or takes_speed(self.dynamics(scenario)))

    def guard_refusals(self, scenario, strategies) -> dict:
        """``{index: why}`` for each of ``strategies`` (fallback names) that the guard
        stage would ask the application for what it does not have (a steering fallback
        without its hooks); empty when it cannot roll fallbacks out at all
        (`rolls_out_fallbacks`: the stage is skipped)."""
        from reachwatch.systems import Fallback
        if (not self.rolls_out_fallbacks(scenario)
                or type(self).fallback_rollouts is not GuardHooks.fallback_rollouts):
            return {}
        needs = {"oracle": ("fallback_policy", "true_estimate"),
                 "dead_reckoning": ("fallback_policy", "carry_estimate")}
        refusals = {}
        for i, name in enumerate(strategies):
            missing = [hook for hook in needs.get(Fallback.parse(name).steering, ())
                       if (self.fallback_policy(scenario) if hook == "fallback_policy"
                           else getattr(self, hook)) is None]
            if missing:
                refusals[i] = (f"needs the application's {' and '.join(missing)}, and "
                               f"'{self.name}' defines none")
        return refusals

    def check_guard(self, scenario, strategies, *, skipped: bool = True):
        """Before anything is swept: a ValueError in one line naming the run-file key when
        the guard stage would ask the application for what it does not have
        (`guard_refusals`), or when its `dynamics` roll out at another speed than
        ``scenario.controller.speed``, the real loop's. When it cannot roll fallbacks out at all
        (`rolls_out_fallbacks`), nothing if the stage is then ``skipped``, else the
        reason."""
        from .guarded_rollouts import check_takes_speed
        if not self.rolls_out_fallbacks(scenario):
            if not skipped:
                check_takes_speed(self.dynamics(scenario))
            return
        for i, why in self.guard_refusals(scenario, strategies).items():
            raise ValueError(f"guard.strategies[{i}]: '{strategies[i]}' {why}; leave it out")
        self.check_guard_speed(scenario)

    def check_guard_speed(self, scenario):
        """A ValueError in one line when the `dynamics` the guard's tables roll out
        (``dynamics(scenario).speed``) go at another speed than the real loop
        (``scenario.controller.speed``): the table's and the real loop's rows would
        disagree without a word."""
        if not self.rolls_out_fallbacks(scenario):
            return
        nominal = getattr(self.dynamics(scenario), "speed", None)
        if nominal is not None and not np.isclose(nominal, scenario.controller.speed):
            raise ValueError(f"the application '{self.name}': its "
                             f"dynamics(scenario).speed is {nominal:g}, and "
                             f"scenario.controller.speed {scenario.controller.speed:g}: the "
                             f"guard's tables would roll out at one speed and its real loop "
                             f"at the other; build the dynamics from scenario.controller.speed")

    def _table_rollouts(self, scenario, grid, tables, horizon):
        """`fallback_rollouts` of these tables: the ``rollouts`` of `reach.guard`."""
        return lambda fallbacks, **settings: self.fallback_rollouts(
            scenario, grid, tables, horizon, fallbacks, **settings)

    def tradeoff_curves(self, scenario, grid, tables, horizon, fallbacks, points: int, *,
                        mission_limit=None, alone=None, score_noise=None, seed=0) -> dict:
        """{fallback: rows} of the failure set against liveness over ``grid``'s nodes as
        the detector threshold sweeps ``points`` quantiles of the swept scores
        (`reach.guard.tradeoff_curves` of `fallback_rollouts`)."""
        from .guard import tradeoff_curves
        return tradeoff_curves(self._table_rollouts(scenario, grid, tables, horizon),
                               tables[self.score_port], fallbacks, points,
                               mission_limit=mission_limit, alone=alone,
                               score_noise=score_noise, seed=seed)

    def flag_budget_threshold(self, scenario, grid, tables, horizon, fallback: str,
                              budget: float, *, starts, mission_limit=None, score_noise=None,
                              seed=0, alone=None) -> dict:
        """The threshold at which ``fallback``'s loop, rolled out in the tables from
        ``starts``, flags ``budget`` of its control ticks, without labels
        (`reach.guard.flag_budget_threshold` of `fallback_rollouts`)."""
        from .guard import flag_budget_threshold
        return flag_budget_threshold(self._table_rollouts(scenario, grid, tables, horizon),
                                     fallback, budget, starts=starts,
                                     mission_limit=mission_limit, score_noise=score_noise,
                                     seed=seed, alone=alone)

    def score_runs(self, scenario, starts, *, duration: float, cache_dir, executor=None,
                   progress: bool = True) -> dict:
        """The detector's score (``scenario.monitor.detector``) at every control tick of
        the controller alone's real loop from each start for ``duration`` s, stopping at
        failure. Per start: ``state`` ``(T, n)``, ``score`` ``(T,)`` (NaN after the run
        ends), ``ticks`` and ``engaged`` (whether the speed left the nominal one all the
        same: such a run is not the controller alone's). Cached by content under
        ``cache_dir``, keyed by the detector but not by its threshold or fallback.
        Default: `reach.loop_runs.loop_scores` (the guarded loop, whose fallback never
        engages)."""
        from .application import ApplicationRef
        from .loop_runs import loop_scores
        from .outcomes import map_states
        scenario = self._watching(scenario)
        rollout = functools.partial(loop_scores, ApplicationRef(self._loaded_as()), scenario,
                                    float(duration))
        fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                                  progress=progress, unit="run",
                                  required=("state", "score", "ticks", "engaged"),
                                  label=f"detector score along real runs "
                                        f"{scenario.environment.name}")
        return fields

    def _watching(self, scenario):
        """`resolved` ``scenario`` with a monitor of its detector alone
        (`MonitorConfig.watching`): what runs that read the detector's score along the
        loop alone are keyed by, without run settings (`without_run_settings`)."""
        from .application import without_run_settings
        return without_run_settings(dc.replace(
            self.resolved(scenario),
            monitor=type(scenario.monitor).watching(scenario.monitor.detector)))

    def real_score_noise(self, scenario, grid, score_table, starts, *, duration: float,
                         cache_dir, executor=None, progress: bool = True):
        """The detector's variation between the nodes of the guarded sweep: a
        `reach.score_noise.ScoreNoise` fitted (`fit_score_noise`) to how the detector's
        score along real runs of the controller alone from ``starts`` (cached under
        ``cache_dir``) departs from ``score_table`` (the sweep's `score_port` on ``grid``)
        at the same states; ``(noise, {"runs", "ticks", "cut_at_box"})``. A ValueError
        when it cannot be fitted. Default: the runs of `score_runs` (the guarded loop,
        whose fallback never engages), along the distance `travelled_along`; a run whose
        fallback engaged all the same is left out (``{"left_out"}`` counts them)."""
        from .score_noise import fit_score_noise_on_runs
        fields = self.score_runs(scenario, starts, duration=duration, cache_dir=cache_dir,
                                 executor=executor, progress=progress)
        noise, fit = fit_score_noise_on_runs(
            grid, score_table, fields["state"], fields["score"], fields["ticks"],
            functools.partial(self.travelled_along, scenario), left_out=fields["engaged"])
        return noise, {**fit, "left_out": int(np.sum(fields["engaged"]))}

    def travelled_along(self, scenario, path) -> np.ndarray:
        """The distance (m) a run has travelled at each of its ticks' states ``path``
        ``(T, n)``, along which `real_score_noise` moves the detector's variation. Default:
        the nominal speed times the time (the taxi's: the distance on the ground)."""
        step = scenario.controller.speed * scenario.controller.period
        return step * np.arange(len(path))

    def mission_rollouts(self, scenario, fallback, duration: float, states, *,
                         mission_limit=None) -> dict:
        """The fields of `missions` from ``states``, run here and not cached (the guard
        stage's showcase tries a few candidate starts): the loop built as `missions`
        builds it, without run settings (`without_run_settings`)."""
        from .application import ApplicationRef, without_run_settings
        from .loop_runs import loop_missions
        scenario = (without_run_settings(self.resolved(scenario)) if fallback
                    else self.without_monitor(scenario))
        return loop_missions(ApplicationRef(self._loaded_as()), scenario, fallback,
                             float(duration), states, mission_limit=mission_limit)

    def simulate_guarded(self, scenario, start, folder, *, meshcat_html: bool = True):
        """The controller alone and the guarded loop of ``scenario`` (its monitor's
        fallback) from ``start`` (a state) for ``scenario.duration`` s, with their figure
        (and files) written to ``folder``: ``(alone, guarded, paths)``, two
        `reachwatch.diagrams.Trajectory` (``guarded`` with ``speed`` and ``anomaly``),
        each ``failed`` by `failed`. By default both loops (`loop_diagram`) run until
        the integrator step where `failed` holds, drawn by `plot_runs` or, where that
        draws nothing, against time (`reachwatch.diagrams.plots.plot_runs_over_time`);
        ``meshcat_html`` (a replay) is the taxi's."""
        from pathlib import Path
        from .loop_runs import failure_rule, run_until_failed
        rule = failure_rule(self, scenario)
        loops = [(self.without_monitor(scenario), False), (self.resolved(scenario), True)]
        diagrams = [self.loop_diagram(loop, guarded=guarded) for loop, guarded in loops]
        if not all(diagrams[1].HasOutputPort(port) for port in ("speed", "anomaly")):
            raise ValueError(f"the application '{self.name}': its guarded loop exports no "
                             f"'speed' and 'anomaly' (reachwatch.diagrams.export_loop_ports), "
                             f"which a guarded run's figure reads")
        alone, guarded = (run_until_failed(diagram, loop, rule, start, scenario.duration)[0]
                          for diagram, (loop, _) in zip(diagrams, loops))
        name = f"guarded_{scenario.environment.name}"
        labelled = [(alone, "controller alone"),
                    (guarded, f"guarded ({scenario.monitor.fallback.name})")]
        title = f"{scenario.environment.name}: from {np.round(np.asarray(start, float), 2)}"
        return alone, guarded, [self.draw_runs(labelled, scenario=scenario,
                                               path=Path(folder) / f"{name}.png", title=title)]
