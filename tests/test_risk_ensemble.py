"""An ensemble of history monitors: online (one `HistoryMonitor` of the ensemble, in a
real rendered loop) it outputs at each tick the offline mean of its members' raw risks,
calibrated; its members' encoders run as one `GroupedEncoder` with each member's
features; its checkpoint holds every member and refuses a bad member count by name."""

import numpy as np
import pytest
import torch

from reachwatch.diagrams import DETECTOR, load_scenario, save_checkpoint, simulate
from reachwatch.diagrams.checkpoints import CheckpointError, load_history_monitor
from reachwatch.systems import (GroupedEncoder, HistoryMonitor, HistoryMonitorConfig,
                                HistoryRiskEnsemble, HistoryRiskModel, check_members,
                                grouped_gru, platt)
from reachwatch.systems.detector import inference_model
from reachwatch.taxi import OffRunway
from reachwatch.taxi.fidelity import make_watched_loop
from reachwatch.taxi.history import record_runs


def _members(config, count, seed=0):
    out = []
    for m in range(count):
        torch.manual_seed(seed + m)
        model = HistoryRiskModel(config)
        for p in model.parameters():             # spread the raw risk over (0, 1)
            p.data.mul_(3.0)
        out.append(model.eval())
    return out


def _save(path, ensemble, calibration=(0.6, 0.2), members=None):
    save_checkpoint(path, kind="history_monitor", model=ensemble, model_config=ensemble.config,
                    preprocess_config=None,
                    metadata={"calibration": list(calibration), "threshold": 0.5,
                              "members": len(ensemble.members) if members is None else members})
    return path


def test_online_the_ensemble_outputs_the_calibrated_mean_of_its_members(tmp_path):
    config = HistoryMonitorConfig(frames=3, stride=2, height=24, width=40, channels=[4, 8],
                                  features=6, signals=3, signal_mean=[0.1] * 3,
                                  signal_std=[2.0] * 3, temporal="gru", hidden=8)
    members = _members(config, 3)
    path = _save(tmp_path / "ensemble.pt", HistoryRiskEnsemble.of(members))
    model, _, metadata = load_history_monitor(path)
    assert isinstance(model, HistoryRiskEnsemble) and len(model.members) == 3
    for loaded, trained in zip(model.members, members):
        for a, b in zip(loaded.state_dict().values(), trained.state_dict().values()):
            assert torch.equal(a, b)
    scenario = load_scenario(data=f"monitor: {{detector: {path}, threshold: 0.5}}\n")
    start = np.array([[2.0, 120.0, 0.1]])
    recorded = record_runs(scenario, 0.6, 24, 40, start)
    ticks = int(recorded["ticks"][0])
    diagram = make_watched_loop(scenario)
    names = {s.get_name() for s in diagram.GetSystems()}
    assert DETECTOR in names and not any("member" in name for name in names)
    run = simulate(diagram, initial_state=start[0], duration=0.6, period=0.05,
                   failed=OffRunway(scenario.environment.half_width))
    frames, signals = recorded["frames"][0, :ticks], recorded["signals"][0, :ticks]
    each = [m.risk_sequence(frames, signals) for m in members]
    offline = model.risk_sequence(frames, signals, calibration=lambda q: platt(q, 0.6, 0.2))
    np.testing.assert_allclose(offline, platt(np.mean(each, axis=0), 0.6, 0.2))
    np.testing.assert_allclose(run.score, offline, rtol=1e-4, atol=1e-5)
    # the members disagree: the mean is none of them
    assert min(np.abs(np.mean(each, axis=0) - e).max() for e in each) > 1e-3


def _spread_batch_norms(model, seed):
    """Running statistics other than a fresh layer's, so folding them matters."""
    generator = torch.Generator().manual_seed(seed)
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5, generator=generator)
            module.running_var.uniform_(0.5, 2.0, generator=generator)
    return model


@pytest.mark.parametrize("pool, input_norm", [([1, 1], "per_frame"), ([2, 3], "fixed")])
def test_the_grouped_encoder_gives_each_members_features(pool, input_norm):
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4, 6], features=5,
                                  pool=pool, input_norm=input_norm)
    members = [_spread_batch_norms(m, i) for i, m in enumerate(_members(config, 3))]
    images = torch.from_numpy(np.random.default_rng(1).integers(0, 256, (4, 16, 24, 3),
                                                                  dtype=np.uint8))
    with torch.no_grad():
        grouped = GroupedEncoder([inference_model(m) for m in members]).encode(images)
        each = torch.stack([m.encode(images) for m in members], dim=1)
    assert grouped.shape == (4, 3, 5)
    torch.testing.assert_close(grouped, each, rtol=1e-4, atol=1e-5)
    assert (each[:, 0] - each[:, 1]).abs().max() > 1e-2        # the members differ
    with pytest.raises(TypeError, match="cannot group a BatchNorm2d .*inference_model"):
        GroupedEncoder(members)


def test_the_grouped_gru_runs_each_members_gru_side_by_side():
    torch.manual_seed(0)
    grus = [torch.nn.GRU(7, 5, batch_first=True) for _ in range(3)]
    inputs = [torch.randn(4, 6, 7) for _ in grus]
    states = [torch.randn(1, 4, 5) for _ in grus]
    with torch.no_grad():
        out, last = grouped_gru(grus)(torch.cat(inputs, -1), torch.cat(states, -1))
        for m, gru in enumerate(grus):
            each_out, each_last = gru(inputs[m], states[m])
            torch.testing.assert_close(out[..., 5 * m:5 * (m + 1)], each_out, rtol=1e-6,
                                       atol=1e-7)
            torch.testing.assert_close(last[..., 5 * m:5 * (m + 1)], each_last, rtol=1e-6,
                                       atol=1e-7)
    with pytest.raises(ValueError, match="must be alike"):
        grouped_gru([grus[0], torch.nn.GRU(7, 6, batch_first=True)])


