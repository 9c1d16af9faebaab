"""The runtime monitor over the image history: `HistoryMonitor`, the LeafSystem that
keeps the history of one `HistoryRiskModel`, or of a `HistoryRiskEnsemble`'s members,
in its Context and outputs their (mean) risk, calibrated, and its flag.

The model sees, at tick ``t``, the frames of ticks ``t - (frames - 1) * stride, ...,
t - stride, t`` (ticks before the run's first repeat its first frame), so the same
function of a recorded run (`HistoryRiskModel.risk_sequence`) gives what the system
outputs online, tick by tick."""

import numpy as np
import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer
from pydrake.systems.sensors import ImageRgba8U

from .detector import check_trained_size, flag_of, inference_model, resize_for_detector
from .frame_worker import add_frame_worker
from .history_model import HistoryRiskModel, platt
from .ports import weak_callback
from .risk_ensemble import GroupedEncoder, HistoryRiskEnsemble, grouped_gru
from .torch_threads import one_torch_thread


class FrameEncoder:
    """A `HistoryMonitor`'s frame work, picklable (`FrameWorker` runs it in a process of
    its own): a camera frame, uint8 ``(H, W, 3|4)``, resized to the model's size, then
    every member's features (one member's, or a `GroupedEncoder`'s of all), float32
    ``(members * features,)``, on one torch thread."""

    def __init__(self, members, image_config):
        self._members = members
        self._grouped = GroupedEncoder(members) if len(members) > 1 else None
        self._image_config = image_config

    def __call__(self, rgba: np.ndarray) -> np.ndarray:
        image = torch.from_numpy(resize_for_detector(rgba[None], self._image_config))
        with one_torch_thread():
            if self._grouped is None:
                return self._members[0].encode(image)[0].numpy()
            return self._grouped.encode(image)[0].reshape(-1).numpy()


