"""Training the history monitor on recorded runs: labels leave censored ticks out, and
on runs where only the change between frames says a failure is coming (every frame's
brightness alone is ambiguous) stacked frames learn it and a single frame cannot."""

import dataclasses as dc

import numpy as np
import pytest
import torch

from reachwatch.systems import HistoryMonitorConfig
from reachwatch.training.history_train import (HistoryTrainConfig, encode_runs, run_risks,
                                               tick_labels, train_encoder, train_head)
from reachwatch.training.metrics import auroc

PERIOD, DURATION, T = 0.1, 3.0, 31


def _runs(seed, count=40):
    """Brightness = a run's base + a drift: runs that will fail brighten 12 steps a tick
    over their last 6 ticks (the ticks labelled "fails within 0.5 s"), the others
    darken as fast now and then; the base spreads far wider than a drift, so one
    frame's brightness says little."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((count, T, 16, 16, 3), np.uint8)
    ticks = np.full(count, T)
    failure = np.full(count, np.nan)
    for r in range(count):
        base = rng.uniform(60, 190, size=T)[0] + np.zeros(T)
        fails = r % 2 == 0
        end = int(rng.integers(15, T)) if fails else T
        drift = np.zeros(T)
        if fails:
            drift[end - 6:end] = np.arange(1, 7) * 12.0
        else:
            drift[:] = np.where(np.arange(T) % 12 >= 6, -12.0 * (np.arange(T) % 6 + 1), 0)
        noise = rng.normal(0, 1, size=(T, 16, 16, 3))
        frames[r] = np.clip(base[:, None, None, None] + drift[:, None, None, None] + noise, 0, 255)
        if fails:
            ticks[r], failure[r] = end, (end - 1) * PERIOD
    return {"frames": frames, "signals": np.zeros((count, T, 1)), "ticks": ticks,
            "failure_time": failure}


def test_labels_leave_censored_ticks_out():
    runs = _runs(0, 4)
    labels = tick_labels(runs, period=PERIOD, duration=DURATION, within=0.5)
    assert labels[1, :26].tolist() == [0] * 26 and labels[1, 26:].tolist() == [-1] * 5
    end = runs["ticks"][0]
    assert labels[0, end - 6:end].tolist() == [1] * 6 and labels[0, end:].tolist() == [-1] * (T - end)


def test_stacked_frames_see_what_one_frame_cannot():
    train, test = _runs(1, 60), _runs(2, 40)
    within = 0.5
    labels = tick_labels(train, period=PERIOD, duration=DURATION, within=within)
    # the cue is each frame's brightness, which colour jitter would blur and per-frame
    # standardisation remove on purpose
    config = HistoryMonitorConfig(frames=1, height=16, width=16, channels=[8], features=8,
                                  hidden=16, within=within, input_norm="fixed")
    settings = HistoryTrainConfig(epochs=4, head_epochs=60, batch_size=64, tick_stride=1,
                                  augment=False)
    encoder = train_encoder(train, labels, config, settings)
    features, test_features = encode_runs(encoder, train), encode_runs(encoder, test)
    test_labels = tick_labels(test, period=PERIOD, duration=DURATION, within=within)
    known = test_labels >= 0

    def score(model):
        risks = run_risks(model, test_features, test)
        flat = np.concatenate([np.pad(r, (0, T - len(r))) for r in risks]).reshape(-1, T)
        return auroc(test_labels[known], flat[known])

    single = train_head(encoder, features, train, labels, config, settings)
    stacked = train_head(encoder, features, train, labels, dc.replace(config, frames=4), settings)
    assert score(stacked) > 0.9
    assert score(stacked) > score(single) + 0.1


def _shortcut_runs(seed, count, shift):
    """Runs on a plain ground of grey 110 whose failing runs show a fine checker
    (+-12) over their last 6 ticks, the whole frame also ``shift`` brighter: where the
    training environments' light makes failures brighter (``shift`` > 0), brightness
    alone separates them; an environment with ``shift`` < 0 reverses that cue and
    keeps the checker."""
    rng = np.random.default_rng(seed)
    checker = (np.indices((16, 16)).sum(axis=0) % 2 * 2 - 1).astype(float)
    frames = np.zeros((count, T, 16, 16, 3), np.uint8)
    ticks, failure = np.full(count, T), np.full(count, np.nan)
    for r in range(count):
        img = 110.0 + rng.normal(0, 2, (T, 16, 16, 3))
        if r % 2 == 0:
            end = int(rng.integers(15, T))
            img[end - 6:end] += shift + 12 * checker[None, :, :, None]
            ticks[r], failure[r] = end, (end - 1) * PERIOD
        frames[r] = np.clip(img, 0, 255)
    return {"frames": frames, "signals": np.zeros((count, T, 1)), "ticks": ticks,
            "failure_time": failure}


def test_colour_jitter_keeps_the_encoder_off_the_training_light():
    """Trained where failing frames are also brighter, an encoder that sees the frames'
    brightness (``input_norm: fixed``) without colour jitter ranks an environment whose
    failing frames are darker backwards; with it (the default) it reads the checker and
    ranks them right. Same seed, same encoder. Standardising each frame (the default
    ``per_frame``) takes the brightness away without the jitter too."""
    within = 0.5
    train, test = _shortcut_runs(1, 60, 30.0), _shortcut_runs(2, 40, -30.0)
    labels = tick_labels(train, period=PERIOD, duration=DURATION, within=within)
    test_labels = tick_labels(test, period=PERIOD, duration=DURATION, within=within)
    known = test_labels >= 0
    config = HistoryMonitorConfig(frames=1, height=16, width=16, channels=[8], features=8,
                                  hidden=16, within=within, input_norm="fixed")

    def held_out_auroc(augment, seed=0, config=config):
        settings = HistoryTrainConfig(epochs=4, batch_size=64, tick_stride=1, augment=augment,
                                      seed=seed)
        encoder = train_encoder(train, labels, config, settings)
        risks = run_risks(encoder, encode_runs(encoder, test), test)
        flat = np.concatenate([np.pad(r, (0, T - len(r))) for r in risks]).reshape(-1, T)
        return auroc(test_labels[known], flat[known]), encoder

    assert HistoryTrainConfig().augment
    plain, _ = held_out_auroc(False)
    jittered, encoder = held_out_auroc(True)
    assert plain < 0.2 and jittered > 0.95
    again = held_out_auroc(True)[1]          # one seed, one encoder
    for a, b in zip(encoder.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    assert held_out_auroc(False, config=dc.replace(config, input_norm="per_frame"))[0] > 0.95


def test_a_cosine_schedule_decays_each_stage_to_zero(monkeypatch):
    """``lr_schedule: cosine`` starts each stage at its learning rate and ends it near
    zero, one scheduler step per optimiser step; ``constant`` keeps the rate; a name
    neither is refused."""
    runs = _runs(0, 8)
    labels = tick_labels(runs, period=PERIOD, duration=DURATION, within=0.5)
    config = HistoryMonitorConfig(frames=2, height=16, width=16, channels=[4], features=4,
                                  hidden=4, within=0.5)
    rates = []
    step = torch.optim.AdamW.step

    def recording_step(self, *args, **kwargs):
        rates.append(self.param_groups[0]["lr"])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", recording_step)
    trained = {}
    for schedule in ("constant", "cosine"):
        settings = HistoryTrainConfig(epochs=3, head_epochs=3, batch_size=16, tick_stride=1,
                                      lr_schedule=schedule)
        rates.clear()
        said = []
        encoder = train_encoder(runs, labels, config, settings, progress=said.append)
        assert [m.split(":")[0] for m in said] == [f"encoder epoch {e}/3" for e in (1, 2, 3)]
        assert all(0 < float(m.rpartition("mean loss ")[2]) < 10 for m in said)
        encoder_rates = list(rates)
        rates.clear()
        head = train_head(encoder, encode_runs(encoder, runs), runs, labels, config, settings)
        trained[schedule] = (encoder_rates, list(rates), head)
    labelled = int(np.sum(labels >= 0))
    encoder_rates, head_rates, _ = trained["constant"]
    assert len(encoder_rates) == 3 * -(-labelled // 16) and set(encoder_rates) == {1e-3}
    assert len(head_rates) == 3 * -(-labelled // 64) and set(head_rates) == {3e-3}
    encoder_rates, head_rates, _ = trained["cosine"]
    for got, start in ((encoder_rates, 1e-3), (head_rates, 3e-3)):
        assert got[0] == start and np.all(np.diff(got) < 0) and got[-1] < 0.05 * start
    assert len(encoder_rates) == 3 * -(-labelled // 16)
    with pytest.raises(ValueError, match=r"lr_schedule must be one of \('constant', 'cosine'\), "
                                         r"got 'step'"):
        HistoryTrainConfig(lr_schedule="step")


def _stripe_runs(seed, count):
    """A bright vertical stripe at a column the state's component 1 gives (component 0
    is noise the frame does not show); runs fail at random, whatever the stripe."""
    rng = np.random.default_rng(seed)
    frames = np.full((count, T, 16, 16, 3), 40, np.uint8)
    state = np.zeros((count, T, 2))
    state[..., 0] = rng.normal(size=(count, T))
    state[..., 1] = rng.integers(1, 15, size=(count, T))
    for r in range(count):
        for t in range(T):
            frames[r, t, :, int(state[r, t, 1])] = 220
    ticks = np.full(count, T)
    failure = np.where(np.arange(count) % 2 == 0, (T - 1) * PERIOD, np.nan)
    return {"frames": frames, "signals": np.zeros((count, T, 1)), "ticks": ticks,
            "failure_time": failure, "state": state}


def _state_fit(encoder, runs, component):
    """R^2 of a least-squares line from the encoder's features to the state component."""
    features = encode_runs(encoder, runs).reshape(-1, encoder.config.features)
    target = runs["state"][..., component].reshape(-1)
    x = np.column_stack([features, np.ones(len(features))])
    residual = target - x @ np.linalg.lstsq(x, target, rcond=None)[0]
    return 1.0 - residual.var() / target.var()


