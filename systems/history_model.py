"""The network of the monitor over the image history: the risk that the loop fails
within ``T`` seconds, from the last ``frames`` camera frames (as per-frame features)
and, when asked, the signals the loop has online (the controller's outputs).
`HistoryMonitorConfig` says what it reads, `HistoryRiskModel` is the network;
`reachwatch.systems.history_monitor.HistoryMonitor` is the LeafSystem that keeps the
history in its Context.

The model sees, at tick ``t``, the frames of ticks ``t - (frames - 1) * stride, ...,
t - stride, t`` (ticks before the run's first repeat its first frame), so the same
function of a recorded run (`HistoryRiskModel.risk_sequence`) gives what the system
outputs online, tick by tick."""

import dataclasses as dc
from typing import List

import numpy as np
import torch
from scipy.special import expit
from torch import nn

from .bounds import bounded, check_bounds
from .checks import short
from .detector import DetectorConfig, detector_input, resize_for_detector

#: How the per-frame features of the history are combined: ``stack`` concatenates them
#: into a small MLP (one frame: the single-frame monitor), ``gru`` runs a GRU over them.
TEMPORAL_MODELS = ("stack", "gru")

#: How a frame is normalised before the encoder: ``fixed`` only by `detector_input`'s
#: constants (mean = std = 0.5 on every channel); ``per_frame`` then also by the frame's
#: own statistics (each channel's mean removed, divided by the frame's std), so a frame's
#: overall brightness, contrast and colour cast (the hour, the sky) do not reach the
#: encoder.
INPUT_NORMS = ("fixed", "per_frame")
#: Added to a frame's std before dividing by it (a uniform frame stays finite).
FRAME_STD_FLOOR = 1e-3


def check_input_norm(where: str, value) -> str:
    """``value`` if it is one of `INPUT_NORMS`; else a ValueError naming ``where``
    (the field's path up to ``input_norm``)."""
    if value not in INPUT_NORMS:
        raise ValueError(f"{where}input_norm must be one of {INPUT_NORMS}, got {short(value)}")
    return value


def check_pool(where: str, pool, height: int, width: int, layers: int):
    """A ValueError naming ``where`` (the field's path up to ``pool``) when the grid
    ``pool`` does not fit in the last map of an encoder of ``layers`` layers (each
    halves the frame) at ``height`` x ``width`` px."""
    size = [int(height) >> int(layers), int(width) >> int(layers)]
    if pool[0] > size[0] or pool[1] > size[1]:
        raise ValueError(f"{where}pool {list(pool)} must fit in the encoder's last map, "
                         f"{size[0]} x {size[1]} cells at {height} x {width} px with "
                         f"{layers} layers (at most [{size[0]}, {size[1]}])")


@dc.dataclass
class HistoryMonitorConfig:
    """The monitor's network and what it reads: ``frames`` frames ``stride`` ticks
    apart, each resized to ``height`` x ``width`` and encoded by a small CNN
    (``channels``) into ``features`` numbers; ``signals`` online numbers per tick
    (0: images only), standardised with ``signal_mean`` / ``signal_std``; ``temporal``
    one of `TEMPORAL_MODELS` with ``hidden`` units. ``within`` (s) is the T of "fails
    within T s" that the risk predicts. ``input_norm``: one of `INPUT_NORMS` (a
    checkpoint that does not say was trained ``fixed``). ``pool``: the CNN's last
    feature map is averaged over a grid of ``pool`` = [rows, columns] cells before the
    projection to ``features``: ``[1, 1]`` averages it whole, so where in the frame a
    pattern lies (the runway's edge left or right of the centre) is lost; a finer grid
    keeps it. The grid must fit in the map (``height`` and ``width`` halved once per
    entry of ``channels``)."""
    frames: int = bounded(8, 1, 64, whole=True)
    stride: int = bounded(1, 1, 100, whole=True, unit="ticks")
    height: int = bounded(48, 16, 512, whole=True, unit="px")
    width: int = bounded(80, 16, 512, whole=True, unit="px")
    channels: List[int] = bounded(default_factory=lambda: [16, 32, 48], low=1, high=512,
                                  whole=True, each=True, items=(1, None))
    features: int = bounded(32, 1, 1024, whole=True)
    signals: int = bounded(0, 0, 64, whole=True)
    signal_mean: List[float] = dc.field(default_factory=list)
    signal_std: List[float] = dc.field(default_factory=list)
    temporal: str = "stack"
    hidden: int = bounded(32, 1, 1024, whole=True)
    within: float = bounded(2.0, 0.0, low_open=True, unit="s")
    input_norm: str = "per_frame"
    pool: List[int] = bounded(default_factory=lambda: [1, 1], low=1, high=64, whole=True,
                              each=True, items=(2, 2))

    def validate(self):
        check_bounds(self, "history monitor ")
        check_pool("history monitor ", self.pool, self.height, self.width, len(self.channels))
        if self.temporal not in TEMPORAL_MODELS:
            raise ValueError(f"history monitor temporal must be one of {TEMPORAL_MODELS}, got "
                             f"{self.temporal!r}")
        check_input_norm("history monitor ", self.input_norm)
        if len(self.signal_mean) not in (0, self.signals) or \
                len(self.signal_std) != len(self.signal_mean):
            raise ValueError(f"history monitor signal_mean and signal_std need {self.signals} "
                             f"numbers each (or none), got {len(self.signal_mean)} and "
                             f"{len(self.signal_std)}")
        return self

    @property
    def image_config(self) -> DetectorConfig:
        """The per-frame resize and normalisation (the detector's, at this size)."""
        return DetectorConfig(height=self.height, width=self.width)

    def history_ticks(self, tick) -> np.ndarray:
        """The ticks whose frames the risk at ``tick`` reads (oldest first, clamped at 0);
        for an array of ticks, one row each."""
        offsets = np.arange(self.frames - 1, -1, -1) * self.stride
        return np.maximum(np.asarray(tick)[..., None] - offsets, 0)


