import numpy as np
import pytest

from reachwatch.diagrams import (CONTROL_PORT, DETECTOR, SWITCH, load_scenario, make_closed_loop_diagram,
                                 make_guarded_diagram, simulate)
from reachwatch.pipeline.cli import main
from reachwatch.reach import InlineExecutor
from reachwatch.taxi import OffRunway, dynamics_for, taxi_guarded_rollouts, paper_grid, sweep_guarded
from reachwatch.systems import FallbackSwitch, next_speed

def _switch_ticks(flags, **kwargs):
    """Speed after each 0.05 s tick of a FallbackSwitch simulated alone."""
    from pydrake.systems.analysis import Simulator
    switch = FallbackSwitch(**{"nominal_speed": 5.0, **kwargs})
    simulator = Simulator(switch)
    context = simulator.get_mutable_context()
    switch.get_steering_angle_input_port().FixValue(context, [0.1])
    switch.get_anomaly_input_port().FixValue(context, [0.0])
    simulator.Initialize()
    speeds = []
    for k, flag in enumerate(flags):
        switch.get_anomaly_input_port().FixValue(context, [float(flag)])
        simulator.AdvanceTo((k + 1) * 0.05)        # the update at t = k * 0.05 reads `flag`
        speeds.append(switch.get_speed_output_port().Eval(context)[0])
    return np.array(speeds)


def test_slow_down_schedule_tick_by_tick():
    speeds = _switch_ticks([1, 1, 1, 0, 1])
    np.testing.assert_allclose(speeds, [4.99, 4.98, 4.97, 5.0, 4.99])   # reset when clear


def test_brake_schedule_and_floor():
    speeds = _switch_ticks([1] * 120, strategy="brake", brake_deceleration=1.0)
    np.testing.assert_allclose(speeds[:3], [4.95, 4.90, 4.85])
    assert speeds.min() == 0.0 and np.all(np.diff(speeds) <= 0)
    np.testing.assert_allclose(next_speed(np.array([0.005, 3.0]), [True, False], nominal=5.0), [0.0, 5.0])


def test_resume_acceleration_tick_by_tick():
    """A clear frame inside a run of flagged ones: with the paper's rule the speed
    jumps back to nominal; with resume_acceleration it climbs back one tick's worth, so
    the braking goes on almost where it was."""
    flags = [1, 1, 1, 1, 0, 1, 1, 0, 0, 0]
    at_once = _switch_ticks(flags, strategy="brake", brake_deceleration=1.0)
    np.testing.assert_allclose(at_once, [4.95, 4.9, 4.85, 4.8, 5.0, 4.95, 4.9, 5.0, 5.0, 5.0])
    gradual = _switch_ticks(flags, strategy="brake", brake_deceleration=1.0,
                            resume_acceleration=2.0)
    np.testing.assert_allclose(gradual, [4.95, 4.9, 4.85, 4.8, 4.9, 4.85, 4.8, 4.9, 5.0, 5.0])
    # The table rollouts use the same rule as the LeafSystem.
    v, table = 5.0, []
    for f in flags:
        v = float(next_speed(v, f, strategy="brake", nominal=5.0, brake_deceleration=1.0,
                             resume_acceleration=2.0))
        table.append(v)
    np.testing.assert_allclose(table, gradual)
    for bad in (-1.0, float("nan"), "fast"):
        with pytest.raises(ValueError, match=f"resume_acceleration.*got {bad!r}"):
            FallbackSwitch(nominal_speed=5.0, resume_acceleration=bad)
    with pytest.raises(ValueError, match="monitor.resume_acceleration"):
        load_scenario(data="monitor: {resume_acceleration: -2.0}\n")


def test_switch_steering_modes_and_errors():
    switch = FallbackSwitch(nominal_speed=5.0, steering="oracle")
    context = switch.CreateDefaultContext()
    switch.get_steering_angle_input_port().FixValue(context, [0.1])
    switch.get_anomaly_input_port().FixValue(context, [1.0])
    with pytest.raises(ValueError, match="fallback_steering_angle"):
        switch.get_steering_angle_output_port().Eval(context)
    switch.get_fallback_steering_angle_input_port().FixValue(context, [-0.2])
    assert switch.get_steering_angle_output_port().Eval(context)[0] == pytest.approx(-0.2)
    switch.get_anomaly_input_port().FixValue(context, [0.0])
    assert switch.get_steering_angle_output_port().Eval(context)[0] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="strategy"):
        FallbackSwitch(nominal_speed=5.0, strategy="teleport")