@pytest.mark.parametrize("temporal", ["stack", "gru"])
def test_a_monitor_of_an_ensemble_outputs_the_calibrated_mean_and_its_flag(temporal):
    """Tick by tick, without a loop: the frames of a run fed to one `HistoryMonitor`
    of the ensemble give the offline calibrated mean of the members' raw risks; one
    member alone (calibration None) gives its raw risk."""
    from pydrake.systems.sensors import ImageRgba8U
    config = HistoryMonitorConfig(frames=3, stride=2, height=16, width=24, channels=[4],
                                  features=4, temporal=temporal, hidden=6)
    members = _members(config, 2)
    ensemble = HistoryRiskEnsemble.of(members)
    frames = np.random.default_rng(0).integers(0, 256, (7, 20, 30, 4), dtype=np.uint8)
    offline = ensemble.risk_sequence(frames, calibration=lambda q: platt(q, 2.0, -0.5))
    for model, calibration, expected in (
            (ensemble, (2.0, -0.5), offline), (members[0], None, members[0].risk_sequence(frames))):
        system = HistoryMonitor(model=model, threshold=0.4, period=0.05, calibration=calibration)
        context = system.CreateDefaultContext()
        image = ImageRgba8U(30, 20)
        for tick, frame in enumerate(frames):
            context.SetTime(0.05 * tick)
            image.mutable_data[:] = frame
            system.get_color_image_input_port().FixValue(context, image)
            score = system.get_score_output_port().Eval(context)[0]
            assert score == pytest.approx(expected[tick], rel=1e-4, abs=1e-6)
            assert system.get_anomaly_output_port().Eval(context)[0] == float(score >= 0.4)
            context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    assert np.abs(offline - platt(members[0].risk_sequence(frames), 2.0, -0.5)).max() > 1e-3
    with pytest.raises(TypeError, match="a HistoryRiskModel or a HistoryRiskEnsemble, got str"):
        HistoryMonitor(model="weights.pt", threshold=0.4, period=0.05)


@pytest.mark.parametrize("members, message", [
    (0, "1 to 32 members, got 0"), (33, "got 33"), ("two", "got 'two'"), (True, "got True")])
def test_a_bad_member_count_is_refused_by_name(tmp_path, members, message):
    with pytest.raises(ValueError, match=message):
        check_members(members)
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4)
    path = _save(tmp_path / "m.pt", HistoryRiskEnsemble.of(_members(config, 2)), members=members)
    with pytest.raises(CheckpointError, match=f"its members: .*{message}"):
        load_history_monitor(path)


def test_a_checkpoint_whose_weights_hold_other_members_than_it_says_is_refused(tmp_path):
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4)
    ensemble = HistoryRiskEnsemble.of(_members(config, 2))
    for said in (1, 3):
        path = _save(tmp_path / f"m{said}.pt", ensemble, members=said)
        with pytest.raises(CheckpointError, match=f"its weights hold 2 member.s. of an ensemble, "
                                                  f"its metadata says members: {said}"):
            load_history_monitor(path)
    single = tmp_path / "single.pt"
    save_checkpoint(single, kind="history_monitor", model=_members(config, 1)[0],
                    model_config=config, preprocess_config=None, metadata={"members": 2})
    with pytest.raises(CheckpointError, match="hold 1 member.s. of an ensemble, its metadata "
                                              "says members: 2"):
        load_history_monitor(single)


def test_the_guarded_loop_confirms_the_ensembles_flags_and_brakes(tmp_path):
    """An ensemble checkpoint in ``monitor.detector`` with a k-of-n rule: the members,
    one `HistoryMonitor`, the `FlagFilter` and the switch; flagged at every tick
    (threshold 0), the loop brakes to a stop."""
    from reachwatch.diagrams import make_guarded_diagram
    config = HistoryMonitorConfig(frames=2, height=16, width=24, channels=[4], features=4)
    path = _save(tmp_path / "e.pt", HistoryRiskEnsemble.of(_members(config, 2)))
    scenario = load_scenario(data=f"monitor: {{detector: {path}, threshold: 0.0, strategy: "
                                  f"brake, brake_deceleration: 3.0, flags_needed: 2, "
                                  f"flag_window: 3}}\n")
    diagram = make_guarded_diagram(scenario)
    names = {s.get_name() for s in diagram.GetSystems()}
    assert {DETECTOR, "flag_filter", "fallback_switch"} <= names
    run = simulate(diagram, initial_state=np.array([0.0, 120.0, 0.0]), duration=2.5,
                   period=0.05, failed=OffRunway(scenario.environment.half_width))
    assert run.anomaly[0] == 0 and run.anomaly[1] == 1 and run.anomaly[-1] == 1
    assert run.speed[-1] == 0.0


def test_an_ensemble_is_of_one_config():
    a = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4)
    b = HistoryMonitorConfig(frames=2, height=16, width=24, channels=[4], features=4)
    with pytest.raises(ValueError, match="all of one config; got 2 models with 2 configs"):
        HistoryRiskEnsemble.of(_members(a, 1) + _members(b, 1))
    with pytest.raises(ValueError, match="at least two models, all of one config; got 1 "):
        HistoryRiskEnsemble.of(_members(a, 1))
