"""The fallback switch: when the detector flags the image, trade speed for safety.

A fallback is defined once, by `Fallback`: its speed strategy, its steering while
flagged and their parameters, read from a name such as ``"slow_down+dead_reckoning"``
by `Fallback.parse`. Its two rules work on arrays: `Fallback.next_speed` (the speed of
the next tick) and `Fallback.steering_angle` (whose steering is applied). The Drake
`FallbackSwitch` and the table rollouts of the guarded loop both call them, so the two
cannot drift apart.

The speed strategies are `SpeedStrategy` entries of the registry `STRATEGY_REGISTRY`
(``slow_down`` and ``brake`` here): a new one is a module that registers its rule, and
`Fallback`, the switch, the table rollouts, run files and ``--fallbacks`` take its name."""

import dataclasses as dc
from typing import Callable, Optional, Tuple

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from .registry import Registry


@dc.dataclass(frozen=True)
class SpeedStrategy:
    """A fallback's speed rule while flagged, registered by ``name`` in
    `STRATEGY_REGISTRY`. ``flagged(speed, fallback, period)``: the speed (m/s, arrays) of
    the next tick while the image is flagged, from this tick's ``speed``, the `Fallback`
    (its fields are the rule's parameters) and the control ``period`` (s); `Fallback`
    stops it at 0, and the rule once the image is clear is the same for every strategy
    (`Fallback.next_speed`). ``params``: the `Fallback` fields the rule reads (each
    checked by `Fallback`); ``check(fallback)``: a further check of them for this
    strategy (raise a one-line ValueError), or None; ``text``: what it does, in a
    sentence, for help and reports. The name is all that cache keys and run files hold
    of a strategy: give a changed rule a new name."""
    name: str
    flagged: Callable
    text: str = ""
    params: Tuple[str, ...] = ()
    check: Optional[Callable] = None

    def describe(self) -> str:
        """``name``, its text and the `Fallback` fields it reads, in one line."""
        reads = f" (reads {', '.join(self.params)})" if self.params else ""
        return f"{self.name}: {self.text}{reads}"


#: The registered speed strategies (`SpeedStrategy`), by name.
STRATEGY_REGISTRY = Registry("speed strategy")
STRATEGY_REGISTRY.register(SpeedStrategy(
    "slow_down", lambda speed, fallback, period: speed - fallback.slow_down_step,
    "the paper's rule: -slow_down_step m/s per tick", ("slow_down_step",)))
STRATEGY_REGISTRY.register(SpeedStrategy(
    "brake", lambda speed, fallback, period: speed - fallback.brake_deceleration * period,
    "-brake_deceleration m/s^2", ("brake_deceleration",)))
#: The registered speed strategies' names (a live view: it prints and compares like the
#: tuple of them, ``('slow_down', 'brake')`` until another is registered).
STRATEGIES = STRATEGY_REGISTRY.names
#: Steering while flagged: the controller's own (``controller``: the flag only changes
#: the speed), the P-controller on the dead-reckoned estimate (honest), or on the true
#: state (privileged, a reference only).
STEERING = ("controller", "dead_reckoning", "oracle")
#: Older names of the steering modes, still read (run files and ``--fallbacks`` written
#: when the taxi's TaxiNet was the only controller).
STEERING_ALIASES = {"taxinet": "controller"}


#: The fallbacks compared by default: the paper's slow-down, braking, dead reckoning
#: with slow-down (honest), and slow-down with the true state's steering (privileged:
#: the paper's reference point, never an honest result).
DEFAULT_FALLBACKS = ("slow_down", "brake", "slow_down+dead_reckoning", "slow_down+oracle")


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


