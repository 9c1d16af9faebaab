"""Training a monitor over the image history from recorded real-loop runs, in two
stages that every variant shares: (1) the per-frame encoder, trained as a
single-frame monitor on the runs' ticks; (2) with the encoder frozen, each variant's
head (one frame, stacked frames, a GRU; with or without the online signals) on the
encoded runs. The label of a tick is "the run fails within ``within`` s"
(`reachwatch.training.monitor_eval.run_labels`): a censored tick (the run ended
sooner without failing) is left out, never called safe.

``runs`` is a dict of arrays as an application's
`reachwatch.reach.application.Application.recorded_runs` returns them (``frames``
``(R, T, h, w, 3)``, ``signals`` ``(R, T, m)``, ``ticks``, ``failure_time``), recorded
at ``period`` s a tick for ``duration`` s."""

import copy
import dataclasses as dc

import numpy as np
import torch
import torch.nn.functional as F

from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel, detector_input
from reachwatch.systems.bounds import bounded, check_bounds

from .detector_train import colour_jitter
from .monitor_eval import run_labels


@dc.dataclass
class HistoryTrainConfig:
    """Optimisation settings: stage 1 runs ``epochs`` over every ``tick_stride``-th
    labelled tick; stage 2 ``head_epochs`` over all of them. ``augment``: stage 1 sees
    each frame colour-jittered (`reachwatch.training.detector_train.colour_jitter`:
    per-frame channel gains, brightness and contrast, drawn from ``seed``), so that
    the encoder leans less on the training environments' light and paint.
    ``lr_schedule``: ``constant`` keeps each stage's learning rate; ``cosine`` decays it
    to zero over the stage's steps (`torch.optim.lr_scheduler.CosineAnnealingLR`), so
    the last epochs take small steps and one training ends nearer the next.
    ``state_targets``: components of the runs' recorded ``state`` that stage 1 also
    teaches the encoder to estimate from the frame (each standardised over the training
    ticks, a squared error weighted ``state_weight`` beside the failure loss, through a
    linear read-out dropped after training), so that its features carry what the state
    is, not only what the training environments' failures looked like; ``[]``: none
    (the encoder's weights are then those of a training without the option). The state
    is privileged: it is read in training only, never online.
    ``weight_average``: the share of each stage's last epochs whose end-of-epoch weights
    are averaged into the model it returns (stochastic weight averaging, Izmailov et
    al. 2018: the mean of points along one training's path, which lands nearer the
    middle of a flat region than its last point); the encoder's BatchNorm statistics
    are then measured again on the training ticks as inference sees them (no jitter,
    batches in a seeded random order).
    0: off, the last epoch's weights, bit for bit those of a training without it."""
    epochs: int = 12
    head_epochs: int = 40
    head_learning_rate: float = 3e-3
    batch_size: int = 128
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    tick_stride: int = 2
    seed: int = 0
    augment: bool = True
    lr_schedule: str = "constant"
    state_targets: tuple = ()
    state_weight: float = bounded(1.0, 0.0, 1e6, low_open=True, high_open=True)
    weight_average: float = bounded(0.0, 0.0, 1.0, high_open=True)

    def __post_init__(self):
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got "
                             f"{self.lr_schedule!r}")
        self.state_targets = tuple(check_state_targets("state_targets", self.state_targets))
        check_bounds(self)


def check_state_targets(where: str, targets) -> list:
    """``targets`` as a list of distinct whole numbers >= 0 (state components), or a
    one-line ValueError naming ``where``."""
    values = list(targets) if isinstance(targets, (list, tuple)) else None
    if values is None or any(isinstance(t, bool) or not isinstance(t, (int, np.integer))
                             or t < 0 for t in values) or len(set(values)) != len(values):
        raise ValueError(f"{where} must list distinct state components (whole numbers >= 0), "
                         f"got {targets!r}")
    return [int(t) for t in values]


