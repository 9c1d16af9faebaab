"""Dead reckoning: while the detector flags the image, carry the last trusted estimate
forward with the steering and speed the aircraft itself commanded."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from .plant import WHEELBASE_M


def propagate_estimate(estimate, steering, speed, duration, *, wheelbase=WHEELBASE_M):
    """The taxi estimate ``[..., 2]`` = ``[px m, theta deg]`` after ``duration`` s at a
    constant ``steering`` (rad) and ``speed`` (m/s), by the plant's own kinematics
    (``px' = v sin(theta)``, ``theta' = (v / L) tan(steering)``), in closed form: exact
    for a steering held over the period, as the loop holds it. Works on arrays."""
    estimate = np.asarray(estimate, float)
    px, theta = estimate[..., 0], np.deg2rad(estimate[..., 1])
    speed = np.asarray(speed, float)
    rate = speed / wheelbase * np.tan(np.asarray(steering, float))
    theta_end = theta + rate * duration
    turning = np.abs(rate) > 1e-12
    safe_rate = np.where(turning, rate, 1.0)
    px_end = px + np.where(turning, speed / safe_rate * (np.cos(theta) - np.cos(theta_end)),
                           speed * np.sin(theta) * duration)
    return np.stack([px_end, np.rad2deg(theta_end)], axis=-1)


class DeadReckoning(LeafSystem):
    """The controller's estimate while the image is trusted; while it is flagged, the
    last trusted estimate carried forward by the taxi kinematics with the steering and
    speed that were applied (the aircraft knows both). Honest: no true state.

    .. pydrake_system::

        name: DeadReckoning
        input_ports:
        - estimate
        - anomaly
        - steering_angle
        - speed
        output_ports:
        - estimate

    ``estimate`` in and out is ``[px m, theta deg]`` (TaxiNet's). ``steering_angle``
    (rad) is what the loop applies from this tick on (the fallback switch's output) and
    ``speed`` (m/s) the speed applied since the previous tick (the switch's speed,
    read before its update). Discrete state, updated every ``period`` s: the estimate
    this tick believed, the steering applied from it, and whether any image has been
    trusted yet; until one has, the output is the controller's own estimate (there is
    nothing trusted to carry forward). The output does not depend on the
    ``steering_angle`` input, so the output can feed the steering without a loop.
    """

    def __init__(self, *, period=0.05, wheelbase=WHEELBASE_M):
        super().__init__()
        if not period > 0:
            raise ValueError(f"DeadReckoning: period must be > 0 s, got {period}")
        if not wheelbase > 0:
            raise ValueError(f"DeadReckoning: wheelbase must be > 0 m, got {wheelbase}")
        self._period, self._wheelbase = float(period), float(wheelbase)
        self._estimate_in = self.DeclareVectorInputPort("estimate", 2)
        self._anomaly_in = self.DeclareVectorInputPort("anomaly", 1)
        self._steering_in = self.DeclareVectorInputPort("steering_angle", 1)
        self._speed_in = self.DeclareVectorInputPort("speed", 1)
        # [px m, theta deg] believed at the last tick, steering applied from it, trusted
        self._state_index = self.DeclareDiscreteState(BasicVector([0.0, 0.0, 0.0, 0.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)
        self._estimate_out = self.DeclareVectorOutputPort(
            "estimate", 2, self._calc_estimate,
            prerequisites_of_calc={self.input_port_ticket(p.get_index())
                                   for p in (self._estimate_in, self._anomaly_in,
                                             self._speed_in)}
            | {self.discrete_state_ticket(self._state_index)})

    def get_estimate_input_port(self):
        return self._estimate_in

    def get_anomaly_input_port(self):
        return self._anomaly_in

    def get_steering_angle_input_port(self):
        return self._steering_in

    def get_speed_input_port(self):
        return self._speed_in

    def get_estimate_output_port(self):
        return self._estimate_out

    def _belief(self, context):
        state = context.get_discrete_state(self._state_index).CopyToVector()
        flagged = self._anomaly_in.Eval(context)[0] >= 0.5
        if not flagged or state[3] < 0.5:
            return self._estimate_in.Eval(context).copy()
        return propagate_estimate(state[:2], state[2], self._speed_in.Eval(context)[0],
                                  self._period, wheelbase=self._wheelbase)

    def _calc_estimate(self, context, output):
        output.SetFromVector(self._belief(context))

    def _update(self, context, discrete_state):
        trusted = context.get_discrete_state(self._state_index).GetAtIndex(3) >= 0.5
        flagged = self._anomaly_in.Eval(context)[0] >= 0.5
        belief = self._belief(context)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(
            [belief[0], belief[1], self._steering_in.Eval(context)[0],
             float(trusted or not flagged)])
