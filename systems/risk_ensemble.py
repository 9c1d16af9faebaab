"""An ensemble of history monitors: several trainings of one monitor (other seeds: other
initial weights, batch order and colour jitter) whose raw risks are averaged at every
tick before one Platt calibration and one threshold. One training's ranking of an
environment it has never seen depends on its seed; the mean of several depends on it
less. `HistoryRiskEnsemble` holds the networks (one checkpoint); `GroupedEncoder` runs
their per-frame encoders as one network, which is how a `HistoryMonitor` of an
ensemble encodes each frame online."""

from typing import Sequence

import numpy as np
import torch
from torch import nn

from .detector import OneDnnConv2d, detector_input
from .history_model import HistoryMonitorConfig, HistoryRiskModel, normalised, pooled

#: The most members an ensemble may have (each encodes every frame online).
MAX_MEMBERS = 32


def check_members(members) -> int:
    """``members`` as an int in [1, `MAX_MEMBERS`]; else a ValueError naming it."""
    if isinstance(members, bool) or not isinstance(members, (int, np.integer)) \
            or not 1 <= members <= MAX_MEMBERS:
        raise ValueError(f"an ensemble has 1 to {MAX_MEMBERS} members, got {members!r}")
    return int(members)


class HistoryRiskEnsemble(nn.Module):
    """``members`` `HistoryRiskModel` of one ``config`` (each with its own encoder and
    head). Its raw risk is the mean of the members' raw risks."""

    def __init__(self, config: HistoryMonitorConfig, members: int):
        super().__init__()
        self.config = config.validate()
        self.members = nn.ModuleList(HistoryRiskModel(config)
                                     for _ in range(check_members(members)))

    @classmethod
    def of(cls, models: Sequence[HistoryRiskModel]) -> "HistoryRiskEnsemble":
        """The ensemble of trained ``models`` (one config; their weights are copied)."""
        models = list(models)
        if len(models) < 2 or any(m.config != models[0].config for m in models):
            configs = len({repr(m.config) for m in models})
            raise ValueError(f"an ensemble needs at least two models, all of one config; got "
                             f"{len(models)} models with {configs} configs")
        ensemble = cls(models[0].config, len(models))
        for member, model in zip(ensemble.members, models):
            member.load_state_dict(model.state_dict())
        return ensemble.eval()

    def risk_sequence(self, frames: np.ndarray, signals: np.ndarray = None,
                      calibration=None) -> np.ndarray:
        """The risk at every tick of one recorded run: the mean of the members'
        `HistoryRiskModel.risk_sequence` (raw), then ``calibration``. What a
        `HistoryMonitor` of this ensemble outputs at each tick of the same run."""
        raw = np.mean([m.risk_sequence(frames, signals) for m in self.members], axis=0)
        return calibration(raw) if calibration is not None else raw


class GroupedEncoder(nn.Module):
    """The per-frame encoders of ``models`` (trainings of one config, with every
    ``BatchNorm2d`` folded into its convolution: `inference_model`'s) as one network:
    their first convolutions side by side on the one frame, each later one grouped (a
    group per member), the pooling over all channels at once and the members'
    projections as one batched product. `encode` is each member's `encode`, up to float
    rounding. On one torch thread a small encoder's time goes to calling its layers
    more than to their arithmetic: five members cost about twice one, not five times."""

    def __init__(self, models: Sequence[HistoryRiskModel]):
        super().__init__()
        models = list(models)
        self.config = models[0].config
        self.member_count = len(models)
        layers, shared_input = [], True         # the first convolution reads the frame
        for column in zip(*(model.encoder for model in models)):
            layer = column[0]
            if isinstance(layer, nn.Conv2d):
                layers.append(self._grouped(column, shared_input))
                shared_input = False
            elif isinstance(layer, (nn.ReLU, nn.MaxPool2d, nn.Identity)):
                layers.append(layer)        # channel by channel: the same for every group
            else:
                raise TypeError(f"GroupedEncoder: cannot group a {type(layer).__name__} "
                                f"(fold BatchNorm into its convolution first: "
                                f"inference_model)")
        self.encoder = nn.Sequential(*layers).to(memory_format=torch.channels_last)
        linears = [model.project[0] for model in models]   # then a ReLU: `encode`'s
        self.register_buffer("weight", torch.stack([l.weight.detach() for l in linears]))
        self.register_buffer("bias", torch.stack([l.bias.detach() for l in linears])[:, None])

    def _grouped(self, column, shared_input: bool) -> nn.Conv2d:
        """One convolution for the members' ``column``: on the shared frame, their
        output channels side by side; later, a group per member (an `OneDnnConv2d`, as
        `inference_model` makes each member's)."""
        first, count = column[0], len(column)
        conv = OneDnnConv2d(first.in_channels * (1 if shared_input else count),
                         first.out_channels * count, first.kernel_size, first.stride,
                         first.padding, first.dilation, groups=1 if shared_input else count,
                         bias=True)
        with torch.no_grad():
            conv.weight.copy_(torch.cat([c.weight for c in column]))
            conv.bias.copy_(torch.cat([c.bias if c.bias is not None else
                                       torch.zeros(c.out_channels) for c in column]))
        return conv

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 RGB ``(N, H, W, 3)`` at the configured size -> every member's features
        ``(N, members, features)``."""
        x = normalised(detector_input(images, self.config.image_config), self.config.input_norm)
        maps = pooled(self.encoder(x), self.config.pool)
        per_member = maps.reshape(len(maps), self.member_count, -1).transpose(0, 1)
        return torch.relu(torch.bmm(per_member, self.weight.transpose(1, 2))
                          + self.bias).transpose(0, 1)


def grouped_gru(grus: Sequence[nn.GRU]) -> nn.GRU:
    """One single-layer GRU that runs the members' ``grus`` side by side: input and
    hidden state are the members' concatenated (member ``m``'s units at ``m * hidden``),
    every weight block-diagonal per gate, so each member's units read only its own
    input and state. Its outputs are the members' side by side, up to float rounding."""
    grus = list(grus)
    first, count = grus[0], len(grus)
    if any(g.num_layers != 1 or g.bidirectional or not g.bias or not g.batch_first
           or (g.input_size, g.hidden_size) != (first.input_size, first.hidden_size)
           for g in grus):
        raise ValueError("grouped_gru: the members' GRUs must be alike: one layer, one "
                         "direction, with biases, batch_first")
    size, hidden = first.input_size, first.hidden_size
    fused = nn.GRU(size * count, hidden * count, batch_first=True)
    with torch.no_grad():
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"):
            target = getattr(fused, name)
            target.zero_()
            width = size if name == "weight_ih_l0" else hidden
            for m, gru in enumerate(grus):
                source = getattr(gru, name)
                for gate in range(3):           # PyTorch stacks the gates r, z, n
                    rows = slice(gate * hidden * count + m * hidden,
                                 gate * hidden * count + (m + 1) * hidden)
                    block = source[gate * hidden:(gate + 1) * hidden]
                    if name.startswith("bias"):
                        target[rows] = block
                    else:
                        target[rows, m * width:(m + 1) * width] = block
    return fused.eval()