def _state_read_out(runs: dict, rows, cols, train: HistoryTrainConfig, features: int):
    """``(targets (N, k) standardised, linear read-out)`` of ``train.state_targets`` at
    the ticks ``rows, cols``, or ``(None, None)`` without targets."""
    if not train.state_targets:
        return None, None
    state = np.asarray(runs.get("state", np.zeros((0, 0, 0))), float)
    width = state.shape[-1] if state.ndim == 3 else 0
    if max(train.state_targets) >= width:
        raise ValueError(f"state_targets {list(train.state_targets)} name components the "
                         f"recorded runs do not have (their state has {width})")
    values = state[rows, cols][:, list(train.state_targets)]
    values = (values - values.mean(axis=0)) / np.maximum(values.std(axis=0), 1e-6)
    return (torch.from_numpy(values.astype(np.float32)),
            torch.nn.Linear(features, len(train.state_targets)))


LR_SCHEDULES = ("constant", "cosine")


def _schedule(optimiser, train: HistoryTrainConfig, steps: int):
    """The learning-rate scheduler of ``train.lr_schedule`` over ``steps`` optimiser
    steps (None: constant)."""
    if train.lr_schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=max(1, steps))
    return None


def averaged_epochs(train: HistoryTrainConfig, epochs: int) -> int:
    """How many of a stage's ``epochs`` last epochs ``train.weight_average`` averages (0:
    none; at least one when on)."""
    if train.weight_average <= 0:
        return 0
    return max(1, round(train.weight_average * epochs))


class _WeightMean:
    """The running mean of a model's parameters at the ends of its last epochs
    (`torch.optim.swa_utils.AveragedModel`), copied into it at the end."""

    def __init__(self, model, train: HistoryTrainConfig, epochs: int):
        self.first = epochs - averaged_epochs(train, epochs)
        self.mean = None if self.first >= epochs else \
            torch.optim.swa_utils.AveragedModel(model, use_buffers=False)
        self.model = model

    def epoch_done(self, epoch: int):
        if self.mean is not None and epoch >= self.first:
            self.mean.update_parameters(self.model)

    def into_model(self) -> bool:
        """Copies the mean into the model; False when nothing was averaged."""
        if self.mean is None:
            return False
        with torch.no_grad():
            for mine, mean in zip(self.model.parameters(), self.mean.module.parameters()):
                mine.copy_(mean)
        return True


@torch.no_grad()
def _measure_batch_norm(model: HistoryRiskModel, frames, rows, cols, train: HistoryTrainConfig):
    """Each BatchNorm's running statistics measured again after the weights were
    averaged (`torch.optim.swa_utils.update_bn`'s way: the mean of the batches'
    statistics, each batch weighing the same), over the ticks ``rows, cols`` in batches
    of ``train.batch_size`` drawn in a seeded random order, as training drew them: in
    the ticks' own order a batch holds one or two runs of one environment, and the
    spread between runs and environments would be left out of the variances."""
    norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    momenta = [m.momentum for m in norms]
    order = np.random.default_rng([train.seed, 1]).permutation(len(rows))
    try:
        for m in norms:
            m.reset_running_stats()
            m.momentum = None                   # cumulative: every batch weighs the same
        model.train()
        for i in range(0, len(order), train.batch_size):
            b = order[i:i + train.batch_size]
            model.encode_input(detector_input(torch.from_numpy(frames[rows[b], cols[b]]),
                                              model.config.image_config))
    finally:
        for m, momentum in zip(norms, momenta):
            m.momentum = momentum
        model.eval()


def tick_labels(runs: dict, *, period: float, duration: float, within: float) -> np.ndarray:
    """``(R, T)`` int8: 1 where the run fails within ``within`` s of the tick, 0 where
    it does not, -1 where censoring leaves it unknown or the run had ended."""
    ticks, failure = np.asarray(runs["ticks"], int), np.asarray(runs["failure_time"], float)
    length = runs["frames"].shape[1]
    out = np.full((len(ticks), length), -1, np.int8)
    for r, n in enumerate(ticks):
        out[r, :n] = run_labels(n, failure[r], period=period, duration=duration, within=within)
    return out


def _pos_weight(labels) -> torch.Tensor:
    positives = max(1, int(np.sum(labels == 1)))
    return torch.tensor(min(50.0, np.sum(labels == 0) / positives))


#: The settings only `train_head` reads: an encoder does not depend on them (`encoder_settings`).
HEAD_SETTINGS = ("head_epochs", "head_learning_rate")