class HistoryMonitor(LeafSystem):
    """The risk that the loop fails within ``config.within`` s, from the image history:
    of one `HistoryRiskModel`, or the mean of a `HistoryRiskEnsemble`'s members' raw
    risks (their per-frame encoders run as one `GroupedEncoder`).

    .. pydrake_system::

        name: HistoryMonitor
        input_ports:
        - color_image
        - signals (when config.signals > 0)
        output_ports:
        - frame_features
        - score
        - anomaly

    Every ``period`` s (the control tick) the current frame is encoded once (every
    member's features, then the signals: ``frame_features``, which Drake caches) and
    joins what the discrete state keeps. ``score`` is the calibrated risk at the current time, from the
    kept state and the current frame (so the fallback switch, updated at the same tick,
    sees this tick's frame; ``calibration`` None: the raw risk, whose ``anomaly`` is then
    no operating flag: the threshold is on the calibrated scale); ``anomaly`` is 1.0
    when ``score >= threshold``, or when it is NaN (a signal that is: `flag_of`). Ports
    are named as `AnomalyDetector`'s (connect them by name or getter: their indices
    differ), so either monitors a guarded loop.

    What the state keeps depends on the temporal model (for each member). ``stack``: the
    rows of the last ``(frames - 1) * stride`` ticks. ``gru``: the GRU's hidden state in each window
    still open, that is the windows of the next ``(frames - 1) * stride`` ticks, each
    begun from zero at its first tick; a tick advances the ``frames`` windows that
    hold it by one step, together, instead of re-running a window of ``frames`` steps.
    Either way ``score`` is the offline `HistoryRiskModel.risk_sequence` of the run
    (the same function, up to float rounding). ``image_size = (height, width)`` of the
    camera frames it was trained on, when given, is enforced (each frame is resized to
    the model's size, so a camera of another size or shape would pass unseen).

    ``encoder_process=True`` runs the frame work (the resize and the members' encoders)
    in a process of its own (`FrameWorker`), begun at each tick's publish event, when
    the tick's frame is rendered, so that it runs on another core while the loop
    evaluates its controller; the row then reads its answer for the same pixels (the
    same numbers: the same code on one torch thread). It gains when the loop asks the
    controller's output before the monitor's at each tick, as the guarded loop's
    `FallbackSwitch` does, and the machine has a core to spare."""

    def __init__(self, *, model, threshold: float, period: float, calibration=(1.0, 0.0),
                 image_size=None, encoder_process: bool = False):
        super().__init__()
        self._image_size = tuple(image_size) if image_size is not None else None
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"HistoryMonitor: threshold must be in [0, 1], got {threshold}")
        if not (np.isfinite(period) and period > 0):
            raise ValueError(f"HistoryMonitor: period must be > 0 s, got {period}")
        members = (list(model.members) if isinstance(model, HistoryRiskEnsemble) else
                   [model] if isinstance(model, HistoryRiskModel) else None)
        if members is None:
            raise TypeError(f"HistoryMonitor: model must be a HistoryRiskModel or a "
                            f"HistoryRiskEnsemble, got {type(model).__name__}")
        # Conv-BN folded, channels-last; an ensemble's encoders as one network
        self._members = [inference_model(member) for member in members]
        self._config = model.config
        self._encode_frame = FrameEncoder(self._members, self._config.image_config)
        self._threshold = float(threshold)
        self._platt = None if calibration is None else tuple(float(v) for v in calibration)
        c = self._config
        self._encoded = len(members) * c.features       # the members' features, per row
        self._width = self._encoded + c.signals
        self._gru = c.temporal == "gru"
        # the members' GRUs as one (one member: its own)
        self._gru_units = (None if not self._gru else self._members[0].gru
                           if len(members) == 1 else grouped_gru(m.gru for m in self._members))
        self._slots = (c.frames - 1) * c.stride          # past ticks kept / open windows
        self._kept = len(members) * c.hidden if self._gru else self._width
        self._image_port = self.DeclareAbstractInputPort(
            "color_image", AbstractValue.Make(ImageRgba8U()))
        self._signals_port = (self.DeclareVectorInputPort("signals", c.signals)
                              if c.signals else None)
        # [ticks seen so far, then a row per kept tick (stack: its features, oldest
        # first) or per open window (gru: its hidden state, the next tick's first)]
        self._history = self.DeclareDiscreteState(BasicVector(
            np.zeros(1 + self._slots * self._kept)))
        self._row_port = self.DeclareVectorOutputPort(
            "frame_features", self._width, self._calc_row,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        if self._gru:
            # neither the entry (which holds its system) nor a callback holding this
            # system strongly is kept on it: either would keep it, and its whole
            # diagram, alive for good (a cycle through C++, `weak_callback`)
            shape = (self._slots + 1, len(self._members), c.hidden)
            self._windows_index = self.DeclareCacheEntry(
                "the open GRU windows advanced by this tick's frame", ValueProducer(
                    allocate=lambda: AbstractValue.Make(np.zeros(shape, np.float32)),
                    calc=weak_callback(self._calc_windows)),
                {self.all_input_ports_ticket(), self.xd_ticket()}).cache_index()
        if self._slots:
            self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self._score_port = self.DeclareVectorOutputPort("score", 1, self._calc_score)
        self._anomaly_port = self.DeclareVectorOutputPort("anomaly", 1, self._calc_anomaly)
        self._worker = (add_frame_worker(self, work=self._encode_frame,
                                         image_port=self._image_port, period=period,
                                         name="HistoryMonitor") if encoder_process else None)

    @property
    def threshold(self) -> float:
        return self._threshold

    def get_color_image_input_port(self):
        return self._image_port

    def get_signals_input_port(self):
        return self._signals_port

    def get_anomaly_output_port(self):
        return self._anomaly_port

    def get_score_output_port(self):
        return self._score_port

    def get_frame_features_output_port(self):
        return self._row_port

    @property
    def frame_worker(self):
        """The `FrameWorker` of ``encoder_process=True``, else None."""
        return self._worker

    def _calc_row(self, context, row):
        rgba = self._image_port.Eval(context).data
        check_trained_size(rgba, self._image_size, "HistoryMonitor", "monitor")
        # the signals first: they ask the controller, which works while the frame's
        # process does (``encoder_process``)
        signals = None if self._signals_port is None else self._signals_port.Eval(context)
        features = (self._encode_frame(rgba) if self._worker is None
                    else self._worker.work(rgba))
        if signals is not None:
            features = np.concatenate([features, signals])
        row.SetFromVector(features.astype(float))

    def _rows(self, context):
        """The rows of the kept ticks and the current one, ``(slots + 1, width)``, with
        ticks before the run's first filled by its first row (``stack``)."""
        current = self._row_port.Eval(context)
        state = context.get_discrete_state(self._history).get_value()
        seen = int(round(state[0]))
        kept = state[1:].reshape(self._slots, self._width)
        rows = np.vstack([kept, current[None]])
        if seen < self._slots:
            first = rows[self._slots - seen] if seen else current
            rows[:self._slots - seen] = first
        return rows

    def _member_input(self, member: int, rows: torch.Tensor) -> torch.Tensor:
        """What ``member``'s temporal model reads of ``rows`` ``(..., width)``: its
        features and the signals, standardised (`HistoryRiskModel.head_input`)."""
        f = self._config.features
        return self._members[member].head_input(rows[..., member * f:(member + 1) * f],
                                                rows[..., self._encoded:])

    def _open_windows(self, context) -> np.ndarray:
        """The cache entry `_calc_windows` fills, for ``context``."""
        return self.get_cache_entry(self._windows_index).Eval(context)

    def _calc_windows(self, context, value):
        """The hidden states ``(slots + 1, members, hidden)`` of the windows of ticks
        ``t .. t + slots`` after this tick ``t``'s frame (``gru``): row ``d`` is the
        window of tick ``t + d``; row 0 is complete. Rows ``d = 0, stride, ..`` hold tick ``t``
        and step; the others wait. At the run's first tick every window has seen the
        first frame at each of its ticks so far (the ticks before it repeat it)."""
        c = self._config
        row = torch.from_numpy(self._row_port.Eval(context).astype(np.float32))
        state = context.get_discrete_state(self._history).get_value()
        units = len(self._members) * c.hidden          # the members' side by side
        with one_torch_thread():
            x = torch.cat([self._member_input(m, row) for m in range(len(self._members))])
            if state[0] == 0:
                # the window of tick d has read the first frame frames - ceil(d / stride)
                # times; steps[i] is the state after i + 1 of them
                steps = self._gru_units(x.expand(1, c.frames, -1))[0][0]
                repeats = c.frames - -(-np.arange(self._slots + 1) // c.stride)
                windows = steps[torch.from_numpy(repeats - 1)]
            else:
                windows = torch.cat([torch.from_numpy(
                    state[1:].astype(np.float32).reshape(self._slots, units)),
                    torch.zeros(1, units)])                     # the newest begins at zero
                due = windows[::c.stride]
                windows[::c.stride] = self._gru_units(
                    x.expand(len(due), 1, -1), due[None].contiguous())[1][0]
        value.set_value(windows.numpy().reshape(self._slots + 1, len(self._members), c.hidden))

    def _update(self, context, discrete_state):
        state = context.get_discrete_state(self._history).get_value()
        if self._gru:
            kept = self._open_windows(context)[1:]          # (slots, members, hidden)
        else:
            kept = self._rows(context)[1:]
        out = np.concatenate([[min(state[0] + 1, self._slots)], kept.reshape(-1)])
        discrete_state.get_mutable_vector(self._history).SetFromVector(out)

    def _calc_score(self, context, output):
        c = self._config
        risks = []
        if self._gru:
            complete = torch.from_numpy(self._open_windows(context)[0])   # (members, hidden)
            with one_torch_thread():
                for m, member in enumerate(self._members):
                    logit = member.head(complete[m:m + 1]).squeeze(-1)
                    risks.append(float(torch.sigmoid(logit.double())[0]))
        else:
            rows = self._rows(context)[::-1][::c.stride][::-1]   # every stride-th, newest last
            x = torch.from_numpy(rows.astype(np.float32))[None]
            f = c.features
            with one_torch_thread():
                for m, member in enumerate(self._members):
                    logit = member.head_logits(x[..., m * f:(m + 1) * f], x[..., self._encoded:])
                    risks.append(float(torch.sigmoid(logit.double())[0]))
        risk = sum(risks) / len(risks)          # one member: its risk, bit for bit
        output.SetAtIndex(0, risk if self._platt is None else float(platt(risk, *self._platt)))

    def _calc_anomaly(self, context, output):
        output.SetAtIndex(0, flag_of(self._score_port.Eval(context)[0], self._threshold))
