"""The monitor study's runs in the guarded real loop: the oracle monitor goes on from
the recorded states as the loop alone does, stops are needless only of runs that survive
the risk's horizon, the watch past a recording, and the rows of runs that cannot flag."""

from dataclasses import replace as dc_replace

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline.monitor_guarded import oracle_flag_ticks
from reachwatch.taxi.application import TAXI_APPLICATION


def test_the_oracle_goes_on_from_a_recorded_state_as_the_loop_alone_does(tmp_path):
    """The oracle's guarded runs start at its flag from the recorded state there: the
    loop alone started from a recorded state of a failing run fails when the recording
    did, so that state is all the loop carries; the oracle flags one lead (and a tick)
    before the failure; braking from its flag, flagged at every tick, saves the run."""
    from reachwatch.diagrams import MonitorConfig
    from reachwatch.reach.application import load_application
    application = load_application(TAXI_APPLICATION)
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    period = scenario.controller.period
    B = scenario.environment.half_width
    starts = np.array([[B - 3.0, 100.0, 0.6], [-(B - 5.0), 100.0, -0.8]])  # heading out
    runs = application.recorded_runs(scenario, starts, duration=3.0, height=16, width=24,
                                     cache_dir=tmp_path / "runs", progress=False)
    failure = runs["failure_time"]
    assert np.all(np.isfinite(failure)) and np.all(failure > 0.5)
    lead = 0.5
    flag = oracle_flag_ticks(runs["ticks"], failure, period=period, lead=lead)
    assert np.allclose(flag * period, np.ceil((failure - lead - period - 1e-9) / period) * period)
    states = np.stack([runs["state"][i, k] for i, k in enumerate(flag)])
    alone = application.missions(scenario, states, duration=3.0, cache_dir=tmp_path / "m",
                                 progress=False)
    assert alone.failed.all()
    assert np.allclose((alone.ticks - 1) * period, failure - flag * period, atol=1e-6)
    detector = tmp_path / "always.pt"          # any history monitor: threshold 0 flags all
    _save_tiny_history_monitor(detector)
    braked = application.missions(
        dc_replace(scenario, monitor=MonitorConfig(detector=str(detector), threshold=0.0,
                                                   strategy="brake", brake_deceleration=3.0)),
        states, fallback="brake", duration=3.0, cache_dir=tmp_path / "m", progress=False)
    assert np.all(braked.flagged_ticks == braked.ticks)
    assert np.all(braked.distance < alone.distance)
    # the guarded-loop row of the oracle from those recordings: braking from one stop's
    # lead (5/3 s at 3 m/s^2) before each failure
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_guarded import _oracle_guarded
    group = {**runs, "environment": scenario.environment, "name": scenario.environment.name}
    from_start = application.missions(scenario, starts, duration=3.0, cache_dir=tmp_path / "m",
                                      progress=False)
    row = _oracle_guarded(SimpleNamespace(duration=3.0, brake_deceleration=3.0), application,
                          scenario, [group], [from_start], [np.zeros(2, bool)], str(detector),
                          lead=5.0 / 3.0,
                          cache_dir=tmp_path / "m", executor=None, progress=False)
    assert row["failed_alone"] == 2
    assert row["prevented"] + row["failed_guarded"] == 2 and row["prevented"] >= 1
    assert 0 < row["distance_guarded_m"] < row["distance_alone_m"]


def test_a_stop_is_needless_only_of_a_run_that_survives_the_risks_horizon_past_the_window():
    """Four runs: one the loop alone fails within the window (the guarded loop saves it:
    prevented), one it fails within ``within`` s after the window (stopped: neither
    needless nor prevented), one it survives both (stopped: needless) and one it
    survives unstopped."""
    from reachwatch.pipeline.monitor_guarded import judged_runs
    row = judged_runs("E", failed_alone=[True, False, False, False],
                      failed_after=[False, True, False, False],
                      failed_guarded=[False, False, False, False],
                      stopped=[True, True, True, False])
    assert row == {"environment": "E", "runs": 4, "failed_alone": 1, "failed_guarded": 0,
                   "prevented": 1, "failing_after": 1, "stopped_failing_after": 1,
                   "safe_alone": 2, "needless_stops": 1}
    with pytest.raises(ValueError, match="does not repeat its recordings"):
        judged_runs("E", [True], [True], [False], [False])


