"""The history monitor: what the LeafSystem outputs at each tick of a real rendered run
is the offline function of the same run's recorded frames and signals (so a monitor
trained on recorded runs sees online what it saw in training), with and without
signals, for both temporal models; its checkpoint drives the guarded loop."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import ImageRgba8U
import torch

from reachwatch.diagrams import load_scenario, save_checkpoint, simulate
from reachwatch.diagrams.checkpoints import CheckpointError, checkpoint_kind, load_history_monitor
from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel, platt
from reachwatch.taxi import OffRunway
from reachwatch.taxi.fidelity import make_watched_loop
from reachwatch.taxi.history import record_runs


def _checkpoint(path, config, seed=0, calibration=(0.05, 0.3), **metadata):
    torch.manual_seed(seed)
    model = HistoryRiskModel(config)
    for p in model.parameters():                 # spread the raw risk over (0, 1)
        p.data.mul_(2.0)
    save_checkpoint(path, kind="history_monitor", model=model.eval(), model_config=config,
                    preprocess_config=None,
                    metadata={"calibration": list(calibration), "threshold": 0.5,
                              **metadata})
    return path


@pytest.mark.parametrize("temporal, frames, stride, signals, input_norm", [
    ("stack", 3, 2, 0, "per_frame"), ("gru", 4, 1, 3, "per_frame"), ("stack", 1, 1, 3, "fixed")])
def test_online_risk_is_the_offline_function_of_the_recorded_run(tmp_path, temporal, frames,
                                                                  stride, signals, input_norm):
    config = HistoryMonitorConfig(frames=frames, stride=stride, height=24, width=40,
                                  channels=[4, 8], features=6, signals=signals,
                                  signal_mean=[0.1] * signals, signal_std=[2.0] * signals,
                                  temporal=temporal, hidden=8, input_norm=input_norm)
    path = _checkpoint(tmp_path / "monitor.pt", config)
    scenario = load_scenario(data=f"monitor: {{detector: {path}, threshold: 0.5}}\n")
    start = np.array([[2.0, 120.0, 0.1]])
    recorded = record_runs(scenario, 0.6, 24, 40, start)
    ticks = int(recorded["ticks"][0])
    assert ticks == 13 and recorded["signals"].shape[-1] == 3   # estimate (2) + steering

    diagram = make_watched_loop(scenario)
    run = simulate(diagram, initial_state=start[0], duration=0.6, period=0.05,
                   failed=OffRunway(scenario.environment.half_width))
    np.testing.assert_allclose(run.state, recorded["state"][0, :ticks])
    model, loaded_config, metadata = load_history_monitor(path)
    offline = model.risk_sequence(recorded["frames"][0, :ticks],
                                  recorded["signals"][0, :ticks, :signals],
                                  calibration=lambda q: platt(q, *metadata["calibration"]))
    np.testing.assert_allclose(run.score, offline, rtol=1e-4, atol=1e-5)
    assert np.ptp(offline) > 1e-4                # the history changes the risk
    assert checkpoint_kind(path) == "history_monitor"


def test_a_scenario_runs_a_checkpoint_at_its_own_threshold_and_flag_rule(tmp_path):
    """``monitor.threshold`` and the k-of-n rule left out are the checkpoint's (a study's
    conformal threshold and flag rule); set, they are the file's; a checkpoint with no
    threshold of its own is refused in one line unless the file sets one."""
    from reachwatch.diagrams import MonitorConfig, make_guarded_diagram
    config = HistoryMonitorConfig(frames=2, height=16, width=24, channels=[4], features=4)
    path = _checkpoint(tmp_path / "m.pt", config, threshold=0.37, flag_rule=[2, 3])
    monitor = load_scenario(data=f"monitor: {{detector: {path}}}\n").monitor
    assert (monitor.threshold, monitor.flags_needed, monitor.flag_window) == (None, None, None)
    full = monitor.with_checkpoint_defaults()
    assert (full.threshold, full.flags_needed, full.flag_window) == (0.37, 2, 3)
    # one of the pair set, the other the checkpoint's: a pair nothing judged, said once
    import logging
    import reachwatch.systems.checks as checks
    checks.WARNED.clear()
    for half in ("threshold: 0.6", "flags_needed: 1, flag_window: 1"):
        logger = logging.getLogger("reachwatch")
        seen = []
        handler = logging.Handler()
        handler.emit = lambda record: seen.append(record.getMessage())
        logger.addHandler(handler)
        try:
            mixed = load_scenario(data=f"monitor: {{detector: {path}, {half}}}\n").monitor
            mixed.with_checkpoint_defaults()
        finally:
            logger.removeHandler(handler)
        assert any("fixed its threshold 0.37 together with its rule 2 of 3" in m and
                   "a pair nothing judged" in m for m in seen), (half, seen)
    own = load_scenario(data=f"monitor: {{detector: {path}, threshold: 0.6, flags_needed: 1, "
                             f"flag_window: 1}}\n").monitor.with_checkpoint_defaults()
    assert (own.threshold, own.flags_needed, own.flag_window) == (0.6, 1, 1)
    # a pipeline that names another checkpoint later takes that one's rule, not the first's
    other = _checkpoint(tmp_path / "other.pt", config, threshold=0.8, flag_rule=[1, 1])
    monitor.detector = str(other)
    swapped = monitor.with_checkpoint_defaults()
    assert (swapped.threshold, swapped.flags_needed, swapped.flag_window) == (0.8, 1, 1)
    high = _checkpoint(tmp_path / "high.pt", config, threshold=1.5, flag_rule=[1, 1])
    with pytest.raises(ValueError,
                       match=r"monitor.threshold must be a finite number in \[0, 1\], got 1.5$"):
        load_scenario(data=f"monitor: {{detector: {high}}}\n")
    built = MonitorConfig(detector=str(path), strategy="brake")     # never validated
    names = {s.get_name() for s in make_guarded_diagram(_with_monitor(built)).GetSystems()}
    assert "flag_filter" in names
    assert MonitorConfig(strategy="brake").with_checkpoint_defaults().threshold is None     # nothing to run
    bare = tmp_path / "bare.pt"
    save_checkpoint(bare, kind="history_monitor", model=HistoryRiskModel(config).eval(),
                    model_config=config, preprocess_config=None, metadata={})
    with pytest.raises(ValueError, match=r"monitor.threshold: \S*bare.pt holds no threshold of "
                                         r"its own; set monitor.threshold$"):
        load_scenario(data=f"monitor: {{detector: {bare}}}\n")
    given = load_scenario(data=f"monitor: {{detector: {bare}, threshold: 0.2}}\n")
    assert given.monitor.with_checkpoint_defaults().flag_window == 1
    # loops that only read its score take it as it is (a placeholder threshold)
    from reachwatch.taxi.fidelity import score_runs
    scored = score_runs(given, np.array([[0.0, 120.0, 0.0]]), duration=0.1,
                        cache_dir=tmp_path / "scores", progress=False)
    assert scored["ticks"][0] == 3 and np.isfinite(scored["score"][0, :3]).all()
    with pytest.raises(ValueError, match="monitor.flags_needed / monitor.flag_window: set both "
                                         "or neither"):
        load_scenario(data=f"monitor: {{detector: {path}, flag_window: 5}}\n")


def _with_monitor(monitor):
    import dataclasses as dc
    return dc.replace(load_scenario(data=""), monitor=monitor)


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


def test_a_monitor_trained_at_another_control_period_is_refused(tmp_path):
    """Its history, k-of-n rule and threshold count ticks: at another period they span
    other times, so the loop refuses it (a checkpoint that names no period loads)."""
    from pydrake.systems.framework import DiagramBuilder
    from reachwatch.diagrams import MonitorConfig, add_detector
    config = HistoryMonitorConfig(frames=2, height=24, width=40, channels=[4], features=4,
                                  hidden=4)
    path = _checkpoint(tmp_path / "m.pt", config, period_s=0.05)
    with pytest.raises(ValueError, match=r"trained on frames every 0.05 s and this loop ticks "
                                         r"every 0.1 s"):
        add_detector(DiagramBuilder(), image_port=None, period=0.1,
                     monitor=MonitorConfig(detector=str(path)))
    for checkpoint, period in [(path, 0.05), (_checkpoint(tmp_path / "any.pt", config), 0.1)]:
        builder = DiagramBuilder()
        image = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(40, 24))))
        add_detector(builder, image_port=image.get_output_port(), period=period,
                     monitor=MonitorConfig(detector=str(checkpoint)))


def test_a_monitor_trained_on_another_camera_size_is_refused_at_its_first_frame(tmp_path):
    """Each frame is resized to the model's size, so a camera of another size or shape
    would pass unseen: the checkpoint's ``image_size`` (the study's camera) is enforced,
    as the image detector's is; a checkpoint that names none takes any frame."""
    from pydrake.systems.framework import DiagramBuilder
    from reachwatch.diagrams import MonitorConfig, add_detector
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4,
                                  hidden=4)
    for metadata, frame, refused in (({"image_size": [24, 40]}, (40, 24), False),
                                     ({"image_size": [24, 40]}, (64, 24), True),
                                     ({}, (64, 24), False)):
        path = _checkpoint(tmp_path / "m.pt", config, **metadata)
        builder = DiagramBuilder()
        image = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(*frame))))
        system = add_detector(builder, image_port=image.get_output_port(), period=0.05,
                              monitor=MonitorConfig(detector=str(path)))
        builder.ExportOutput(system.GetOutputPort("score"), "score")
        diagram = builder.Build()
        score = diagram.GetOutputPort("score")
        if refused:
            with pytest.raises(ValueError, match=r"HistoryMonitor: input port 'color_image' "
                                                 r"got a 24x64 image, but this monitor was "
                                                 r"trained on 24x40"):
                score.Eval(diagram.CreateDefaultContext())
        else:
            assert np.isfinite(score.Eval(diagram.CreateDefaultContext())[0])


