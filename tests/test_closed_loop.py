import numpy as np
import pytest

from reachwatch.diagrams import (CONTROL_PORT, PLANT, REFERENCE_TAXINET, ScenarioError,
                                 load_scenario, make_closed_loop_diagram, simulate)
from reachwatch.pipeline.cli import main
from reachwatch.taxi.taxinet_train import TaxiNetTrainConfig, train_taxinet
from reachwatch.diagrams import load_taxinet
from reachwatch.systems import CameraConfig
from reachwatch.taxi import OffRunway


@pytest.fixture(scope="module")
def nominal_loop():
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    return scenario, make_closed_loop_diagram(scenario)


def test_reference_checkpoint_is_shipped():
    model, preprocess_config, metadata = load_taxinet(REFERENCE_TAXINET)
    assert metadata["image_size"] == [200, 360]
    assert metadata["environment"] == "KMWH_9h_clear"
    # good at the nominal condition (measured on held-out renders at training time)
    assert metadata["validation"]["px_mean_m"] < 2.0


def test_closed_loop_structure(nominal_loop):
    _, diagram = nominal_loop
    names = {diagram.GetSubsystemByName(n).get_name() for n in
             ["taxi_plant", "controller", "steering_hold", "speed"]}
    assert len(names) == 4
    assert [diagram.get_output_port(i).get_name()
            for i in range(diagram.num_output_ports())] == ["state", "estimate"]
    system, port = CONTROL_PORT.split(".")
    assert diagram.GetSubsystemByName(system).GetOutputPort(port).size() == 1
    assert diagram.GetSubsystemByName(PLANT).num_continuous_states() == 3


def test_centreline_start_stays_on_runway_nominal(nominal_loop):
    scenario, diagram = nominal_loop
    trajectory = simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=3.0, period=0.05,
                          failed=OffRunway(10.0))
    assert not trajectory.failed
    assert np.abs(trajectory.state[:, 0]).max() < 4.0
    assert len(trajectory.time) == 61                        # one log per 0.05 s tick
    np.testing.assert_allclose(np.diff(trajectory.time), 0.05, atol=1e-9)
    assert trajectory.state[-1, 1] == pytest.approx(125.0, abs=0.5)   # 5 m/s


def test_steering_is_held_between_ticks(nominal_loop):
    """The camera renders and TaxiNet acts once per tick: within a tick theta moves
    at the constant rate tan(phi) of the steering sampled at the tick's start."""
    _, diagram = nominal_loop
    trajectory = simulate(diagram, initial_state=[4.0, 110.0, 0.0], duration=0.1, period=0.05,
                          failed=OffRunway(10.0))
    phi0 = np.deg2rad(-0.74 * trajectory.estimate[0, 0] - 0.44 * trajectory.estimate[0, 1])
    assert trajectory.state[1, 2] == pytest.approx(0.05 * np.tan(phi0), rel=1e-4, abs=1e-7)


def test_failure_stops_the_run(nominal_loop):
    _, diagram = nominal_loop
    trajectory = simulate(diagram, initial_state=[9.9, 110.0, np.deg2rad(28.0)],
                          duration=8.0, period=0.05, failed=OffRunway(10.0))
    assert trajectory.failed and trajectory.failure_time < 1.0
    assert trajectory.time[-1] < 1.0


def test_any_failure_rule_stops_the_run(nominal_loop):
    """`simulate` knows no runway: its ``failed`` is any function of the plant states.
    A rule on py (not the taxi's px) ends the run once py passes 111 m (about 5 m/s
    from 110); not stopping, the run logs every tick and fails at the first tick past
    it; without a rule it never fails."""
    _, diagram = nominal_loop
    past = lambda states: np.asarray(states)[:, 1] >= 111.0      # noqa: E731
    logged = simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=1.0, period=0.05,
                      failed=past, stop_on_failure=False)
    first = logged.time[np.argmax(logged.state[:, 1] >= 111.0)]
    assert logged.failed and len(logged.time) == 21 and 0.15 < first < 0.35
    assert logged.failure_time == first
    stopped = simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=1.0, period=0.05,
                       failed=past)
    assert stopped.failed and first - 0.05 < stopped.failure_time <= first + 1e-9
    assert stopped.time[-1] <= first + 1e-9
    never = simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=1.0, period=0.05)
    assert not never.failed and np.isnan(never.failure_time) and len(never.time) == 21
    with pytest.raises(ValueError, match="failed must be a function of the plant states .*"
                                         "got float"):
        simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=1.0, period=0.05,
                 failed=10.0)
    one_state = lambda x: bool(np.asarray(x).ravel()[1] >= 111.0)     # noqa: E731
    with pytest.raises(ValueError, match=r"failed gave shape \(\) for 1 states; a failure rule "
                                         r"maps states \(n, d\) to n bools"):
        simulate(diagram, initial_state=[0.0, 110.0, 0.0], duration=1.0, period=0.05,
                 failed=one_state)