def test_a_pooling_grid_keeps_where_in_the_frame_things_are():
    """Averaged whole (``pool`` [1, 1]), the last feature map says little of where the
    stripe is (a linear read-out of held-out runs explains under half of its column);
    averaged over 4 columns of cells it says most of it, with the same training; a grid
    finer than the map is refused in one line."""
    train, test = _stripe_runs(0, 24), _stripe_runs(1, 12)
    labels = tick_labels(train, period=PERIOD, duration=DURATION, within=0.5)
    config = HistoryMonitorConfig(frames=1, height=16, width=16, channels=[8], features=8,
                                  hidden=8, within=0.5)
    settings = HistoryTrainConfig(epochs=6, batch_size=32, tick_stride=1, augment=False)
    whole = train_encoder(train, labels, config, settings)
    grid = train_encoder(train, labels, dc.replace(config, pool=[1, 4]), settings)
    assert _state_fit(whole, test, 1) < 0.5 and _state_fit(grid, test, 1) > 0.9
    with pytest.raises(ValueError, match=r"^history monitor pool \[1, 9\] must fit in the "
                                         r"encoder's last map, 8 x 8 cells at 16 x 16 px "
                                         r"with 1 layers \(at most \[8, 8\]\)$"):
        dc.replace(config, pool=[1, 9]).validate()


