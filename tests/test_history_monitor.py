"""The history monitor: what the LeafSystem outputs at each tick of a real rendered run
is the offline function of the same run's recorded frames and signals (so a monitor
trained on recorded runs sees online what it saw in training), with and without
signals, for both temporal models; its checkpoint drives the guarded loop."""

import numpy as np
import pytest
import torch

from reachwatch.diagrams import load_scenario, save_checkpoint, simulate
from reachwatch.diagrams.checkpoints import CheckpointError, checkpoint_kind, load_history_monitor
from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel, platt
from reachwatch.taxi.fidelity import make_watched_loop
from reachwatch.taxi.history import record_runs


def _checkpoint(path, config, seed=0, calibration=(0.05, 0.3)):
    torch.manual_seed(seed)
    model = HistoryRiskModel(config)
    for p in model.parameters():                 # spread the raw risk over (0, 1)
        p.data.mul_(3.0)
    save_checkpoint(path, kind="history_monitor", model=model.eval(), model_config=config,
                    preprocess_config=None,
                    metadata={"calibration": list(calibration), "threshold": 0.5})
    return path


@pytest.mark.parametrize("temporal, frames, stride, signals", [
    ("stack", 3, 2, 0), ("gru", 4, 1, 3), ("stack", 1, 1, 3)])
def test_online_risk_is_the_offline_function_of_the_recorded_run(tmp_path, temporal, frames,
                                                                  stride, signals):
    config = HistoryMonitorConfig(frames=frames, stride=stride, height=24, width=40,
                                  channels=[4, 8], features=6, signals=signals,
                                  signal_mean=[0.1] * signals, signal_std=[2.0] * signals,
                                  temporal=temporal, hidden=8)
    path = _checkpoint(tmp_path / "monitor.pt", config)
    scenario = load_scenario(data=f"monitor: {{detector: {path}, threshold: 0.5}}\n")
    start = np.array([[2.0, 120.0, 0.1]])
    recorded = record_runs(scenario, 0.6, 24, 40, start)
    ticks = int(recorded["ticks"][0])
    assert ticks == 13 and recorded["signals"].shape[-1] == 3   # estimate (2) + steering

    diagram = make_watched_loop(scenario)
    run = simulate(diagram, initial_state=start[0], duration=0.6, period=0.05,
                   half_width=scenario.environment.half_width)
    np.testing.assert_allclose(run.state, recorded["state"][0, :ticks])
    model, loaded_config, metadata = load_history_monitor(path)
    offline = model.risk_sequence(recorded["frames"][0, :ticks],
                                  recorded["signals"][0, :ticks, :signals],
                                  calibration=lambda q: platt(q, *metadata["calibration"]))
    np.testing.assert_allclose(run.score, offline, rtol=1e-4, atol=1e-5)
    assert np.ptp(offline) > 1e-4                # the history changes the risk
    assert checkpoint_kind(path) == "history_monitor"


def test_history_ticks_clamp_at_the_run_start():
    config = HistoryMonitorConfig(frames=3, stride=2)
    assert config.history_ticks(0).tolist() == [0, 0, 0]
    assert config.history_ticks(3).tolist() == [0, 1, 3]
    assert config.history_ticks(9).tolist() == [5, 7, 9]


def test_a_monitor_with_signals_refuses_a_loop_offering_other_signals(tmp_path):
    from pydrake.systems.framework import DiagramBuilder
    from reachwatch.diagrams import MonitorConfig, add_detector
    config = HistoryMonitorConfig(frames=2, height=24, width=40, channels=[4], features=4,
                                  signals=5, hidden=4)
    path = _checkpoint(tmp_path / "m.pt", config)
    with pytest.raises(ValueError, match="reads 5 online signals, this loop offers none"):
        add_detector(DiagramBuilder(), image_port=None, period=0.05,
                     monitor=MonitorConfig(detector=str(path)))


def test_config_and_checkpoint_errors(tmp_path):
    with pytest.raises(ValueError, match="temporal must be one of"):
        HistoryMonitorConfig(temporal="lstm").validate()
    with pytest.raises(ValueError, match="frames must be a whole number"):
        HistoryMonitorConfig(frames=0).validate()
    with pytest.raises(ValueError, match="signal_mean and signal_std need 2"):
        HistoryMonitorConfig(signals=2, signal_mean=[0.0], signal_std=[1.0]).validate()
    from reachwatch.diagrams import load_detector
    path = _checkpoint(tmp_path / "m.pt", HistoryMonitorConfig(height=24, width=40,
                                                                channels=[4], features=4))
    with pytest.raises(CheckpointError, match="holds a 'history_monitor' model, not a 'detector'"):
        load_detector(path)
