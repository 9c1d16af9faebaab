"""An ensemble of history monitors: several trainings of one monitor (other seeds: other
initial weights, batch order and colour jitter) whose raw risks are averaged at every
tick before one Platt calibration and one threshold. One training's ranking of an
environment it has never seen depends on its seed; the mean of several depends on it
less. `HistoryRiskEnsemble` holds the networks (one checkpoint); `MeanRisk` is the
LeafSystem that averages the members' `HistoryMonitor` scores online."""

from typing import Sequence

import numpy as np
from pydrake.systems.framework import LeafSystem
from torch import nn

from .history_monitor import HistoryMonitorConfig, HistoryRiskModel, platt

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
        `MeanRisk` over the members' monitors outputs at each tick of the same run."""
        raw = np.mean([m.risk_sequence(frames, signals) for m in self.members], axis=0)
        return calibration(raw) if calibration is not None else raw


class MeanRisk(LeafSystem):
    """The mean of ``members`` raw risks, Platt-calibrated, and its flag.

    .. pydrake_system::

        name: MeanRisk
        input_ports:
        - member_0
        - ...
        - member_{members-1}
        output_ports:
        - score
        - anomaly

    ``score`` is ``platt(mean of the inputs, *calibration)``; ``anomaly`` is 1.0 when
    ``score >= threshold``. Each input is one member's raw risk (a `HistoryMonitor`
    built with ``calibration=None``). Stateless: the members keep the history. Its
    outputs are named as `HistoryMonitor`'s, so either monitors a guarded loop."""

    def __init__(self, *, members: int, threshold: float, calibration=(1.0, 0.0)):
        super().__init__()
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"MeanRisk: threshold must be in [0, 1], got {threshold}")
        self._threshold = float(threshold)
        self._platt = tuple(float(v) for v in calibration)
        self._inputs = [self.DeclareVectorInputPort(f"member_{i}", 1)
                        for i in range(check_members(members))]
        self._score_port = self.DeclareVectorOutputPort("score", 1, self._calc_score)
        self._anomaly_port = self.DeclareVectorOutputPort("anomaly", 1, self._calc_anomaly)

    @property
    def threshold(self) -> float:
        return self._threshold

    def get_member_input_port(self, i: int):
        return self._inputs[i]

    def get_anomaly_output_port(self):
        return self._anomaly_port

    def get_score_output_port(self):
        return self._score_port

    def _calc_score(self, context, output):
        mean = float(np.mean([port.Eval(context)[0] for port in self._inputs]))
        output.SetAtIndex(0, float(platt(mean, *self._platt)))

    def _calc_anomaly(self, context, output):
        output.SetAtIndex(0, 1.0 if self._score_port.Eval(context)[0] >= self._threshold else 0.0)