def test_state_targets_teach_the_encoder_what_the_frame_shows_of_the_state():
    """With ``state_targets`` the encoder's two features carry the state component the
    frame shows (a linear read-out of held-out runs explains most of it) where the
    failure loss alone leaves most of it out (failures here do not depend on it);
    without targets the weights are those of a training that never heard of the option;
    a component the runs do not record is refused in one line."""
    train, test = _stripe_runs(0, 24), _stripe_runs(1, 12)
    labels = tick_labels(train, period=PERIOD, duration=DURATION, within=0.5)
    config = HistoryMonitorConfig(frames=1, height=16, width=16, channels=[8], features=2,
                                  hidden=8, within=0.5, pool=[1, 4])
    settings = HistoryTrainConfig(epochs=6, batch_size=32, tick_stride=1, augment=False)
    plain = train_encoder(train, labels, config, settings)
    taught = train_encoder(train, labels, config, dc.replace(settings, state_targets=(1,)))
    assert _state_fit(plain, test, 1) < 0.5 and _state_fit(taught, test, 1) > 0.9
    without_state = {k: v for k, v in train.items() if k != "state"}
    again = train_encoder(without_state, labels, config, settings)
    assert all(torch.equal(a, b) for a, b in zip(plain.state_dict().values(),
                                                 again.state_dict().values()))
    with pytest.raises(ValueError, match=r"^state_targets \[2\] name components the recorded "
                                         r"runs do not have \(their state has 2\)$"):
        train_encoder(train, labels, config, dc.replace(settings, state_targets=(2,)))
    for bad in ([-1], [1, 1], [True], "0"):
        with pytest.raises(ValueError, match=r"^state_targets must list distinct state "
                                             r"components \(whole numbers >= 0\), got "):
            HistoryTrainConfig(state_targets=bad)