@pytest.mark.parametrize("memoryless", [True, False])
def test_the_guarded_rows_judge_stops_on_the_studys_longer_watch(tmp_path, monkeypatch,
                                                                 memoryless):
    """`guarded_rows` reads which runs fail soon after the window from the recordings'
    watched failure times, and counts a stop of one of them apart from the needless
    ones (a stand-in application, no render). A controller that keeps state of its own
    gets no oracle row (it goes on from recorded states), said in one line."""
    from types import SimpleNamespace
    from reachwatch.pipeline import monitor_guarded
    from reachwatch.pipeline.monitor_guarded import ORACLE, guarded_rows
    monkeypatch.setattr(monitor_guarded, "continues_from_recordings",
                        lambda application, scenario: memoryless)
    said = []
    from reachwatch.reach.liveness import MissionOutcomes
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    starts = np.arange(12.0).reshape(4, 3)

    def missions(sc, from_starts, *, duration, fallback=None, **_):
        n = len(from_starts)
        assert duration == 8.0
        stopped = np.isin(from_starts[:, 0], [3.0, 6.0]) if fallback else np.zeros(n, bool)
        return MissionOutcomes(failed=np.zeros(n, bool), stopped=stopped,
                               ever_stopped=stopped, distance=np.full(n, 5.0 if fallback else 40.0),
                               flagged_ticks=np.zeros(n), ticks=np.full(n, 10))

    # no run fails within the 8 s; run 1 (stopped) fails at 9.5 s; run 2 (stopped) never
    group = {"environment": scenario.environment, "name": "E", "starts": starts,
             "ticks": np.full(4, 160), "failure_time": np.full(4, np.nan),
             "watched_failure_time": np.array([np.nan, 9.5, np.nan, np.nan]),
             "state": np.zeros((4, 160, 3))}
    spec = SimpleNamespace(duration=8.0, within=4.0, guarded_runs=4, brake_deceleration=3.0)
    rows = guarded_rows(spec, SimpleNamespace(missions=missions), scenario, [group],
                        {"m": ("model", "platt", 0.5, [1, 1])}, {"m": "m.pt"},
                        risks={"m": [[np.full(160, 0.9)] * 4]},   # each may flag: rendered
                        cache_dir=tmp_path, executor=None, progress=False, log=said.append,
                        lead=5.0 / 3.0)
    row = rows["m"]
    assert (row["failing_after"], row["stopped_failing_after"]) == (1, 1)
    assert (row["safe_alone"], row["needless_stops"]) == (3, 1)
    assert rows["m"]["needless_rate"]["of"] == 3
    if memoryless:
        assert rows[ORACLE]["safe_alone"] == 3 and rows[ORACLE]["needless_stops"] == 0
    else:
        assert ORACLE not in rows and any("keeps state of its own" in m for m in said)