def normalised(x: torch.Tensor, input_norm: str) -> torch.Tensor:
    """The encoder's input from `detector_input`'s ``(N, 3, H, W)``: with ``input_norm``
    ``per_frame`` each frame standardised on its own, else as it is."""
    if input_norm == "per_frame":
        return ((x - x.mean(dim=(2, 3), keepdim=True))
                / (x.std(dim=(1, 2, 3), keepdim=True) + FRAME_STD_FLOOR))
    return x


def pooled(maps: torch.Tensor, pool) -> torch.Tensor:
    """The encoder's last maps ``(N, C, h, w)`` averaged over the grid ``pool`` =
    [rows, columns] -> ``(N, C * rows * columns)``, each channel's cells together."""
    if list(pool) == [1, 1]:        # as before the grid: older checkpoints' bits
        return maps.mean(dim=(2, 3))
    return nn.functional.adaptive_avg_pool2d(maps, pool).flatten(1)


#: The least raw probability `logit_of` takes apart from 0 (below it, 0 included, all
#: alike); at the top, the largest float below 1. A raw risk is a float64 sigmoid of
#: the network's float32 logit, so only a logit below about -690 or above about 36.7
#: meets them. (They were 1e-7 and 1 - 1e-7: with a calibration slope of 0.28, the
#: fourth protocol run's, most of a held-out environment's ticks shared the one
#: calibrated risk 0.0057, and their ties pulled its AUROC down by up to 0.1.)
PROBABILITY_FLOOR = 1e-300


def logit_of(q):
    """``log(q / (1 - q))`` of raw probabilities ``q`` (arrays too), ``q`` clipped to
    [`PROBABILITY_FLOOR`, the largest float below 1] first."""
    q = np.clip(np.asarray(q, float), PROBABILITY_FLOOR, np.nextafter(1.0, 0.0))
    return np.log(q) - np.log1p(-q)


def platt(q, a: float = 1.0, b: float = 0.0):
    """``sigmoid(a * logit(q) + b)``: Platt scaling of a raw probability ``q`` (works on
    arrays; `logit_of` ``q``). Monotone for ``a > 0``: it keeps the raw risks' order,
    ties made only below `PROBABILITY_FLOOR`."""
    return expit(a * logit_of(q) + b)