def test_a_monitor_guarding_a_gentler_fallback_than_its_study_braked_is_warned_once(
        tmp_path, caplog):
    """A study fixes the threshold for warnings its lead ahead, braking at its
    deceleration: a loop whose fallback slows down or brakes more gently is warned of
    (once per checkpoint and fallback), not refused; one braking as hard, or one that
    only watches (threshold 1), is not."""
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource
    from reachwatch.diagrams import ControllerConfig, MonitorConfig, add_monitor
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4,
                                  hidden=4)
    path = str(_checkpoint(tmp_path / "m.pt", config, threshold=0.4, brake_deceleration=3.0,
                           lead_s=1.67, period_s=0.05, image_size=[16, 24]))

    def build(**monitor):
        builder = DiagramBuilder()
        image = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(24, 16))))
        steering = builder.AddSystem(ConstantVectorSource([0.0]))
        add_monitor(builder, image_port=image.get_output_port(),
                    steering_port=steering.get_output_port(),
                    monitor=MonitorConfig(detector=path, **monitor),
                    controller=ControllerConfig())
    with caplog.at_level("WARNING", logger="reachwatch"):
        build(strategy="brake", brake_deceleration=3.0)
        build(threshold=1.0)                              # watching only
        assert not caplog.text
        build(strategy="slow_down")
        build(strategy="slow_down")                       # said once
        build(strategy="brake", brake_deceleration=1.0)
    assert caplog.text.count("its threshold was fixed for a fallback braking at 3 m/s^2, "
                             "warning 1.67 s ahead; this loop's fallback is") == 2
    assert "is 'slow_down', which may need longer" in caplog.text
    assert "is braking at 1 m/s^2, which may need longer" in caplog.text


