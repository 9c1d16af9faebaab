"""Confirming the detector's flags over time: flag only when at least k of the last n
control ticks were flagged (a k-of-n rule), so that one odd frame does not hand over
control and one clear frame does not hand it back."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem


def check_k_of_n(flags_needed, window):
    """``(k, n)`` as ints if ``1 <= k <= n``; else a ValueError naming both."""
    ok = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
             for v in (flags_needed, window))
    if not ok or not 1 <= flags_needed <= window:
        raise ValueError(f"the k-of-n flag rule needs whole numbers 1 <= flags_needed (k) <= "
                         f"window (n), got flags_needed={flags_needed!r}, window={window!r}")
    return int(flags_needed), int(window)


def confirmed_flags(raw, history, flags_needed):
    """One tick of the k-of-n rule on arrays: ``raw`` ``(m,)`` this tick's flags,
    ``history`` ``(m, n - 1)`` the previous ``n - 1`` ticks' raw flags, newest first.
    Returns ``(confirmed (m,), the history for the next tick)``."""
    raw = np.asarray(raw, bool)
    history = np.asarray(history, bool).reshape(len(raw), -1)
    confirmed = raw.astype(int) + history.sum(axis=1) >= flags_needed
    shifted = np.concatenate([raw[:, None], history], axis=1)[:, :history.shape[1]]
    return confirmed, shifted


class FlagFilter(LeafSystem):
    """The detector's ``anomaly`` confirmed by a k-of-n rule over control ticks.

    .. pydrake_system::

        name: FlagFilter
        input_ports:
        - anomaly
        output_ports:
        - anomaly

    The output is 1 when this tick's input flag plus the input flags of the previous
    ``window - 1`` ticks (discrete state, updated every ``period`` s) count at least
    ``flags_needed``; the ticks before the first count as clear. ``flags_needed =
    window = 1`` passes the input through. The output depends on the input at once (no
    added delay when ``flags_needed`` = 1). Read at a tick after that tick's update, it
    is still the flag the tick acted on: the state keeps the time of
    its last update and one more past flag for that."""

    def __init__(self, *, flags_needed=1, window=1, period=0.05):
        super().__init__()
        self._k, self._n = check_k_of_n(flags_needed, window)
        if not period > 0:
            raise ValueError(f"FlagFilter: period must be > 0 s, got {period}")
        self._anomaly_in = self.DeclareVectorInputPort("anomaly", 1)
        # [time of the last update (s), the last n raw flags, newest first]
        self._state_index = self.DeclareDiscreteState(BasicVector(
            np.concatenate([[-np.inf], np.zeros(self._n)])))
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self._anomaly_out = self.DeclareVectorOutputPort("anomaly", 1, self._calc_anomaly)

    @property
    def k_of_n(self):
        return self._k, self._n

    def get_anomaly_input_port(self):
        return self._anomaly_in

    def get_anomaly_output_port(self):
        return self._anomaly_out

    def _raw(self, context):
        return np.array([self._anomaly_in.Eval(context)[0] >= 0.5])

    def _history(self, context):
        """The previous ``n - 1`` ticks' raw flags as the current tick's rule sees them."""
        state = context.get_discrete_state(self._state_index).get_value()
        updated_now = state[0] == context.get_time()      # read after this tick's update
        flags = state[2:] if updated_now else state[1:-1]
        return flags[None].astype(bool)

    def _update(self, context, discrete_state):
        state = context.get_discrete_state(self._state_index).get_value()
        raw = self._raw(context)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(
            np.concatenate([[context.get_time()], raw.astype(float), state[1:-1]]))

    def _calc_anomaly(self, context, output):
        confirmed, _ = confirmed_flags(self._raw(context), self._history(context), self._k)
        output.SetAtIndex(0, float(confirmed[0]))