def test_guarded_runs_that_cannot_flag_are_the_loop_alones(tmp_path):
    """`guarded_missions` renders the runs whose recorded risk reaches the threshold
    (or comes within the margin of it) and the first that does not; the others are
    the loop alone's. A quiet run that comes out otherwise stops it with one line."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_guarded import QUIET_MARGIN, guarded_missions
    from reachwatch.reach.liveness import MissionOutcomes

    def outcomes(first, n, braked):
        stopped = braked & (first % 2 == 1)             # odd starts brake to a stop
        return MissionOutcomes(failed=~stopped & (first >= 4), stopped=stopped,
                               ever_stopped=stopped, distance=np.where(stopped, 3.0, first),
                               flagged_ticks=np.where(stopped, 5, 0), ticks=np.full(n, 20))

    asked = []

    def missions(sc, from_starts, *, fallback=None, **_):
        asked.append(from_starts[:, 0].tolist())
        return outcomes(from_starts[:, 0], len(from_starts), fallback == "brake")

    starts = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    alone = outcomes(starts[:, 0], 6, False)
    # runs 1 and 3 reach the threshold 0.5, run 5 comes within the margin; 0, 2, 4 do not
    peaks = [0.1, 0.7, 0.2, 0.5, 0.3, 0.5 - QUIET_MARGIN / 2]
    guarded, rendered = guarded_missions(
        SimpleNamespace(missions=missions), None, starts, alone, peaks, 0.5, duration=8.0,
        cache_dir=tmp_path, executor=None, progress=False, what="m in E")
    assert asked == [[0.0, 1.0, 3.0, 5.0]] and rendered == 4      # run 0: the check
    everything = outcomes(starts[:, 0], 6, True)
    for name, value in everything.as_fields().items():
        np.testing.assert_array_equal(getattr(guarded, name), value, err_msg=name)
    # a quiet run that the guarded loop changes: not the loop alone, or not its monitor
    with pytest.raises(RuntimeError, match=r"m in E: run 1 never reaches the threshold.*"
                                           r"differs from the loop alone in \['stopped'"):
        guarded_missions(SimpleNamespace(missions=missions), None, starts, alone,
                         [0.6, 0.1, 0.6, 0.1, 0.6, 0.6], 0.5, duration=8.0,
                         cache_dir=tmp_path, executor=None, progress=False, what="m in E")
    with pytest.raises(ValueError, match="6 starts, 6 runs alone and 2 recorded risks"):
        guarded_missions(SimpleNamespace(missions=missions), None, starts, alone, [0.1, 0.2],
                         0.5, duration=8.0, cache_dir=tmp_path, executor=None,
                         progress=False, what="m in E")


def test_the_watch_goes_on_from_the_last_recorded_state(tmp_path):
    """A run that survives its recording is watched on from its last recorded state
    (the taxi's controller keeps no state of its own), and fails when the loop alone
    from its start does; a loop whose recorded state is not all it carries is refused
    with one line."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_runs import (continues_from_recordings,
                                                  watched_failure_times)
    from reachwatch.reach.application import load_application
    application = load_application(TAXI_APPLICATION)
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    B = scenario.environment.half_width
    starts = np.array([[B - 3.0, 100.0, 0.6], [-(B - 5.0), 100.0, -0.8], [0.0, 100.0, 0.0]])
    assert continues_from_recordings(application, scenario)
    spec = SimpleNamespace(duration=0.5, within=2.5)
    recorded = application.recorded_runs(scenario, starts, duration=spec.duration, height=16,
                                         width=24, cache_dir=tmp_path / "runs", progress=False)
    assert not np.isfinite(recorded["failure_time"]).any()        # each survives 0.5 s
    common = dict(cache_dir=tmp_path / "m", executor=None, progress=False)
    whole = watched_failure_times(spec, application, scenario, starts,
                                  recorded["failure_time"], **common)
    on = watched_failure_times(spec, application, scenario, starts, recorded["failure_time"],
                               recorded=recorded, **common)
    assert np.isfinite(whole[:2]).all() and np.all(whole[:2] > 0.5) and np.isnan(whole[2])
    np.testing.assert_allclose(on, whole, atol=1e-6)
    # a recording whose last state is not the loop's: its first run disagrees
    moved = {**recorded, "state": recorded["state"].copy()}
    moved["state"][:, -1, 0] = 0.0                   # back on the centre line
    with pytest.raises(RuntimeError, match="from its last recorded state, run 0 fails at "
                                           "nan s, from its start at") as error:
        watched_failure_times(spec, application, scenario, starts, recorded["failure_time"],
                              recorded=moved, **common)
    assert "\n" not in str(error.value)
    # a controller that keeps state of its own: watched from the starts
    from pydrake.systems.framework import DiagramBuilder, LeafSystem

    class Counter(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclareDiscreteState(1)

    builder = DiagramBuilder()
    builder.AddNamedSystem("controller", Counter())
    stateful = builder.Build()
    stand_in = SimpleNamespace(without_monitor=lambda sc: sc, loop_diagram=lambda sc: stateful,
                               probe=lambda sc: SimpleNamespace(control_port="controller.u"))
    assert not continues_from_recordings(stand_in, scenario)


def test_a_failure_just_after_the_recording_is_at_the_next_tick(tmp_path):
    """A loop that stops at the crossing logs the tick before it: a run that survived
    its recording and leaves the safe set before the next tick fails at that next
    tick, not at the recording's last; one that fails before the recording's end is
    refused in one line (a stand-in application, no render)."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_runs import watched_failure_times
    from reachwatch.reach.liveness import MissionOutcomes
    scenario = load_scenario(data="")
    spec = SimpleNamespace(duration=8.0, within=4.0)

    def stand_in(ticks):
        def missions(sc, starts, *, duration, **_):
            n = len(starts)
            return MissionOutcomes(failed=np.ones(n, bool), stopped=np.zeros(n, bool),
                                   ever_stopped=np.zeros(n, bool), distance=np.ones(n),
                                   flagged_ticks=np.zeros(n), ticks=np.full(n, ticks))
        return SimpleNamespace(missions=missions)

    common = dict(cache_dir=tmp_path, executor=None, progress=False)
    starts, survived = np.zeros((1, 3)), np.array([np.nan])
    for ticks, at in [(161, 8.05), (162, 8.05), (200, 9.95), (242, np.nan)]:
        got = watched_failure_times(spec, stand_in(ticks), scenario, starts, survived, **common)
        np.testing.assert_allclose(got, [at], err_msg=str(ticks))
    with pytest.raises(RuntimeError, match="fails within 8 s from a start whose recorded run "
                                           "did not"):
        watched_failure_times(spec, stand_in(160), scenario, starts, survived, **common)


def test_recorded_runs_of_every_environment_are_in_flight_together(tmp_path):
    """On a pool, the study's recordings (and their watch) of all environments share one
    window of chunks; the groups are those recorded one environment after another."""
    import concurrent.futures as cf
    import threading
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_runs import record_split
    from reachwatch.reach.application import load_application
    from reachwatch.reach.executors import InlineExecutor

    class Pool(cf.ThreadPoolExecutor):
        """Notes which environments' chunks it holds at once (by the submitting thread)."""

        def __init__(self):
            super().__init__(2)
            self.lock, self.held, self.both = threading.Lock(), {}, False

        def submit(self, fn, /, *args, **kwargs):
            future = super().submit(fn, *args, **kwargs)
            with self.lock:
                self.held[future] = threading.current_thread().name
                self.both |= len(set(self.held.values())) > 1
            future.add_done_callback(lambda f: self.held.pop(f, None))
            return future

    application, scenario = load_application(TAXI_APPLICATION), load_scenario(data="")
    spec = SimpleNamespace(duration=0.5, within=0.5, height=16, width=24,
                           family=SimpleNamespace(seed=3))
    envs = [load_scenario(data=f"environment: {{runway: {r}, hour: 9.0, sky: clear}}\n"
                          ).environment for r in ("KMWH", "KSFO")]
    common = dict(runs=3, progress=False)
    alone = record_split(spec, application, scenario, envs, 0, cache_dir=tmp_path / "a",
                        executor=InlineExecutor(), **common)
    with Pool() as pool:
        together = record_split(spec, application, scenario, envs, 0, cache_dir=tmp_path / "b",
                               executor=pool, **common)
    assert pool.both
    assert [g["name"] for g in together] == [g["name"] for g in alone] == [e.name for e in envs]
    for a, b in zip(alone, together):
        assert len(a["ticks"]) == len(b["ticks"]) == 3
        for key in ("frames", "state", "ticks", "failure_time", "watched_failure_time",
                    "starts"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_frames_read_back_are_the_recorded_ones_and_not_held(tmp_path, monkeypatch):
    """A split recorded with ``frames_read_back`` holds no frames (a protocol's judged
    runs are gigabytes of them), not even while its runs are watched on (which renders
    for minutes while every other environment's runs come in); `recorded_frames` reads
    back the very frames the same runs record; a split name that is not recorded is
    refused."""
    from types import SimpleNamespace
    from reachwatch.pipeline import monitor_runs
    from reachwatch.pipeline.monitor_runs import record_splits, recorded_frames
    watch, held_while_watched = monitor_runs.watched_failure_times, []

    def watched(*args, recorded=None, **kwargs):
        held_while_watched.append(recorded is not None and "frames" in recorded)
        return watch(*args, recorded=recorded, **kwargs)
    monkeypatch.setattr(monitor_runs, "watched_failure_times", watched)
    from reachwatch.reach.application import load_application
    application, scenario = load_application(TAXI_APPLICATION), load_scenario(data="")
    spec = SimpleNamespace(duration=0.5, within=0.5, height=16, width=24,
                           family=SimpleNamespace(seed=3))
    envs = [load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n"
                          ).environment]
    common = dict(cache_dir=tmp_path, executor=None, progress=False)
    splits = {"train": (envs, 0, 2, None), "judged": (envs, 1, 2, None)}
    held = record_splits(spec, application, scenario, splits, **common)
    read_back = record_splits(spec, application, scenario, splits, frames_read_back=["judged"],
                              **common)
    assert "frames" in read_back["train"][0] and "frames" not in read_back["judged"][0]
    # each recording given to its watch (the loop continues from it): the judged one without
    # its frames
    assert held_while_watched == [True, True, True, False]
    for k in splits:
        frames = recorded_frames(read_back[k][0])
        assert frames.shape[:2] == (2, 11) and frames.any()
        np.testing.assert_array_equal(frames, held[k][0]["frames"], err_msg=k)
    with pytest.raises(ValueError, match=r"frames_read_back names splits \['held_out'\]"):
        record_splits(spec, application, scenario, splits, frames_read_back=["held_out"],
                      **common)


def _save_tiny_history_monitor(path):
    from reachwatch.diagrams import save_checkpoint
    from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel
    config = HistoryMonitorConfig(height=16, width=24)
    model = HistoryRiskModel(config)
    save_checkpoint(path, kind="history_monitor", model=model, model_config=config,
                    preprocess_config=None, metadata={"calibration": [1.0, 0.0],
                                                      "threshold": 0.0})


def test_the_oracle_refuses_recordings_the_loop_alone_does_not_repeat(tmp_path):
    """Recordings that do not match the loop alone (another loop, a nondeterministic
    one) stop the oracle's row with one line instead of giving it."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_guarded import _oracle_guarded
    from reachwatch.reach.application import load_application
    application = load_application(TAXI_APPLICATION)
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    period = scenario.controller.period
    group = {"ticks": np.array([40]), "failure_time": np.array([39 * period]),
             "state": np.zeros((1, 40, 3)), "environment": scenario.environment,
             "name": scenario.environment.name}
    safe = SimpleNamespace(failed=np.array([False]), distance=np.array([10.0]))
    with pytest.raises(RuntimeError, match="disagree on failing") as error:
        _oracle_guarded(SimpleNamespace(duration=3.0, brake_deceleration=3.0), application,
                        scenario, [group], [safe], [np.zeros(1, bool)], "unused.pt", lead=1.0,
                        cache_dir=tmp_path, executor=None, progress=False)
    assert "\n" not in str(error.value)


def test_the_loop_alone_read_off_recordings_that_stop_at_the_crossing(tmp_path):
    """A loop that stops at the crossing itself (the taxi's) fails after its last
    logged tick: the loop alone's outcome read off its recording covers the stretch to
    the failure, as its run does (`alone_from_recordings`, a stand-in application)."""
    from types import SimpleNamespace
    from reachwatch.pipeline.monitor_runs import alone_from_recordings
    from reachwatch.reach.liveness import MissionOutcomes, travelled
    scenario = load_scenario(data="")
    period, speed = scenario.controller.period, scenario.controller.speed
    # run 0 survives 1 s (21 ticks); run 1 logs 5 ticks and crosses 0.6 period later
    group = {"ticks": np.array([21, 5]), "failed": np.array([False, True]),
             "failure_time": np.array([np.nan, 4.6 * period]), "starts": np.zeros((2, 3))}
    ticks = np.arange(21) * period                  # as the loop's runs travel them
    ran = MissionOutcomes(failed=[False, True], stopped=[False, False],
                          ever_stopped=[False, False],
                          distance=[travelled(ticks, np.full(21, speed)),
                                    travelled(ticks[:5], np.full(5, speed), 4.6 * period)],
                          flagged_ticks=[0, 0], ticks=[20, 5])
    assert ran.distance[1] == pytest.approx(speed * 4.6 * period)
    application = SimpleNamespace(missions=lambda sc, starts, **_: ran)
    read = alone_from_recordings(application, scenario, group, 2, duration=1.0,
                                 cache_dir=tmp_path, executor=None, progress=False)
    for name, value in ran.as_fields().items():
        np.testing.assert_allclose(getattr(read, name), value, err_msg=name)
