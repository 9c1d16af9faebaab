"""``reachwatch guard`` is a front end of the run's guard stage: it builds the run file
its flags describe (every other key the run file's default) and calls the stage's own
functions; what the online stages need of the plant goes through the application, whose
generic defaults say in one line what they do not implement."""

import dataclasses as dc
import re

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline import cli, online_stages
from reachwatch.pipeline.commands import fill_run_file_defaults
from reachwatch.pipeline.guard_commands import guard_spec
from reachwatch.pipeline.spec import RunSpec
from reachwatch.reach.application import Application, load_application
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.taxi.guarded import SCORE_PORT


def _args(*flags):
    return fill_run_file_defaults(cli.build_parser().parse_args(
        ["guard", "--scenario", "s.yaml", "--out", "o", *flags]))


def test_the_guard_command_describes_a_run_file_with_its_defaults():
    scenario = load_scenario(data="environment: {runway: KSFO, hour: 17.0, sky: clear}\n")
    spec, defaults = guard_spec(_args(), scenario), RunSpec()
    assert spec.guard == dc.replace(defaults.guard, environments=[scenario.environment])
    assert (spec.grid, spec.horizon, spec.slice_py) == (defaults.grid, defaults.horizon,
                                                        defaults.slice_py)
    assert spec.guard_environments() == [scenario.environment] and spec.scenario is scenario
    given = guard_spec(_args("--shape", "5", "3", "5", "--horizon", "2", "--fallbacks", "brake",
                             "--tradeoff-points", "2", "--check-starts", "3", "--seed", "5",
                             "--noise-starts", "4", "--noise-seed", "6", "--flag-budget", "0.2",
                             "--flag-budget-starts", "7", "--flag-budget-seed", "8",
                             "--mission-limit", "2"), scenario)
    assert (given.grid, given.horizon) == ([5, 3, 5], 2.0)
    assert dc.asdict(given.guard) == {**dc.asdict(defaults.guard),
                                      "environments": [dc.asdict(scenario.environment)],
                                      "strategies": ["brake"], "tradeoff_points": 2,
                                      "check_starts": 3, "check_seed": 5, "noise_starts": 4,
                                      "noise_seed": 6, "flag_budget": 0.2,
                                      "flag_budget_starts": 7, "flag_budget_seed": 8,
                                      "mission_limit": 2.0}


def test_the_guard_command_calls_the_stage_with_that_run_file(detector_path, tmp_path,
                                                              monkeypatch):
    seen = {}

    def stage(application, scenario, grid, spec, **kw):
        seen.update(application=application, scenario=scenario, grid=grid, spec=spec, **kw)
        raise KeyboardInterrupt       # what the test wanted: no sweep, no rendering
    monkeypatch.setattr(online_stages, "guard_figures", stage)
    path = tmp_path / "guarded.yaml"
    path.write_text(f"monitor: {{detector: {detector_path}, threshold: 0.3}}\n")
    assert cli.main(["-q", "guard", "--scenario", str(path), "--shape", "3", "3", "3",
                     "--fallbacks", "brake", "--check-starts", "2", "--cache",
                     str(tmp_path / "cache"), "--executor", "inline", "--out",
                     str(tmp_path / "out")]) == 130
    taxi = load_application(TAXI_APPLICATION)
    assert seen["application"] is taxi and seen["scenario"].monitor.threshold == 0.3
    assert seen["grid"] == taxi.grid(seen["scenario"], (3, 3, 3))
    assert seen["spec"].guard.strategies == ["brake"] and seen["spec"].guard.check_starts == 2
    assert str(seen["sweep_cache"]) == str(tmp_path / "cache" / "sweeps")
    assert str(seen["outcomes_cache"]) == str(tmp_path / "cache" / "outcomes")


def test_the_guard_needs_of_an_application_and_what_it_does_not_implement(tmp_path):
    taxi = load_application(TAXI_APPLICATION)
    assert taxi.score_port == SCORE_PORT            # the taxi's guarded sweep's port
    scenario = load_scenario(data="")
    for call, name, key in (
            (lambda: Application.fine_tune(taxi, scenario, None, [], None, tmp_path),
             "fine_tune", "incremental: {enabled: false}"),):
        with pytest.raises(NotImplementedError, match=rf"^Application\.{name}: .*'taxi'.* "
                                                      rf"set {re.escape(key)}$") as e:
            call()
        assert "\n" not in str(e.value)