def test_missing_controller_checkpoint_named():
    with pytest.raises(ScenarioError, match="controller.checkpoint"):
        load_scenario(data="controller: {checkpoint: /nonexistent/x.pt}\n")


def test_training_is_seeded_and_loadable(tmp_path):
    config = TaxiNetTrainConfig(camera=CameraConfig(width=90, height=50), samples=48,
                                epochs=3, batch_size=16, seed=7)
    meta_a = train_taxinet(config, tmp_path / "a.pt")
    meta_b = train_taxinet(config, tmp_path / "b.pt")
    a, _, _ = load_taxinet(tmp_path / "a.pt")
    b, _, _ = load_taxinet(tmp_path / "b.pt")
    for (name, pa), (_, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert np.array_equal(pa.numpy(), pb.numpy()), name
    assert meta_a["image_size"] == [50, 90] and meta_a["final_train_loss"] == \
        meta_b["final_train_loss"]


def test_cli_simulate_writes_trajectory_and_plot(tmp_path):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("duration: 1.0\ninitial_state: {px: 2.0, py: 120.0}\n")
    assert main(["simulate", "--scenario", str(scenario), "--out", str(tmp_path)]) == 0
    rows = np.loadtxt(tmp_path / "KMWH_9h_clear_trajectory.csv", delimiter=",", skiprows=1)
    assert rows.shape == (21, 6) and rows[0, 1] == pytest.approx(2.0)
    assert (tmp_path / "KMWH_9h_clear_trajectory.png").stat().st_size > 1000
    data = np.load(tmp_path / "KMWH_9h_clear_trajectory.npz")
    assert data["state"].shape == (21, 3) and list(data["axes"]) == ["px", "py", "theta"]
    header = (tmp_path / "KMWH_9h_clear_trajectory.csv").read_text().splitlines()[0]
    assert header == "t_s,px_m,py_m,theta_deg,px_hat_m,theta_hat_deg"
    assert np.allclose(rows[:, 3], np.rad2deg(data["state"][:, 2]), atol=1e-6)
    assert np.allclose(rows[:, 4:], data["estimate"], atol=1e-6)
    assert not data["failed"] and np.isnan(data["failure_time"])


def test_runs_of_one_diagram_without_a_context_share_its_own(nominal_loop, monkeypatch):
    """`simulate` without a Context runs in the diagram's own (`loop_context`), made
    once: a new Context per run would clone the render engine again, and clones of one
    engine spoil each other's frames. A run given a Context runs there."""
    from reachwatch.diagrams import closed_loop
    scenario, diagram = nominal_loop
    used, start = [], closed_loop.Simulator
    monkeypatch.setattr(closed_loop, "Simulator", lambda d, c: (used.append(c), start(d, c))[1])
    settings = dict(duration=0.3, period=0.05, failed=OffRunway(10.0))
    runs = [simulate(diagram, initial_state=x, **settings)
            for x in ([2.0, 110.0, 0.0], [-3.0, 140.0, 0.1], [2.0, 110.0, 0.0])]
    assert used[0] is used[1] is used[2] is closed_loop.loop_context(diagram)
    assert np.array_equal(runs[0].estimate, runs[2].estimate)
    assert np.array_equal(runs[0].state, runs[2].state)
    own = diagram.CreateDefaultContext()
    simulate(diagram, initial_state=[2.0, 110.0, 0.0], context=own, **settings)
    assert used[3] is own