class HistoryRiskModel(nn.Module):
    """Per-frame CNN encoder, then the temporal model over the history's features (with
    the standardised signals beside each frame's), then one logit of "fails within
    ``within`` s"."""

    def __init__(self, config: HistoryMonitorConfig):
        super().__init__()
        self.config = config.validate()
        layers, c = [], 3
        for out in config.channels:
            layers += [nn.Conv2d(c, out, 3, padding=1, bias=False), nn.BatchNorm2d(out),
                       nn.ReLU(inplace=True), nn.MaxPool2d(2)]
            c = out
        self.encoder = nn.Sequential(*layers)
        self.project = nn.Sequential(nn.Linear(c * config.pool[0] * config.pool[1],
                                               config.features), nn.ReLU())
        width = config.features + config.signals
        if config.temporal == "gru":
            self.gru = nn.GRU(width, config.hidden, batch_first=True)
            self.head = nn.Linear(config.hidden, 1)
        else:
            self.head = nn.Sequential(nn.Linear(width * config.frames, config.hidden), nn.ReLU(),
                                      nn.Linear(config.hidden, 1))
        mean = config.signal_mean or [0.0] * config.signals
        std = config.signal_std or [1.0] * config.signals
        self.register_buffer("signal_mean", torch.tensor(mean, dtype=torch.float32))
        self.register_buffer("signal_std", torch.tensor(std, dtype=torch.float32).clamp_min(1e-6))
        # the features' standardisation before the head, set when the head is trained
        self.register_buffer("feature_mean", torch.zeros(config.features))
        self.register_buffer("feature_std", torch.ones(config.features))

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 RGB ``(N, H, W, 3)`` at the configured size -> features ``(N, features)``."""
        return self.encode_input(detector_input(images, self.config.image_config))

    def encode_input(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised float ``(N, 3, H, W)`` (`detector_input`'s) -> features
        ``(N, features)``: where training changes the input (colour jitter) first. With
        ``input_norm`` ``per_frame`` each frame is standardised on its own here."""
        return self.project(pooled(self.encoder(normalised(x, self.config.input_norm)),
                                   self.config.pool))

    def head_input(self, features: torch.Tensor, signals: torch.Tensor = None) -> torch.Tensor:
        """Raw ``features`` ``(..., features)`` and ``signals`` ``(..., signals)`` ->
        what the temporal model reads per frame ``(..., features + signals)``: both
        standardised, side by side (element-wise, so one frame's row is the same numbers
        whether it comes alone or in a batch)."""
        features = (features - self.feature_mean) / self.feature_std
        if self.config.signals:
            return torch.cat([features, (signals - self.signal_mean) / self.signal_std], dim=-1)
        return features

    def head_logits(self, features: torch.Tensor, signals: torch.Tensor = None) -> torch.Tensor:
        """``features`` ``(N, frames, features)`` and ``signals`` ``(N, frames, signals)``
        (both raw; standardised here) -> logits ``(N,)``."""
        x = self.head_input(features, signals)
        if self.config.temporal == "gru":
            return self.head(self.gru(x)[0][:, -1]).squeeze(-1)
        return self.head(x.flatten(1)).squeeze(-1)

    def forward(self, images: torch.Tensor, signals: torch.Tensor = None) -> torch.Tensor:
        """uint8 ``(N, frames, H, W, 3)`` (and ``(N, frames, signals)``) -> logits ``(N,)``."""
        n, k = images.shape[:2]
        features = self.encode(images.reshape(n * k, *images.shape[2:])).reshape(n, k, -1)
        return self.head_logits(features, signals)

    @torch.no_grad()
    def encode_frames(self, frames: np.ndarray, batch: int = 256) -> torch.Tensor:
        """Features ``(T, features)`` of uint8 frames ``(T, H, W, 3|4)`` of any size
        (resized as online)."""
        self.eval()
        images = torch.from_numpy(resize_for_detector(frames, self.config.image_config))
        return torch.cat([self.encode(images[i:i + batch]) for i in range(0, len(images), batch)])

    @torch.no_grad()
    def risk_from_features(self, features, signals=None, calibration=None) -> np.ndarray:
        """The risk at every tick of one run from its per-tick ``features``
        ``(T, features)`` (`encode_frames`) and ``signals`` ``(T, signals)``."""
        self.eval()
        features = torch.as_tensor(features, dtype=torch.float32)
        index = torch.from_numpy(self.config.history_ticks(np.arange(len(features))))
        sig = (torch.as_tensor(np.asarray(signals, np.float32))[index]
               if self.config.signals else None)
        # the sigmoid in float64: in float32 it rounds to 1.0 from a logit of about 17
        raw = torch.sigmoid(self.head_logits(features[index], sig).double()).numpy()
        return calibration(raw) if calibration is not None else raw

    def risk_sequence(self, frames: np.ndarray, signals: np.ndarray = None,
                      calibration=None) -> np.ndarray:
        """The risk at every tick of one recorded run: ``frames`` uint8 ``(T, H, W, 3|4)``
        (any size: resized as online), ``signals`` ``(T, signals)``; ``calibration`` maps
        the raw probability (e.g. a `PlattCalibration`). What `HistoryMonitor` outputs
        at each tick of the same run."""
        return self.risk_from_features(self.encode_frames(frames), signals, calibration)
