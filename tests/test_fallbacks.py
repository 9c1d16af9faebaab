"""Fallbacks that keep moving, and liveness beside every failure figure: dead
reckoning tick by tick, in a Drake loop with a scheduled flag, in the rendered loop,
the table rollouts' liveness, and the liveness arithmetic on known answers."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ZeroOrderHold

from reachwatch.diagrams import (CONTROL_PORT, DETECTOR, add_dead_reckoning, load_scenario,
                                 make_guarded_diagram)
from reachwatch.diagrams.scenario import ControllerConfig
from reachwatch.reach.liveness import MISSION_FIELDS, MissionOutcomes, liveness_figures
from reachwatch.systems import (DeadReckoning, FallbackSwitch, FlagFilter, confirmed_flags,
                                ProportionalController, TaxiPlant, TrueStateEstimator,
                                fallback_parts, propagate_estimate,
                                taxi_dynamics)
from reachwatch.taxi import (UNGUARDED, dynamics_for, taxi_fallback_rollouts,
                             taxi_guarded_rollouts,
                             mission_rollouts, paper_grid, resolved, sweep_guarded)
from reachwatch.reach import InlineExecutor

PERIOD = 0.05


def test_propagate_estimate_is_the_plant_kinematics():
    x = np.array([1.0, 0.0, np.deg2rad(10.0)])
    for steering in (0.2, -0.05, 0.0):
        y = x.copy()
        for _ in range(4000):                    # fine Euler of the plant itself
            y = y + taxi_dynamics(y, steering, 4.0) * (PERIOD / 4000)
        np.testing.assert_allclose(propagate_estimate([1.0, 10.0], steering, 4.0, PERIOD),
                                   [y[0], np.rad2deg(y[2])], atol=1e-5)


def _reckon(flags, estimates, steering, speeds):
    """DeadReckoning alone: its output at each tick, inputs fixed per tick."""
    system = DeadReckoning(period=PERIOD)
    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    out = []
    for k, (flag, estimate, u, v) in enumerate(zip(flags, estimates, steering, speeds)):
        for port, value in ((system.get_anomaly_input_port(), [flag]),
                            (system.get_estimate_input_port(), estimate),
                            (system.get_steering_angle_input_port(), [u]),
                            (system.get_speed_input_port(), [v])):
            port.FixValue(context, value)
        if k == 0:
            simulator.Initialize()
        out.append(system.get_estimate_output_port().Eval(context).copy())
        simulator.AdvanceTo((k + 1) * PERIOD)   # runs the update at k * period on these inputs
    return np.array(out)


def test_dead_reckoning_tick_by_tick():
    flags = [1, 0, 1, 1, 0, 1]
    estimates = [[9.0, 9.0], [1.0, 5.0], [7.0, -7.0], [8.0, 8.0], [2.0, -3.0], [6.0, 6.0]]
    steering = [0.3, 0.1, -0.2, 0.05, 0.0, 0.1]
    speeds = [5.0, 5.0, 4.99, 4.98, 4.97, 5.0]
    out = _reckon(flags, estimates, steering, speeds)
    np.testing.assert_allclose(out[0], [9.0, 9.0])   # flagged, nothing trusted yet: as seen
    np.testing.assert_allclose(out[1], [1.0, 5.0])   # clear: the controller's estimate
    # flagged: the belief of the previous tick carried over the period with the steering
    # applied from it and the speed applied since (the speed input at this tick)
    two = propagate_estimate([1.0, 5.0], 0.1, 4.99, PERIOD)
    three = propagate_estimate(two, -0.2, 4.98, PERIOD)
    np.testing.assert_allclose(out[2], two)
    np.testing.assert_allclose(out[3], three)
    np.testing.assert_allclose(out[4], [2.0, -3.0])
    np.testing.assert_allclose(out[5], propagate_estimate([2.0, -3.0], 0.0, 5.0, PERIOD))
    system = DeadReckoning()
    assert not system.HasDirectFeedthrough(2, 0)     # steering feeds back without a loop
    with pytest.raises(ValueError, match="period"):
        DeadReckoning(period=0.0)


def test_switch_steers_from_the_fallback_input_only_while_flagged():
    for mode in ("dead_reckoning", "oracle"):
        switch = FallbackSwitch(nominal_speed=5.0, steering=mode)
        context = switch.CreateDefaultContext()
        switch.get_steering_angle_input_port().FixValue(context, [0.1])
        switch.get_fallback_steering_angle_input_port().FixValue(context, [-0.2])
        for flag, expected in ((1.0, -0.2), (0.0, 0.1)):
            switch.get_anomaly_input_port().FixValue(context, [flag])
            assert switch.get_steering_angle_output_port().Eval(context)[0] == pytest.approx(expected)
    assert fallback_parts("brake") == ("brake", "controller")
    assert fallback_parts("slow_down+dead_reckoning") == ("slow_down", "dead_reckoning")
    with pytest.raises(ValueError, match="'slow_down\\+gps'"):
        fallback_parts("slow_down+gps")


class _Schedule(LeafSystem):
    """Flag 1 on the ticks listed (a hand-made detector)."""

    def __init__(self, flagged_ticks):
        super().__init__()
        self._ticks = set(flagged_ticks)
        self.DeclareVectorOutputPort("anomaly", 1, self._calc)

    def _calc(self, context, output):
        output.SetAtIndex(0, float(round(context.get_time() / PERIOD) in self._ticks))


class _Corrupt(LeafSystem):
    """The true estimate, with ``bias`` added while the schedule flags (a camera gone bad)."""

    def __init__(self, bias):
        super().__init__()
        self._bias = np.asarray(bias, float)
        self._truth = self.DeclareVectorInputPort("truth", 2)
        self._flag = self.DeclareVectorInputPort("anomaly", 1)
        self.DeclareVectorOutputPort("estimate", 2, self._calc)

    def _calc(self, context, output):
        flagged = self._flag.Eval(context)[0] >= 0.5
        output.SetFromVector(self._truth.Eval(context) + (self._bias if flagged else 0.0))


def _scheduled_loop(steering, flagged_ticks, bias, x0, duration=3.0):
    """The taxi plant, a P-controller on a corruptible estimate and the fallback switch
    with ``steering`` (its dead-reckoning wired by `add_dead_reckoning`), flags from a
    schedule; the plant's states at every tick."""
    controller = ControllerConfig()
    builder = DiagramBuilder()
    plant = builder.AddSystem(TaxiPlant(initial_state=x0))
    truth = builder.AddSystem(TrueStateEstimator())
    flags = builder.AddSystem(_Schedule(flagged_ticks))
    corrupt = builder.AddSystem(_Corrupt(bias))
    p = builder.AddSystem(ProportionalController(px_gain=controller.px_gain,
                                                 theta_gain=controller.theta_gain))
    switch = builder.AddSystem(FallbackSwitch(nominal_speed=controller.speed, strategy="slow_down",
                                              steering=steering))
    hold = builder.AddSystem(ZeroOrderHold(PERIOD, 1))
    builder.Connect(plant.get_state_output_port(), truth.get_state_input_port())
    builder.Connect(truth.get_estimate_output_port(), corrupt.get_input_port(0))
    builder.Connect(flags.get_output_port(), corrupt.get_input_port(1))
    builder.Connect(corrupt.get_output_port(), p.get_estimate_input_port())
    builder.Connect(p.get_steering_angle_output_port(), switch.get_steering_angle_input_port())
    builder.Connect(flags.get_output_port(), switch.get_anomaly_input_port())
    if steering == "dead_reckoning":
        add_dead_reckoning(builder, estimate_port=corrupt.get_output_port(),
                           anomaly_port=flags.get_output_port(), switch=switch,
                           controller=controller, wheelbase=plant.wheelbase)
    builder.Connect(switch.get_steering_angle_output_port(), hold.get_input_port())
    builder.Connect(hold.get_output_port(), plant.get_steering_angle_input_port())
    builder.Connect(switch.get_speed_output_port(), plant.get_speed_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = plant.GetMyContextFromRoot(simulator.get_mutable_context())
    states = []
    for k in range(int(round(duration / PERIOD)) + 1):
        simulator.AdvanceTo(k * PERIOD)
        states.append(plant.get_state_output_port().Eval(context).copy())
    return np.array(states)


def test_dead_reckoning_rides_out_a_corrupted_estimate_in_a_drake_loop():
    """With the estimate corrupted while flagged (ticks 10-59), dead reckoning steers as
    if it had seen the truth: the loop follows the uncorrupted loop (which only slows
    down), while the controller's own steering follows the corruption metres away."""
    x0, bias, flagged = [3.0, 0.0, np.deg2rad(-8.0)], [-8.0, -20.0], range(10, 60)
    reference = _scheduled_loop("dead_reckoning", flagged, [0.0, 0.0], x0)
    reckoned = _scheduled_loop("dead_reckoning", flagged, bias, x0)
    own = _scheduled_loop("controller", flagged, bias, x0)
    np.testing.assert_allclose(reckoned, reference, atol=1e-4)
    assert np.max(np.abs(own[:, 0] - reference[:, 0])) > 2.0


def test_same_distance_figures_known_answer():
    """A straight run that leaves a 10 m runway after 36.1 m, with a detector that
    flags every tick. Alone it fails at 7.22 s, within the 8 s horizon. Slowing down
    (-0.01 m/s per tick) covers only 33.56 m in 8 s, so by the horizon it "survives":
    a 100 % cut that is only a delay, since the path is the same; judged at the same
    distance (40 m) it fails like the controller alone. Braking (-1 m/s^2) parks after
    12.375 m: it never fails, but falls short of the distance."""
    scenario = load_scenario(data="")
    dynamics = dynamics_for(scenario)
    grid = paper_grid(10.0, (3, 3, 3))
    theta = np.deg2rad(10.0)
    starts = np.array([[10.0 - 36.1 * np.sin(theta), 110.0, theta]])
    steer, always = np.zeros(grid.shape), np.ones(grid.shape)
    kw = dict(horizon=8.0, starts=starts, mission_limit=3.0)
    alone = taxi_guarded_rollouts(grid, dynamics, steer, None, **kw)
    slowed = taxi_guarded_rollouts(grid, dynamics, steer, always, strategy="slow_down", **kw)
    braked = taxi_guarded_rollouts(grid, dynamics, steer, always, strategy="brake", **kw)
    assert alone.failed.tolist() == alone.failed_same_distance.tolist() == [True]
    assert alone.distance[0] == pytest.approx(36.25)           # 145 ticks of 0.25 m
    assert slowed.failed.tolist() == [False] and slowed.distance[0] == pytest.approx(33.56)
    assert slowed.failed_same_distance.tolist() == [True]
    assert braked.stopped.tolist() == braked.short_of_distance.tolist() == [True]
    assert not braked.failed_same_distance.any()
    f = liveness_figures(alone, slowed)
    assert f["failure_cut"] == pytest.approx(1.0)
    assert f["same_distance_failure_cut"] == pytest.approx(0.0)
    assert f["short_of_distance"]["count"] == 0
    g = liveness_figures(alone, braked)
    assert g["same_distance_failure_cut"] == pytest.approx(1.0)
    assert g["short_of_distance"]["count"] == 1
    # without a mission limit the fields stay absent and the horizon figures are the same
    plain = taxi_guarded_rollouts(grid, dynamics, steer, always, strategy="slow_down", horizon=8.0,
                             starts=starts)
    assert not plain.has_same_distance and "same_distance_failure_cut" not in liveness_figures(
        alone, plain)
    assert plain.distance[0] == pytest.approx(slowed.distance[0])
    with pytest.raises(ValueError, match="or neither"):
        MissionOutcomes(failed=[1], stopped=[0], ever_stopped=[0], distance=[0],
                        flagged_ticks=[0], ticks=[1], failed_same_distance=[1])
    with pytest.raises(ValueError, match=">= 1"):
        taxi_guarded_rollouts(grid, dynamics, steer, None, horizon=8.0, starts=starts,
                         mission_limit=0.5)


# raw flags by tick, and the 2-of-3 rule's verdict worked out by hand
RAW = [1, 0, 1, 1, 0, 0, 1, 1, 1, 0]
TWO_OF_THREE = [0, 0, 1, 1, 1, 0, 0, 1, 1, 1]


def test_k_of_n_flags_tick_by_tick():
    history, got = np.zeros((1, 2), bool), []
    for raw in RAW:
        confirmed, history = confirmed_flags([raw], history, 2)
        got.append(int(confirmed[0]))
    assert got == TWO_OF_THREE
    # the same in a Drake loop, read as the switch reads it: sampled at every tick (a
    # zero-order hold, whose output between ticks is what it sampled at the last one)
    builder = DiagramBuilder()
    source = builder.AddSystem(_Schedule([t for t, r in enumerate(RAW) if r]))
    confirm = builder.AddSystem(FlagFilter(flags_needed=2, window=3, period=PERIOD))
    sample = builder.AddSystem(ZeroOrderHold(PERIOD, 1))
    builder.Connect(source.get_output_port(0), confirm.get_anomaly_input_port())
    builder.Connect(confirm.get_anomaly_output_port(), sample.get_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    seen, logged = [], []
    for tick in range(len(RAW)):
        simulator.AdvanceTo(tick * PERIOD)      # read at the tick, after its update (a logger)
        logged.append(int(confirm.get_anomaly_output_port().Eval(
            confirm.GetMyContextFromRoot(context))[0]))
        simulator.AdvanceTo((tick + 0.4) * PERIOD)
        seen.append(int(sample.get_output_port().Eval(sample.GetMyContextFromRoot(context))[0]))
    assert seen == logged == TWO_OF_THREE
    # 1 of 1 passes the raw flags through; bad rules are named
    one = FlagFilter(period=PERIOD)
    one_context = one.CreateDefaultContext()
    one.get_anomaly_input_port().FixValue(one_context, [1.0])
    assert one.get_anomaly_output_port().Eval(one_context)[0] == 1.0
    for k, n in ((3, 2), (0, 1), (True, 2), (1.5, 2)):
        with pytest.raises(ValueError, match="1 <= flags_needed"):
            FlagFilter(flags_needed=k, window=n)
    with pytest.raises(ValueError, match="monitor.flags_needed / monitor.flag_window"):
        load_scenario(data="{monitor: {flags_needed: 4, flag_window: 3}}")


def test_dead_reckoning_in_the_rendered_loop(detector_path, tmp_path):
    """The guarded diagram with dead reckoning in the real rendered loop: flagged from
    the first tick, nothing is trusted, so it steers like slow-down with TaxiNet; never
    flagged, it is TaxiNet alone (0 % stopped, the same failures); and the tables'
    rollouts of a sweep of it read the same verdicts."""
    def scenario(threshold):
        return resolved(load_scenario(data=f"monitor: {{detector: {detector_path}, "
                                           f"threshold: {threshold}}}\n"))
    starts = np.array([[6.0, 100.0, 0.3], [-1.0, 150.0, -0.1]])
    always = scenario(0.0)
    diagram = make_guarded_diagram(load_scenario(data=f"monitor: {{detector: {detector_path}, "
                                                      f"steering: dead_reckoning}}\n"))
    assert diagram.HasSubsystemNamed("dead_reckoning")
    reckoned = mission_rollouts(always, "slow_down+dead_reckoning", 3.0, starts)
    slowed = mission_rollouts(always, "slow_down", 3.0, starts)
    for name in ("failed", "distance", "flagged_ticks"):
        np.testing.assert_allclose(reckoned[name], slowed[name])
    # judged by distance too: the horizon's fields are unchanged, a failure within the
    # horizon is one before the distance, and braking parks short of it
    limited = mission_rollouts(always, "slow_down", 3.0, starts, mission_limit=3.0)
    for name in MISSION_FIELDS:
        np.testing.assert_allclose(limited[name], slowed[name])
    assert (limited["failed_same_distance"] >= limited["failed"]).all()
    parked = mission_rollouts(always, "brake", 3.0, starts[1:], mission_limit=3.0)
    assert parked["short_of_distance"].tolist() == [True] and not parked["failed"].any()
    never = scenario(1.0)
    alone = MissionOutcomes.from_fields(mission_rollouts(never, None, 3.0, starts))
    guarded = MissionOutcomes.from_fields(mission_rollouts(never, "slow_down+dead_reckoning",
                                                           3.0, starts))
    f = liveness_figures(alone, guarded)
    assert f["ended_stopped"]["count"] == 0 and f["flagged_ticks"] == 0.0
    assert f["failure_set"] == f["alone_failure_set"] and f["distance_ratio"] == pytest.approx(1.0)
    grid = paper_grid(10.0, (5, 2, 5))
    tables = sweep_guarded(never, grid, cache_dir=tmp_path, executor=InlineExecutor(),
                           progress=False)
    runs = taxi_fallback_rollouts(never, grid, tables, 3.0, ["slow_down+dead_reckoning"])
    np.testing.assert_array_equal(runs[UNGUARDED].failed, runs["slow_down+dead_reckoning"].failed)
    assert CONTROL_PORT in tables.tables and f"{DETECTOR}.score" in tables.tables


def test_guard_command_reports_liveness_and_the_real_loop_check(detector_path, tmp_path):
    import json
    from reachwatch.pipeline.cli import main
    path = tmp_path / "guarded.yaml"
    path.write_text(f"monitor: {{detector: {detector_path}, threshold: 0.5, "
                    f"resume_acceleration: 2.0}}\n")
    assert main(["-q", "guard", "--scenario", str(path), "--shape", "3", "3", "3", "--horizon",
                 "2", "--fallbacks", "brake", "slow_down+dead_reckoning", "--tradeoff-points",
                 "2", "--check-starts", "2", "--noise-starts", "3", "--flag-budget", "0.4",
                 "--flag-budget-starts", "20", "--executor", "inline", "--cache",
                 str(tmp_path / "cache"), "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "guard_KMWH_9h_clear.json").read_text())
    # the threshold the figures were made at is the flag budget's, chosen for the first fallback
    budget = record["flag_budget"]
    assert record["monitor"]["threshold"] == budget["threshold"] != 0.5
    assert (budget["scenario_threshold"], budget["fallback"], budget["starts"]) == (0.5, "brake", 20)
    assert budget["flagged_ticks"] <= 0.4
    assert set(record["liveness"]) == {"brake", "slow_down+dead_reckoning"}
    assert record["monitor"]["resume_acceleration"] == 2.0       # what produced the figures
    assert record["check"]["starts"] == 2
    noise = record["check"]["score_noise"]            # fitted here (the branches below
    assert noise["runs"] == 3 and noise["seed"] == 4000 and "error" not in noise, noise
    for both in record["check"]["fallbacks"].values():
        assert both["real"]["starts"] == both["table"]["starts"] == 2
        if "error" not in noise:
            assert both["table_with_noise"]["starts"] == 2
    # the trade-off curves again with the fitted noise, point for point, or none without a fit
    noisy = record["tradeoff_with_noise"]
    assert ({f: len(rows) for f, rows in noisy.items()} ==
            ({} if "error" in noise else {f: len(rows) for f, rows in record["tradeoff"].items()}))
    # and the grid's figures at the threshold, from the same alone runs
    assert set(record["liveness_with_noise"]) == (set() if "error" in noise
                                                  else set(record["liveness"]))
    for f, v in record["liveness_with_noise"].items():
        assert v["alone_failure_set"] == record["liveness"][f]["alone_failure_set"]
    assert (tmp_path / "tradeoff_KMWH_9h_clear.png").stat().st_size > 1000