def _scenario(detector_path, threshold, strategy="brake"):
    return load_scenario(data=f"monitor: {{detector: {detector_path}, threshold: {threshold},"
                              f" strategy: {strategy}, brake_deceleration: 4.0}}\n"
                              "duration: 8.0\n")


def test_guarded_diagram_structure(detector_path):
    diagram = make_guarded_diagram(_scenario(detector_path, 0.5))
    switch = diagram.GetSubsystemByName(SWITCH)
    detector = diagram.GetSubsystemByName(DETECTOR)
    assert [detector.get_output_port(i).get_name() for i in range(2)] == ["anomaly", "score"]
    assert [switch.get_output_port(i).get_name() for i in range(2)] == ["steering_angle", "speed"]
    for name in ["taxi_plant", "controller", "steering_hold"]:
        assert diagram.HasSubsystemNamed(name)
    assert [diagram.get_output_port(i).get_name() for i in range(5)] == [
        "state", "estimate", "speed", "anomaly", "score"]
    with pytest.raises(ValueError, match="monitor.detector"):
        make_guarded_diagram(load_scenario(data=""))


def test_guarded_run_survives_where_nominal_fails(detector_path, tmp_path):
    """Pick, from swept tables, a start that TaxiNet alone fails from and the braking
    pipeline saves; then check both verdicts in the real Drake loops."""
    scenario = _scenario(detector_path, 0.0)           # threshold 0: every image flagged
    grid = paper_grid(10.0, (12, 2, 9))
    tables = sweep_guarded(scenario, grid, cache_dir=tmp_path, executor=InlineExecutor(),
                           progress=False)
    dynamics = dynamics_for(scenario)
    steer, score = tables[CONTROL_PORT], tables[f"{DETECTOR}.score"]
    nominal_fail = taxi_guarded_rollouts(grid, dynamics, steer, None).failed
    guarded = taxi_guarded_rollouts(grid, dynamics, steer, score, threshold=0.0, strategy="brake",
                               brake_deceleration=4.0)
    saved = np.flatnonzero(nominal_fail & ~guarded.failed)
    assert len(saved) > 0 and guarded.ever_stopped.any()
    assert np.all(guarded.stopped[saved])           # braking at 4 m/s^2: every save is a stop
    x0 = grid.states([saved[len(saved) // 2]])[0]
    nominal = simulate(make_closed_loop_diagram(scenario), initial_state=x0, duration=8.0, period=0.05,
                       failed=OffRunway(10.0))
    guarded = simulate(make_guarded_diagram(scenario), initial_state=x0, duration=8.0, period=0.05,
                       failed=OffRunway(10.0))
    assert nominal.failed and not guarded.failed
    assert guarded.anomaly.min() == 1.0 and guarded.speed[-1] == 0.0


def test_never_flagging_pipeline_equals_taxinet_alone(detector_path):
    scenario = _scenario(detector_path, 1.0)           # threshold 1: nothing flagged
    x0 = [2.0, 120.0, np.deg2rad(-10.0)]
    a = simulate(make_closed_loop_diagram(scenario), initial_state=x0, duration=2.0, period=0.05,
                 failed=OffRunway(10.0))
    b = simulate(make_guarded_diagram(scenario), initial_state=x0, duration=2.0, period=0.05,
                 failed=OffRunway(10.0))
    np.testing.assert_allclose(a.state, b.state, atol=1e-9)
    assert np.all(b.speed == 5.0)
    # The loop alone watched by the detector (added through make_closed_loop_diagram's
    # prebuild_callback): the same run, and the guarded loop's score at every tick.
    from reachwatch.taxi.fidelity import make_watched_loop
    c = simulate(make_watched_loop(scenario), initial_state=x0, duration=2.0, period=0.05,
                 failed=OffRunway(10.0))
    np.testing.assert_allclose(c.state, a.state, atol=1e-9)
    assert a.score is None and c.score.shape == (len(c.time),)
    np.testing.assert_allclose(c.score, b.score, rtol=1e-6)
    assert len(np.unique(c.score)) > 1           # the score changes along the run


def test_cli_simulate_guarded_writes_plot_and_replay(detector_path, tmp_path):
    import socket
    from pydrake.geometry import Meshcat, MeshcatParams
    port = Meshcat(MeshcatParams(host="127.0.0.1")).port()    # the port a new server takes
    path = tmp_path / "s.yaml"
    path.write_text(f"monitor: {{detector: {detector_path}, threshold: 0.0, strategy: brake}}\n"
                    "duration: 1.0\n")
    assert main(["simulate", "--loop", "guarded", "--scenario", str(path),
                 "--out", str(tmp_path)]) == 0
    html = (tmp_path / "guarded_KMWH_9h_clear_brake.html").read_text()
    assert "<html" in html.lower() and len(html) > 10000
    assert (tmp_path / "guarded_KMWH_9h_clear_brake.png").stat().st_size > 1000
    with socket.socket() as s:       # the replay's Meshcat server is closed again
        assert s.connect_ex(("127.0.0.1", port)) != 0


def test_paired_rates_alternates_blocks_and_checks_arguments(monkeypatch):
    """Both loops run from the same start, advanced block by block in turn, the one
    going first alternating; each rate is ticks over its own blocks' wall time."""
    import reachwatch.diagrams.timing as timing
    from reachwatch.diagrams import make_state_feedback_diagram, paired_rates
    scenario = load_scenario(data="")
    reference, candidate = make_state_feedback_diagram(scenario), make_state_feedback_diagram(scenario)
    calls = []

    class FakeSimulator:
        def __init__(self, diagram, x0):
            self.name = "ref" if diagram is reference else "cand"
            calls.append(("start", self.name, list(x0)))

        def AdvanceTo(self, t):
            calls.append(("advance", self.name, round(t, 6)))

    monkeypatch.setattr(timing, "start_simulator",
                        lambda d, *, initial_state, context: (FakeSimulator(d, initial_state), {}))
    monkeypatch.setattr(timing, "_ticks", lambda simulator, period: 20)
    starts = [[0.0, 110.0, 0.0], [1.0, 120.0, 0.1]]
    ref, cand = paired_rates(reference, candidate, rounds=3, duration=1.0, period=0.05, block=0.5,
                             starts=starts)
    assert ref.shape == cand.shape == (3,) and np.all(ref > 0) and np.all(cand > 0)
    rounds = [calls[i:i + 6] for i in range(4, len(calls), 6)]   # after the warm-up round
    assert len(rounds) == 3
    assert [c[2] for r in rounds for c in r if c[0] == "start"] == [starts[0], starts[0],
                                                                   starts[1], starts[1],
                                                                   starts[0], starts[0]]
    for r in rounds:
        assert [(c[1], c[2]) for c in r if c[0] == "advance"] == [
            ("ref", 0.5), ("cand", 0.5), ("cand", 1.0), ("ref", 1.0)]
    with pytest.raises(ValueError, match="rounds >= 1"):
        paired_rates(reference, candidate, rounds=0, duration=1.0, period=0.05, starts=starts)
    with pytest.raises(ValueError, match="block > 0"):
        paired_rates(reference, candidate, rounds=1, duration=1.0, period=0.05, block=0.0,
                     starts=starts)
    with pytest.raises(ValueError, match="at least one start"):
        paired_rates(reference, candidate, rounds=1, duration=1.0, period=0.05, starts=[])


def test_paired_rates_times_real_runs():
    from reachwatch.diagrams import make_state_feedback_diagram, paired_rates
    diagram = make_state_feedback_diagram(load_scenario(data=""))
    ref, cand = paired_rates(diagram, diagram, rounds=2, duration=0.2, period=0.05, block=0.1,
                             starts=[[0.0, 110.0, 0.0]])
    assert ref.shape == cand.shape == (2,) and np.all(ref > 0) and np.all(cand > 0)