def test_a_monitor_guarding_a_faster_loop_than_its_study_ran_is_warned_once(tmp_path, caplog):
    """The same braking from a higher speed takes longer than the study's lead: before,
    nothing was said (the checkpoint did not record the speed)."""
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource
    from reachwatch.diagrams import ControllerConfig, MonitorConfig, add_monitor
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4,
                                  hidden=4)
    path = str(_checkpoint(tmp_path / "m.pt", config, threshold=0.4, brake_deceleration=3.0,
                           lead_s=1.67, speed_mps=5.0, period_s=0.05, image_size=[16, 24]))

    def build(speed):
        builder = DiagramBuilder()
        image = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(24, 16))))
        steering = builder.AddSystem(ConstantVectorSource([0.0]))
        add_monitor(builder, image_port=image.get_output_port(),
                    steering_port=steering.get_output_port(),
                    monitor=MonitorConfig(detector=path, strategy="brake",
                                          brake_deceleration=3.0),
                    controller=ControllerConfig(speed=speed))
    with caplog.at_level("WARNING", logger="reachwatch"):
        build(5.0)
        build(4.0)                                       # slower: stops sooner
        assert not caplog.text
        build(8.0)
        build(8.0)                                       # said once
    assert caplog.text.count("its threshold was fixed for a loop at 5 m/s, warning 1.67 s "
                             "ahead; this loop runs at 8 m/s") == 1


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
    with pytest.raises(ValueError, match=r"input_norm must be one of \('fixed', 'per_frame'\), "
                                         r"got 'instance'$"):
        HistoryMonitorConfig(input_norm="instance").validate()