def test_weight_averaging_returns_the_mean_of_the_last_epochs_weights(monkeypatch):
    """``weight_average``: the model a stage returns holds the mean of the weights at the
    ends of its last epochs (their share), taken without disturbing the training's path
    (the last of them is the plain training's result), and the encoder's BatchNorm
    statistics are the training ticks' under those weights, over batches drawn across
    runs (in the ticks' own order a batch holds one run, and the variances between runs
    would be lost)."""
    runs = _runs(0, 8)
    labels = tick_labels(runs, period=PERIOD, duration=DURATION, within=0.5)
    # fixed: each frame keeps its brightness, which varies between runs
    config = HistoryMonitorConfig(frames=2, height=16, width=16, channels=[4], features=4,
                                  hidden=4, within=0.5, input_norm="fixed")
    plain = HistoryTrainConfig(epochs=4, head_epochs=4, batch_size=16, tick_stride=1)
    # the weights at each epoch's end, recorded where the mean takes them
    ends = []
    update = torch.optim.swa_utils.AveragedModel.update_parameters

    def recording(self, model):
        ends.append([p.detach().clone() for p in model.parameters()])
        return update(self, model)

    monkeypatch.setattr(torch.optim.swa_utils.AveragedModel, "update_parameters", recording)
    averaged = dc.replace(plain, weight_average=0.5)
    encoder = train_encoder(runs, labels, config, averaged)
    assert len(ends) == 2                                   # the last 2 of 4 epochs
    for got, *seen in zip(encoder.parameters(), *ends):
        torch.testing.assert_close(got, torch.stack(seen).mean(dim=0))
    first = train_encoder(runs, labels, config, plain)      # off: no mean taken
    assert len(ends) == 2
    for last, got in zip(ends[-1], first.parameters()):
        assert torch.equal(last, got)
    # BatchNorm: the training ticks' statistics under the averaged weights, within the
    # noise of 16 batches; the ticks in order would give a variance far too low
    norm = encoder.encoder[1]
    rows, cols = np.nonzero(labels >= 0)
    from reachwatch.systems import detector_input
    x = detector_input(torch.from_numpy(runs["frames"][rows, cols]), config.image_config)
    with torch.no_grad():
        conv = encoder.encoder[0](x)
    population = conv.var(dim=(0, 2, 3))
    assert torch.all((norm.running_mean - conv.mean(dim=(0, 2, 3))).abs()
                     < 0.1 * population.sqrt())
    assert torch.all((norm.running_var - population).abs() < 0.1 * population), (
        norm.running_var, population)
    in_order = torch.stack([conv[i:i + 16].var(dim=(0, 2, 3))
                            for i in range(0, len(conv), 16)]).mean(dim=0)
    assert torch.any((in_order - population).abs() > 0.1 * population)   # what it avoids
    assert not encoder.training and norm.momentum == 0.1
    ends.clear()
    features = encode_runs(encoder, runs)
    head = train_head(encoder, features, runs, labels, config, averaged)
    assert len(ends) == 2
    for got, *seen in zip(head.parameters(), *ends):
        torch.testing.assert_close(got, torch.stack(seen).mean(dim=0))
    with pytest.raises(ValueError, match=r"weight_average must be a finite number in \[0, 1\)"):
        HistoryTrainConfig(weight_average=1.0)


def test_signals_that_are_not_finite_are_refused_before_training():
    """A NaN signal within a run (a controller's "no estimate") would make every risk
    NaN: one line naming the column; past a run's last tick the padding is not read."""
    from reachwatch.training.history_train import signal_statistics
    signals = np.zeros((2, 4, 3))
    signals[1, 3, 0] = np.nan                  # after run 1's 3 ticks: padding
    runs = {"signals": signals, "ticks": np.array([4, 3])}
    mean, std = signal_statistics(runs, 3)
    assert mean == [0.0, 0.0, 0.0] and std == [1e-6] * 3
    signals[0, 2, 1] = np.inf
    with pytest.raises(ValueError, match=r"^the recorded online signals are not all finite "
                                         r"\(1 NaN or inf, in column 1 of 3"):
        signal_statistics(runs, 3)


def test_a_monitor_with_signals_is_not_judged_on_signals_that_are_not_finite():
    """Calibration or held-out runs whose signals hold a NaN would give NaN risks that
    no threshold judges: refused as training is; a monitor without signals reads none."""
    from reachwatch.systems.history_model import HistoryRiskModel
    runs = {"signals": np.zeros((1, 3, 2)), "ticks": np.array([3])}
    runs["signals"][0, 1, 0] = np.nan
    features = np.zeros((1, 3, 4), np.float32)
    small = dict(frames=1, height=16, width=24, channels=[4], features=4, hidden=4)
    with pytest.raises(ValueError, match=r"^the recorded online signals are not all finite"):
        run_risks(HistoryRiskModel(HistoryMonitorConfig(signals=2, **small)), features, runs)
    risks = run_risks(HistoryRiskModel(HistoryMonitorConfig(**small)), features, runs)
    assert len(risks) == 1 and np.all(np.isfinite(risks[0]))