def _positive(name, value, unit) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (np.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be a number > 0 {unit}, got {value!r}")
    return number


@dc.dataclass(frozen=True)
class Fallback:
    """What the guarded loop does while the detector flags the image.

    ``strategy``: ``slow_down`` (the paper: -``slow_down_step`` m/s per tick),
    ``brake`` (-``brake_deceleration`` m/s^2) or another `SpeedStrategy` registered in
    `STRATEGY_REGISTRY`, all stopping at 0; once the image is clear the speed returns
    to nominal at once (``resume_acceleration`` = 0, the paper's rule) or climbs back
    at ``resume_acceleration`` m/s^2. ``steering``:
    ``controller`` (the controller keeps steering), ``dead_reckoning`` or ``oracle``
    (the loop's fallback steering takes over while flagged; see `FallbackSwitch`).
    ``taxinet`` is read as ``controller``. Invalid fields raise one ValueError naming
    the field."""
    strategy: str = "slow_down"
    steering: str = "controller"
    slow_down_step: float = 0.01
    brake_deceleration: float = 1.0
    resume_acceleration: float = 0.0

    def __post_init__(self):
        steering = STEERING_ALIASES.get(self.steering, self.steering)
        if self.strategy not in STRATEGY_REGISTRY:
            raise ValueError(f"strategy must be one of {STRATEGIES}, got '{self.strategy}'")
        if steering not in STEERING:
            raise ValueError(f"steering must be one of {STEERING}, got '{self.steering}'")
        set_ = lambda name, value: object.__setattr__(self, name, value)   # noqa: E731
        set_("steering", steering)
        set_("slow_down_step", _positive("slow_down_step", self.slow_down_step, "m/s"))
        set_("brake_deceleration",
             _positive("brake_deceleration", self.brake_deceleration, "m/s^2"))
        set_("resume_acceleration", check_resume_acceleration(self.resume_acceleration))
        check = STRATEGY_REGISTRY.get(self.strategy).check
        if check is not None:
            check(self)

    @classmethod
    def parse(cls, name, **params) -> "Fallback":
        """The fallback named ``name``: a speed strategy alone (``"slow_down"``, the
        controller keeps steering) or ``"strategy+steering"`` (e.g.
        ``"slow_down+dead_reckoning"``, ``"slow_down+oracle"``); ``params`` set the
        other fields. A `Fallback` is returned as it is (with ``params`` replaced)."""
        if isinstance(name, Fallback):
            return dc.replace(name, **params)
        strategy, plus, steering = str(name).partition("+")
        steering = steering if plus else "controller"
        if strategy not in STRATEGY_REGISTRY or \
                STEERING_ALIASES.get(steering, steering) not in STEERING:    # the name alone
            raise ValueError(f"fallback '{name}': write a speed strategy {STRATEGIES}, "
                             f"optionally followed by '+' and a steering {STEERING[1:]} (e.g. "
                             f"'slow_down+dead_reckoning')")
        return cls(strategy, steering, **params)

    @property
    def name(self) -> str:
        """The name `parse` reads back (the speed strategy alone when the controller
        keeps steering)."""
        return (self.strategy if self.steering == "controller"
                else f"{self.strategy}+{self.steering}")

    @property
    def takes_over_steering(self) -> bool:
        """Whether a steering other than the controller's is applied while flagged."""
        return self.steering != "controller"

    @property
    def speed_strategy(self) -> SpeedStrategy:
        """The registered `SpeedStrategy` named ``strategy``."""
        return STRATEGY_REGISTRY.get(self.strategy)

    def next_speed(self, speed, flagged, *, nominal, period):
        """Speed (m/s) for the next tick of a loop ticking every ``period`` s at
        ``nominal`` m/s: while flagged, the speed strategy's rule, stopping at 0; when
        the image is clear, ``nominal`` at once (``resume_acceleration`` = 0, the
        paper's rule), or climbing back at ``resume_acceleration`` m/s^2: then one
        clear frame in a run of flagged ones costs the braking one tick's worth of speed
        instead of all of it. Works on arrays."""
        speed, flagged = np.asarray(speed, float), np.asarray(flagged, bool)
        slowed = self.speed_strategy.flagged(speed, self, period)
        resumed = (np.full_like(speed, nominal) if not self.resume_acceleration else
                   np.minimum(speed + self.resume_acceleration * period, nominal))
        return np.where(flagged, np.maximum(slowed, 0.0), resumed)

    def steering_angle(self, flagged, own, fallback=None):
        """The steering applied (rad): ``own`` (the controller's) where the image is
        clear or this fallback keeps the controller steering; ``fallback`` (its
        steering mode's angle) where flagged otherwise. ``fallback`` may be None only
        where nothing is flagged. Works on arrays."""
        flagged, own = np.asarray(flagged, bool), np.asarray(own, float)
        if not self.takes_over_steering:
            return own
        if fallback is None:
            if flagged.any():
                raise ValueError(f"steering '{self.steering}' needs the fallback's steering "
                                 f"while flagged")
            return own
        return np.where(flagged, np.asarray(fallback, float), own)


def fallback_parts(name: str):
    """``(strategy, steering)`` of a fallback's name (`Fallback.parse`)."""
    fallback = Fallback.parse(name)
    return fallback.strategy, fallback.steering


def fallback_name(strategy: str, steering: str = "controller") -> str:
    """The inverse of `fallback_parts` (`Fallback.name`)."""
    return Fallback(strategy, steering).name


def next_speed(speed, flagged, *, nominal, strategy="slow_down", slow_down_step=0.01,
               brake_deceleration=1.0, resume_acceleration=0.0, period=0.05):
    """Speed (m/s) for the next tick (`Fallback.next_speed` of the fallback with these
    fields). ``slow_down`` (the paper): -0.01 m/s per tick while flagged; ``brake``:
    -``brake_deceleration`` m/s^2 while flagged; any other registered strategy by its
    rule. All stop at 0. When the image is clear the speed returns to ``nominal`` (m/s,
    the loop's own speed) at once (``resume_acceleration`` = 0, the paper's rule), or
    climbs back at ``resume_acceleration`` m/s^2. Works on arrays."""
    return Fallback(strategy, slow_down_step=slow_down_step,
                    brake_deceleration=brake_deceleration,
                    resume_acceleration=resume_acceleration).next_speed(
        speed, flagged, nominal=nominal, period=period)


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

    ``fallback``: a `Fallback` or its name (default ``slow_down``), its fields given as
    keywords otherwise (``strategy=``, ``steering=``, ``brake_deceleration=`` ...);
    ``nominal_speed``: the loop's own speed (m/s), which the application gives. ``speed``
    (m/s) is discrete state, updated once per ``period`` s from ``anomaly`` (1 = flagged)
    by `Fallback.next_speed`. The steering output is `Fallback.steering_angle`: the
    controller's ``steering_angle`` passes through while the image is clear; while it is
    flagged, ``steering="dead_reckoning"`` or ``"oracle"`` steer with
    ``fallback_steering_angle`` instead: the diagram feeds it the P-controller on the
    `DeadReckoning` estimate (honest: the last trusted estimate carried forward with the
    known steering and speed) or on the *true* state (privileged information, for
    comparison only).
    """

    def __init__(self, *, fallback=None, nominal_speed, period=0.05, **fields):
        super().__init__()
        self._fallback = (Fallback(**fields) if fallback is None
                          else Fallback.parse(fallback, **fields))
        if not period > 0:
            raise ValueError(f"FallbackSwitch: period must be > 0 s, got {period}")
        self._nominal, self._period = float(nominal_speed), float(period)
        self._steering_in = self.DeclareVectorInputPort("steering_angle", 1)
        self._anomaly_in = self.DeclareVectorInputPort("anomaly", 1)
        self._fallback_in = self.DeclareVectorInputPort("fallback_steering_angle", 1)
        self._speed_index = self.DeclareDiscreteState(BasicVector([self._nominal]))
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update_speed)
        self._steering_out = self.DeclareVectorOutputPort("steering_angle", 1,
                                                          self._calc_steering)
        self._speed_out = self.DeclareStateOutputPort("speed", self._speed_index)

    @property
    def fallback(self) -> Fallback:
        return self._fallback

    @property
    def strategy(self):
        return self._fallback.strategy

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
        # the controller's steering first (the loop needs it this tick anyway): a monitor
        # whose frame work was begun in a process of its own at the render then works
        # beside the controller (`HistoryMonitor` ``encoder_process``)
        if self._steering_in.HasValue(context):
            self._steering_in.Eval(context)
        speed = context.get_discrete_state(self._speed_index).GetAtIndex(0)
        discrete_state.get_mutable_vector(self._speed_index).SetAtIndex(0, float(
            self._fallback.next_speed(speed, self._flagged(context), nominal=self._nominal,
                                      period=self._period)))

    def _calc_steering(self, context, output):
        steering = self._steering_in.Eval(context)     # before the flag, as `_update_speed`
        flagged = self._flagged(context)
        fallback = None
        if flagged and self._fallback.takes_over_steering:
            if not self._fallback_in.HasValue(context):
                raise ValueError(f"FallbackSwitch: steering='{self._fallback.steering}' needs "
                                 f"the 'fallback_steering_angle' input connected")
            fallback = self._fallback_in.Eval(context)
        output.SetFromVector(self._fallback.steering_angle(
            flagged, steering, fallback))