def test_per_frame_normalisation_ignores_a_frames_brightness_contrast_and_colour_cast():
    """``per_frame``: a frame scaled and shifted (its contrast and brightness, and each
    channel's offset) encodes as the frame itself; ``fixed`` tells them apart."""
    torch.manual_seed(0)
    x = torch.randn(2, 3, 16, 24)
    changed = 2.5 * x + torch.tensor([0.7, -0.4, 1.1])[:, None, None]
    for norm, same in (("per_frame", True), ("fixed", False)):
        model = HistoryRiskModel(HistoryMonitorConfig(height=16, width=24, channels=[4],
                                                      features=4, input_norm=norm)).eval()
        with torch.no_grad():
            close = torch.allclose(model.encode_input(x), model.encode_input(changed),
                                   atol=1e-5)
        assert close == same, norm


def test_a_checkpoint_from_before_input_norm_loads_as_trained(tmp_path):
    """A checkpoint whose config does not name ``input_norm`` was trained ``fixed``: it
    loads so, whatever today's default, and scores as before."""
    config = HistoryMonitorConfig(height=24, width=40, channels=[4], features=4,
                                  input_norm="fixed")
    path = _checkpoint(tmp_path / "old.pt", config)
    payload = torch.load(path, weights_only=True)
    del payload["model_config"]["input_norm"]
    torch.save(payload, path)
    assert HistoryMonitorConfig().input_norm == "per_frame"
    model, loaded, _ = load_history_monitor(path)
    assert loaded.input_norm == "fixed" and loaded == config
    frames = np.random.default_rng(0).integers(0, 256, (3, 24, 40, 3), dtype=np.uint8)
    torch.manual_seed(0)
    fresh = HistoryRiskModel(config)
    for p in fresh.parameters():
        p.data.mul_(2.0)
    np.testing.assert_allclose(model.risk_sequence(frames), fresh.eval().risk_sequence(frames),
                               rtol=1e-6)


def _step_monitor(monitor, frames, signals, on_tick=None):
    """Drives ``monitor`` tick by tick on RGBA ``frames`` (and ``signals``) without a
    loop: its score at each tick, then its periodic update."""
    from pydrake.systems.sensors import ImageRgba8U
    context = monitor.CreateDefaultContext()
    scores = []
    for t, frame in enumerate(frames):
        image = ImageRgba8U(frame.shape[1], frame.shape[0])
        image.mutable_data[:] = frame
        monitor.get_color_image_input_port().FixValue(context, image)
        if monitor.get_signals_input_port() is not None:
            monitor.get_signals_input_port().FixValue(context, signals[t])
        scores.append(monitor.get_score_output_port().Eval(context)[0])
        assert monitor.get_anomaly_output_port().Eval(context)[0] == float(
            not scores[-1] < 0.5)                    # NaN flags (`flag_of`)
        if context.get_discrete_state_vector().size() > 1:      # history kept
            context.SetDiscreteState(monitor.EvalUniquePeriodicDiscreteUpdate(context))
        if on_tick is not None:
            on_tick(t)
    return np.array(scores)


