"""The fallback switch: when the detector flags the image, trade speed for safety."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

STRATEGIES = ("slow_down", "brake")
#: Steering while flagged: the controller's own, the P-controller on the dead-reckoned
#: estimate (honest), or on the true state (privileged, a reference only).
STEERING = ("taxinet", "dead_reckoning", "oracle")


#: The fallbacks compared by default: the paper's slow-down, braking, dead reckoning
#: with slow-down (honest), and slow-down with the true state's steering (privileged:
#: the paper's reference point, never an honest result).
DEFAULT_FALLBACKS = ("slow_down", "brake", "slow_down+dead_reckoning", "slow_down+oracle")


def fallback_parts(name: str):
    """``(strategy, steering)`` of a fallback's name: a speed strategy alone
    (``"slow_down"``, TaxiNet keeps steering) or ``"strategy+steering"`` (e.g.
    ``"slow_down+dead_reckoning"``, ``"slow_down+oracle"``)."""
    strategy, _, steering = str(name).partition("+")
    steering = steering or "taxinet"
    if strategy not in STRATEGIES or steering not in STEERING:
        raise ValueError(f"fallback '{name}': write a speed strategy {STRATEGIES}, optionally "
                         f"followed by '+' and a steering {STEERING[1:]} (e.g. "
                         f"'slow_down+dead_reckoning')")
    return strategy, steering


def fallback_name(strategy: str, steering: str = "taxinet") -> str:
    """The inverse of `fallback_parts`."""
    return strategy if steering == "taxinet" else f"{strategy}+{steering}"


def next_speed(speed, flagged, *, nominal, strategy="slow_down", slow_down_step=0.01,
               brake_deceleration=1.0, resume_acceleration=0.0, period=0.05):
    """Speed (m/s) for the next tick. ``slow_down`` (the paper): -0.01 m/s per tick
    while flagged; ``brake``: -``brake_deceleration`` m/s^2 while flagged. Both stop at
    0. When the image is clear the speed returns to ``nominal`` (m/s, the loop's own
    speed) at once
    (``resume_acceleration`` = 0, the paper's rule), or climbs back at
    ``resume_acceleration`` m/s^2: then one clear frame in a run of flagged ones costs
    the braking one tick's worth of speed instead of all of it. Works on arrays."""
    speed, flagged = np.asarray(speed, float), np.asarray(flagged, bool)
    step = slow_down_step if strategy == "slow_down" else brake_deceleration * period
    resumed = (np.full_like(speed, nominal) if not resume_acceleration else
               np.minimum(speed + resume_acceleration * period, nominal))
    return np.where(flagged, np.maximum(speed - step, 0.0), resumed)


def check_resume_acceleration(value) -> float:
    """``value`` as a float >= 0 (m/s^2; 0 = back to nominal speed at once), or ValueError."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (np.isfinite(number) and number >= 0):
        raise ValueError(f"resume_acceleration must be a number >= 0 m/s^2 (0 = back to the "
                         f"nominal speed at once), got {value!r}")
    return number


class FallbackSwitch(LeafSystem):
    """Hands control to the fallback while the anomaly detector flags the image.

    .. pydrake_system::

        name: FallbackSwitch
        input_ports:
        - steering_angle
        - anomaly
        - fallback_steering_angle (optional)
        output_ports:
        - steering_angle
        - speed

    ``speed`` (m/s) is discrete state, updated once per ``period`` s from ``anomaly``
    (1 = flagged) by `next_speed`. Steering passes the nominal (TaxiNet) steering
    through while the image is clear. While it is flagged, ``steering="dead_reckoning"``
    or ``"oracle"`` steer with ``fallback_steering_angle`` instead: the diagram feeds it
    the P-controller on the `DeadReckoning` estimate (honest: the last trusted
    estimate carried forward with the known steering and speed) or on the *true* state
    (privileged information, for comparison only).
    """

    def __init__(self, *, nominal_speed, strategy="slow_down", steering="taxinet", period=0.05,
                 slow_down_step=0.01, brake_deceleration=1.0, resume_acceleration=0.0):
        super().__init__()
        if strategy not in STRATEGIES:
            raise ValueError(f"FallbackSwitch: strategy must be one of {STRATEGIES}, got "
                             f"'{strategy}'")
        if steering not in STEERING:
            raise ValueError(f"FallbackSwitch: steering must be one of {STEERING}, got "
                             f"'{steering}'")
        if not period > 0:
            raise ValueError(f"FallbackSwitch: period must be > 0 s, got {period}")
        self._params = dict(strategy=strategy, nominal=float(nominal_speed),
                            slow_down_step=float(slow_down_step),
                            brake_deceleration=float(brake_deceleration),
                            resume_acceleration=check_resume_acceleration(resume_acceleration),
                            period=float(period))
        self._steering_mode = steering
        self._steering_in = self.DeclareVectorInputPort("steering_angle", 1)
        self._anomaly_in = self.DeclareVectorInputPort("anomaly", 1)
        self._fallback_in = self.DeclareVectorInputPort("fallback_steering_angle", 1)
        self._speed_index = self.DeclareDiscreteState(BasicVector([float(nominal_speed)]))
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update_speed)
        self._steering_out = self.DeclareVectorOutputPort("steering_angle", 1,
                                                          self._calc_steering)
        self._speed_out = self.DeclareStateOutputPort("speed", self._speed_index)

    @property
    def strategy(self):
        return self._params["strategy"]

    def get_steering_angle_input_port(self):
        return self._steering_in

    def get_anomaly_input_port(self):
        return self._anomaly_in

    def get_fallback_steering_angle_input_port(self):
        return self._fallback_in

    def get_steering_angle_output_port(self):
        return self._steering_out

    def get_speed_output_port(self):
        return self._speed_out

    def _flagged(self, context):
        return self._anomaly_in.Eval(context)[0] >= 0.5

    def _update_speed(self, context, discrete_state):
        speed = context.get_discrete_state(self._speed_index).GetAtIndex(0)
        discrete_state.get_mutable_vector(self._speed_index).SetAtIndex(
            0, float(next_speed(speed, self._flagged(context), **self._params)))

    def _calc_steering(self, context, output):
        if self._steering_mode != "taxinet" and self._flagged(context):
            if not self._fallback_in.HasValue(context):
                raise ValueError(f"FallbackSwitch: steering='{self._steering_mode}' needs the "
                                 f"'fallback_steering_angle' input connected")
            output.SetFromVector(self._fallback_in.Eval(context))
        else:
            output.SetFromVector(self._steering_in.Eval(context))