def test_the_generic_trade_off_reads_the_applications_rollouts():
    """`Application.tradeoff_curves` and `flag_budget_threshold` need nothing of the
    plant but `fallback_rollouts` and `score_port`: a fake application's rollouts, where
    a start is flagged when its score reaches the threshold, give the known curve."""
    from reachwatch.reach.liveness import UNGUARDED, MissionOutcomes

    scores = np.linspace(0.0, 1.0, 5)

    def outcomes(flagged):
        n = len(flagged)
        return MissionOutcomes(failed=~flagged, stopped=flagged, ever_stopped=flagged,
                               distance=np.where(flagged, 0.0, 1.0),
                               flagged_ticks=flagged.astype(int), ticks=np.ones(n, int))

    def rollouts(scenario, grid, tables, horizon, fallbacks, *, threshold=None, starts=None,
                 alone=None, **settings):
        flagged = np.asarray(tables["s.score"]) >= threshold
        return {UNGUARDED: outcomes(np.zeros(len(flagged), bool)),
                **{f: outcomes(flagged) for f in fallbacks}}

    class Fake(Application):
        name, score_port = "fake", "s.score"
        fallback_rollouts = staticmethod(rollouts)
        loop_diagram = probe = dynamics = grid = None

    fake = Fake()
    curves = fake.tradeoff_curves(None, None, {"s.score": scores}, 1.0, ["stop"], 5)
    assert [r["threshold"] for r in curves["stop"]] == list(scores)
    assert [r["ended_stopped"] for r in curves["stop"]] == [1.0, 0.8, 0.6, 0.4, 0.2]
    assert [r["failure_set"] for r in curves["stop"]] == [0.0, 0.2, 0.4, 0.6, 0.8]
    chosen = fake.flag_budget_threshold(None, None, {"s.score": scores}, 1.0, "stop", 0.5,
                                        starts=np.zeros((5, 1)))
    assert chosen["flagged_ticks"] <= 0.5 and 0.5 < chosen["threshold"] <= 0.75


def test_a_nan_score_at_a_node_leaves_the_curves_thresholds_finite():
    """Before: one NaN made every quantile NaN: one row at threshold NaN, flagging all."""
    from reachwatch.reach.guard import tradeoff_curves
    seen = []

    def rollouts(fallbacks, *, threshold, alone, **settings):
        seen.append(threshold)
        raise StopIteration          # the thresholds are what is asked here
    try:
        tradeoff_curves(rollouts, [0.1, 0.5, float("nan"), 0.9], ["brake"], 3)
    except StopIteration:
        pass
    assert seen == [0.1]             # the first of 0.1, 0.5, 0.9: finite
    assert tradeoff_curves(rollouts, [float("nan")], ["brake"], 3) == {"brake": []}


def test_the_guard_stage_says_it_guards_with_its_own_detector_not_the_run_files(
        monkeypatch, caplog):
    """A run file's scenario.monitor.detector and threshold were replaced by the run's
    trained detector without a word."""
    import logging
    import types
    import reachwatch.systems.checks as checks
    from reachwatch.pipeline import online_stages
    monkeypatch.setattr(checks, "WARNED", set())

    class Reached(Exception):
        pass

    def stop(*args, **kwargs):
        raise Reached
    monkeypatch.setattr(online_stages, "guard_figures", stop)
    for text, said in (("monitor: {detector: mine.pt, threshold: 0.3}\n", True), ("", False)):
        run = types.SimpleNamespace(
            spec=types.SimpleNamespace(horizon=4.0, guard=types.SimpleNamespace(strategies=[])),
            outputs={"train": {"detector": "detectors/d.pt", "threshold": 0.5}},
            application=types.SimpleNamespace(resolved=lambda s: s),
            scenario_for=lambda env, text=text: _scenario_without_checks(text),
            path=lambda p: p, grid_for=lambda env: None, sweep_cache=None, executor=None,
            progress=False, log=lambda m: None)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="reachwatch"), pytest.raises(Reached):
            online_stages.guard_environment(run, None)
        assert ("the guard stage guards with the detector this run trains" in caplog.text) == said


def _scenario_without_checks(text):
    """A scenario whose monitor names a checkpoint that need not exist (not validated)."""
    from reachwatch.diagrams import load_scenario
    scenario = load_scenario(data="")
    if text:
        scenario.monitor.detector, scenario.monitor.threshold = "mine.pt", 0.3
    return scenario