@pytest.mark.parametrize("temporal, frames, stride, signals", [
    ("gru", 4, 3, 2), ("gru", 5, 1, 0), ("gru", 1, 1, 1), ("gru", 2, 4, 0), ("stack", 3, 2, 1)])
def test_the_system_steps_to_the_offline_risk_at_every_tick(temporal, frames, stride, signals):
    """Stride, one frame, runs shorter and longer than the history: no render needed."""
    from reachwatch.systems import HistoryMonitor
    config = HistoryMonitorConfig(frames=frames, stride=stride, height=16, width=24,
                                  channels=[4, 6], features=5, signals=signals,
                                  signal_mean=[0.2] * signals, signal_std=[1.5] * signals,
                                  temporal=temporal, hidden=6)
    torch.manual_seed(1)
    model = HistoryRiskModel(config).eval()
    for p in model.parameters():
        p.data.mul_(2.0)
    rng = np.random.default_rng(0)
    ticks = 3 + (frames - 1) * stride + 2 * stride
    images = (rng.integers(0, 256, (ticks, 20, 30, 4)) *       # brightness moves the risk
              rng.uniform(0.0, 1.0, (ticks, 1, 1, 1))).astype(np.uint8)
    sig = rng.normal(size=(ticks, signals))
    monitor = HistoryMonitor(model=model, threshold=0.5, period=0.05, calibration=(0.7, 0.1))
    online = _step_monitor(monitor, images, sig)
    offline = model.risk_sequence(images, sig.astype(np.float32),
                                  calibration=lambda q: platt(q, 0.7, 0.1))
    np.testing.assert_allclose(online, offline, rtol=1e-5, atol=1e-6)
    assert np.ptp(offline) > 1e-3


@pytest.mark.parametrize("members", [1, 3])
def test_each_tick_encodes_its_frame_once_and_steps_the_gru_once(members):
    """Once a tick: the encoder on the current frame, and (past the first tick) one GRU
    step of the open windows together, not a re-run of the window; in one torch thread,
    the caller's thread count given back. An ensemble's members too: one grouped
    encoder and one GRU of all their units, once a tick."""
    from reachwatch.systems import HistoryMonitor, HistoryRiskEnsemble
    config = HistoryMonitorConfig(frames=6, stride=2, height=16, width=24, channels=[4],
                                  features=4, temporal="gru", hidden=5)
    torch.manual_seed(0)
    models = [HistoryRiskModel(config).eval() for _ in range(members)]
    monitor = HistoryMonitor(model=models[0] if members == 1 else
                             HistoryRiskEnsemble.of(models), threshold=0.5, period=0.05)
    encoder = (monitor._members[0] if members == 1 else monitor._encode_frame._grouped).encoder
    calls = {"encode": [], "gru": []}
    encoder.register_forward_pre_hook(
        lambda m, args: calls["encode"].append(torch.get_num_threads()))
    monitor._gru_units.register_forward_pre_hook(
        lambda m, args: calls["gru"].append((tuple(args[0].shape), torch.get_num_threads())))
    per_tick = []
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        _step_monitor(monitor, np.zeros((8, 20, 30, 4), np.uint8), None,
                      on_tick=lambda t: per_tick.append(
                          (len(calls["encode"]), len(calls["gru"]))))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert per_tick == [(t + 1, t + 1) for t in range(8)]
    assert calls["encode"] == [1] * 8
    # tick 0: the first frame through every window at once; then one step of the 6 windows
    # that hold the tick (batch 6, sequence 1)
    assert calls["gru"] == [((1, 6, 4 * members), 1)] + [((6, 1, 4 * members), 1)] * 7