def encoder_settings(train: HistoryTrainConfig) -> HistoryTrainConfig:
    """``train`` with `HEAD_SETTINGS` at their defaults: what an encoder trained by
    `train_encoder` depends on, and is kept by, so that a study that changes only its
    heads' training trains no encoder again."""
    defaults = HistoryTrainConfig()
    return dc.replace(train, **{name: getattr(defaults, name) for name in HEAD_SETTINGS})


def train_encoder(runs: dict, labels: np.ndarray, config: HistoryMonitorConfig,
                  train: HistoryTrainConfig, progress=None) -> HistoryRiskModel:
    """Stage 1: a single-frame monitor (``config`` with one frame, no signals) trained
    on the labelled ticks of ``runs``; its encoder is what every variant reads."""
    config = dc.replace(config, frames=1, stride=1, signals=0, signal_mean=[], signal_std=[],
                        temporal="stack")
    torch.manual_seed(train.seed)
    rng = np.random.default_rng(train.seed)
    model = HistoryRiskModel(config)
    rows, cols = np.nonzero(labels >= 0)
    keep = cols % train.tick_stride == 0
    rows, cols = rows[keep], cols[keep]
    if len(np.unique(labels[rows, cols])) < 2:
        raise ValueError(f"the training runs give {len(rows)} labelled ticks, "
                         f"{int(np.sum(labels[rows, cols] == 1))} of them failing within the "
                         f"horizon: a monitor needs both kinds (more runs, runs that fail, or "
                         f"runs longer than the horizon)")
    y = torch.from_numpy(labels[rows, cols].astype(np.float32))
    # made after the model, so that without targets its weights are drawn as before
    state, read_out = _state_read_out(runs, rows, cols, train, config.features)
    optimiser = torch.optim.AdamW(list(model.parameters()) + (
        list(read_out.parameters()) if read_out is not None else []),
        lr=train.learning_rate, weight_decay=train.weight_decay)
    weight = _pos_weight(labels[rows, cols])
    frames = runs["frames"]
    jitter = torch.Generator().manual_seed(train.seed) if train.augment else None
    schedule = _schedule(optimiser, train, train.epochs * -(-len(rows) // train.batch_size))
    averaged = _WeightMean(model, train, train.epochs)
    for epoch in range(train.epochs):
        model.train()
        order = rng.permutation(len(rows))
        total = 0.0
        for i in range(0, len(order), train.batch_size):
            b = order[i:i + train.batch_size]
            x = detector_input(torch.from_numpy(frames[rows[b], cols[b]]), config.image_config)
            if jitter is not None:
                x = colour_jitter(x, jitter)
            features = model.encode_input(x)
            logits = model.head_logits(features[:, None])
            loss = F.binary_cross_entropy_with_logits(logits, y[b], pos_weight=weight)
            if read_out is not None:
                loss = loss + train.state_weight * F.mse_loss(read_out(features), state[b])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            if schedule is not None:
                schedule.step()
            total += loss.item() * len(b)
        averaged.epoch_done(epoch)
        if progress:        # the epoch's mean: one batch's loss is as noisy as its draw
            progress(f"encoder epoch {epoch + 1}/{train.epochs}: mean loss "
                     f"{total / len(order):.3f}")
    if averaged.into_model():
        _measure_batch_norm(model, frames, rows, cols, train)
    return model.eval()


@torch.no_grad()
def encode_runs(encoder: HistoryRiskModel, runs: dict) -> np.ndarray:
    """Features ``(R, T, features)`` of every recorded frame."""
    frames = runs["frames"]
    out = np.zeros(frames.shape[:2] + (encoder.config.features,), np.float32)
    for r in range(len(frames)):
        n = int(runs["ticks"][r])
        if n:
            out[r, :n] = encoder.encode_frames(frames[r, :n]).numpy()
    return out


def finite_signals(runs: dict, count: int) -> np.ndarray:
    """The first ``count`` online signals at every tick of the runs, ``(ticks, count)``;
    a ValueError in one line when one is not finite (a controller that outputs NaN for
    "no estimate", say): a monitor that reads it has a NaN risk there, which no
    threshold judges (online such a risk flags: `reachwatch.systems.detector.flag_of`)."""
    signals = np.asarray(runs["signals"], float)[..., :count]
    valid = np.arange(signals.shape[1])[None, :] < np.asarray(runs["ticks"])[:, None]
    values = signals[valid]
    bad = ~np.isfinite(values)
    if bad.any():
        columns = ", ".join(str(c) for c in np.flatnonzero(bad.any(axis=0)))
        raise ValueError(f"the recorded online signals are not all finite ({int(bad.sum())} "
                         f"NaN or inf, in column {columns} of {count}: the controller's "
                         f"estimate, then its command): a monitor that reads them can be "
                         f"neither trained nor judged; drop the variants with signals: true")
    return values


def signal_statistics(runs: dict, count: int):
    """``(mean, std)`` of the first ``count`` online signals over the runs' ticks
    (`finite_signals`)."""
    values = finite_signals(runs, count)
    return values.mean(axis=0).tolist(), np.maximum(values.std(axis=0), 1e-6).tolist()


def train_head(encoder: HistoryRiskModel, features: np.ndarray, runs: dict,
               labels: np.ndarray, config: HistoryMonitorConfig,
               train: HistoryTrainConfig) -> HistoryRiskModel:
    """Stage 2: a monitor of ``config`` (its frames, stride, temporal model and
    signals) whose encoder is ``encoder``'s, frozen; only its head is trained, on the
    encoded runs ``features`` (`encode_runs`)."""
    if config.signals:
        mean, std = signal_statistics(runs, config.signals)
        config = dc.replace(config, signal_mean=mean, signal_std=std)
    config = dc.replace(config, height=encoder.config.height, width=encoder.config.width,
                        channels=list(encoder.config.channels),
                        features=encoder.config.features, pool=list(encoder.config.pool),
                        input_norm=encoder.config.input_norm)
    torch.manual_seed(train.seed)
    rng = np.random.default_rng(train.seed)
    model = HistoryRiskModel(config)
    model.encoder = copy.deepcopy(encoder.encoder)
    model.project = copy.deepcopy(encoder.project)
    for module in (model.encoder, model.project):
        for p in module.parameters():
            p.requires_grad_(False)
    rows, cols = np.nonzero(labels >= 0)
    seen = features[rows, cols]
    model.feature_mean.copy_(torch.from_numpy(seen.mean(axis=0)))
    model.feature_std.copy_(torch.from_numpy(np.maximum(seen.std(axis=0), 1e-3)))
    history = config.history_ticks(cols)
    x = torch.from_numpy(features[rows[:, None], history])
    s = (torch.from_numpy(np.asarray(runs["signals"], np.float32)[..., :config.signals]
                          [rows[:, None], history]) if config.signals else None)
    y = torch.from_numpy(labels[rows, cols].astype(np.float32))
    head = [p for p in model.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(head, lr=train.head_learning_rate,
                                  weight_decay=train.weight_decay)
    weight = _pos_weight(labels[rows, cols])
    schedule = _schedule(optimiser, train,
                         train.head_epochs * -(-len(rows) // (4 * train.batch_size)))
    averaged = _WeightMean(model, train, train.head_epochs)
    for epoch in range(train.head_epochs):
        model.train()
        order = torch.from_numpy(rng.permutation(len(rows)))
        for i in range(0, len(order), 4 * train.batch_size):
            b = order[i:i + 4 * train.batch_size]
            logits = model.head_logits(x[b], s[b] if s is not None else None)
            loss = F.binary_cross_entropy_with_logits(logits, y[b], pos_weight=weight)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            if schedule is not None:
                schedule.step()
        averaged.epoch_done(epoch)
    averaged.into_model()           # the frozen encoder's parameters: their own mean
    return model.eval()


def run_risks(model: HistoryRiskModel, features: np.ndarray, runs: dict,
              calibration=None) -> list:
    """The risk at every tick of each run (a list of 1-d arrays, one per run, as long
    as the run), from its encoded frames (and its online signals, which must be finite:
    `finite_signals`)."""
    if model.config.signals:
        finite_signals(runs, model.config.signals)
    out = []
    for r in range(len(features)):
        n = int(runs["ticks"][r])
        signals = np.asarray(runs["signals"][r, :n, :model.config.signals], np.float32)
        out.append(model.risk_from_features(features[r, :n], signals, calibration)
                   if n else np.zeros(0))
    return out