@pytest.mark.parametrize("temporal", ["gru", "stack"])
def test_a_monitor_and_its_diagram_are_freed_once_let_go(temporal):
    """No callback of the monitor holds it strongly (a cycle through C++ that Python's
    collector cannot see would keep it, and its whole loop, alive for good)."""
    import gc
    import weakref
    from pydrake.systems.framework import DiagramBuilder
    from reachwatch.systems import HistoryMonitor
    config = HistoryMonitorConfig(frames=3, stride=1, height=16, width=24, channels=[4],
                                  features=5, temporal=temporal, hidden=6)
    builder = DiagramBuilder()
    monitor = builder.AddSystem(HistoryMonitor(model=HistoryRiskModel(config).eval(),
                                               threshold=0.5, period=0.05))
    builder.ExportInput(monitor.get_color_image_input_port(), "image")
    diagram = builder.Build()
    scores = _step_monitor(monitor, np.zeros((2, 20, 30, 4), np.uint8), None)
    assert np.all(np.isfinite(scores))
    alive = (weakref.ref(monitor), weakref.ref(diagram))
    del builder, monitor, diagram
    gc.collect()
    assert [ref() for ref in alive] == [None, None]


def test_the_guards_tables_refuse_a_monitor_over_several_frames(tmp_path):
    """A table of one score per state reads a history monitor on that state's frame
    alone: one line, before any sweep; a single frame's is a score per state."""
    from reachwatch.diagrams import MonitorConfig, check_per_state_monitor
    small = dict(height=16, width=24, channels=[4], features=5, hidden=6)
    history = _checkpoint(tmp_path / "h.pt", HistoryMonitorConfig(frames=3, **small))
    with pytest.raises(ValueError, match=r"^monitor.detector: \S+h.pt is a history monitor over "
                                         r"3 frames; the guard's tables hold one score per state"):
        check_per_state_monitor(MonitorConfig(detector=str(history)))
    single = _checkpoint(tmp_path / "s.pt", HistoryMonitorConfig(frames=1, **small))
    check_per_state_monitor(MonitorConfig(detector=str(single)))
    check_per_state_monitor(MonitorConfig())


def test_a_risk_that_is_not_a_number_flags():
    """A NaN signal (a controller's estimate gone bad) makes the risk NaN, which compares
    false with every threshold: the monitor flags it, for as long as the history holds
    it, rather than never flagging."""
    from reachwatch.systems import HistoryMonitor
    config = HistoryMonitorConfig(frames=2, stride=1, height=16, width=24, channels=[4],
                                  features=5, signals=1, hidden=6)
    monitor = HistoryMonitor(model=HistoryRiskModel(config).eval(), threshold=0.5, period=0.05)
    signals = np.array([[0.0], [np.nan], [0.0], [0.0]])
    scores = _step_monitor(monitor, np.zeros((4, 20, 30, 4), np.uint8), signals)
    assert np.isnan(scores).tolist() == [False, True, True, False]


def test_flag_of_flags_at_and_above_the_threshold_and_on_nan():
    from reachwatch.systems.detector import flag_of
    assert [flag_of(s, 0.5) for s in (0.49, 0.5, 0.9, float("nan"))] == [0.0, 1.0, 1.0, 1.0]


def test_a_studys_monitor_saved_before_its_period_and_frame_size_were_recorded_is_said(
        tmp_path, caplog):
    """Such a checkpoint ran at any period and camera size without a word."""
    from pydrake.systems.framework import DiagramBuilder
    from reachwatch.diagrams import MonitorConfig, add_detector
    config = HistoryMonitorConfig(frames=1, height=16, width=24, channels=[4], features=4)
    old = str(_checkpoint(tmp_path / "old.pt", config, lead_s=1.67))
    new = str(_checkpoint(tmp_path / "new.pt", config, lead_s=1.67, period_s=0.05,
                          image_size=[16, 24]))
    with caplog.at_level("WARNING", logger="reachwatch"):
        for path in (new, old):
            builder = DiagramBuilder()
            image = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageRgba8U(24, 16))))
            add_detector(builder, image_port=image.get_output_port(), period=0.05,
                         monitor=MonitorConfig(detector=path, threshold=1.0))
    assert caplog.text.count("is a study's monitor saved before its period_s and image_size "
                             "were recorded") == 1 and "old.pt" in caplog.text
