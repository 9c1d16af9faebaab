"""A loop whose state derivative is not finite is stopped in one line, not stepped for
ever.

Drake's error-controlled integrators throw a trial step whose derivative is NaN away
and try a shorter one; where every step from the current time meets a NaN one (a plant
whose derivative turns NaN just past the state it is at), they try for ever
(RobotLocomotion/drake#12647): a run hangs, with no word of where.
`check_finite_derivatives` (which `start_simulator` calls on every loop it runs) makes
each system written in Python count the non-finite derivatives it gives, and refuse in
one line once `STUCK_EVALUATIONS` of them came without the integrator accepting a step
to a later time (`DerivativeChecks.stepped`, which the simulator's monitor calls after
each step: stuck, Drake takes steps of no length). A run the integrator gets through,
a NaN trial step thrown away now and then, is unchanged.
A system written in C++ (a pydrake class, such as ``MultibodyPlant``) is not seen
between control ticks: its derivative is computed where Python cannot look.
`non_finite_message` says which system's derivative is not finite at a time the caller
evaluates it (the control ticks: `LoopRun`)."""

import math
import weakref

import numpy as np
from pydrake.systems.framework import Diagram, PortDataType

#: Non-finite derivatives one system may give without the integrator getting past the
#: time of its last step before the run is refused: a step Drake throws away for a NaN
#: is tried again a few times shorter (2 in a row at most in a stiff plant that
#: recovered); a stuck one, for ever (hundreds a millisecond).
STUCK_EVALUATIONS = 200

_NAME = "DoCalcTimeDerivatives"


def leaf_systems(diagram: Diagram) -> list:
    """The leaf systems of ``diagram``, its sub-diagrams' included."""
    found = []
    for system in diagram.GetSystems():
        found += leaf_systems(system) if isinstance(system, Diagram) else [system]
    return found


class _Count:
    """One checked system's non-finite derivatives since the integrator's last step."""
    __slots__ = ("bad", "since", "state")

    def __init__(self):
        self.bad, self.since, self.state = 0, -math.inf, None


#: The checked systems, each with its `_Count` (wrapped once, held weakly).
_COUNTS = weakref.WeakKeyDictionary()


class DerivativeChecks:
    """A loop's checked systems and their counts (`check_finite_derivatives`)."""

    def __init__(self, checked):
        self._checked = list(checked)       # (system, its _Count)

    def __len__(self):
        return len(self._checked)

    def start(self):
        """A run starts: nothing counted yet."""
        for _, count in self._checked:
            count.bad, count.since, count.state = 0, -math.inf, None

    def stepped(self, root_context):
        """The simulator took a step, to ``root_context``'s time. One that got past the
        time of the last (a step of no length does not: stuck, Drake takes those,
        thousands a second) makes the non-finite derivatives before it trial steps it
        threw away; the state a step of no length stays at, after one, is the one a
        refusal names (copied then alone, not at every step)."""
        time = root_context.get_time()
        for system, count in self._checked:
            if time > count.since:
                count.bad, count.since, count.state = 0, time, None
            elif count.bad and count.state is None:     # a step of no length: stuck here
                count.state = system.GetMyContextFromRoot(
                    root_context).get_continuous_state_vector().CopyToVector()


def check_finite_derivatives(diagram: Diagram) -> DerivativeChecks:
    """Makes each leaf system of ``diagram`` with continuous state whose
    ``DoCalcTimeDerivatives`` is written in Python count the non-finite derivatives
    it computes (once per system: the method its class has at each call, then the
    check) and raise a ValueError in one line at the `STUCK_EVALUATIONS`-th since a
    step got past the time of the one before (`DerivativeChecks`). Holds each system
    weakly (a callback holding it strongly would keep the whole diagram alive,
    `reachwatch.systems.ports.weak_callback`)."""
    loop = diagram.get_name()
    counts = []
    for system in leaf_systems(diagram):
        if not system.num_continuous_states() or not callable(
                getattr(type(system), _NAME, None)):
            continue                # none, or a C++ system's own: not seen
        count = _COUNTS.get(system)
        if count is None:
            count = _COUNTS[system] = _Count()
            setattr(system, _NAME, _checked_derivatives(system, loop, count))
        counts.append((system, count))
    return DerivativeChecks(counts)


def _checked_derivatives(system, loop: str, count: _Count):
    ref = weakref.ref(system)

    def calc(context, derivatives):
        me = ref()
        getattr(type(me), _NAME)(me, context, derivatives)
        values = derivatives.CopyToVector()
        # the sum first (a tenth of a tick of the cheapest loop, a plant on its true
        # state, was the check): finite when every value is; when it is not (finite
        # values overflowing too) every value is looked at
        if math.isfinite(values.sum()) or np.all(np.isfinite(values)):
            return
        count.bad += 1
        if count.bad >= STUCK_EVALUATIONS:
            count.bad = 0
            raise ValueError(not_finite_message(
                me, loop, context, values, state=count.state,
                where=f"at every trial step of the integrator from t = {count.since:.4f} s"))
    return calc


def non_finite_message(diagram: Diagram, root_context):
    """The one-line message of the first leaf system of ``diagram`` whose state
    derivative is not finite in ``root_context`` (any system with continuous state,
    C++ ones too), or None when all are."""
    for system in leaf_systems(diagram):
        if not system.num_continuous_states():
            continue
        context = system.GetMyContextFromRoot(root_context)
        values = system.EvalTimeDerivatives(context).CopyToVector()
        if not np.all(np.isfinite(values)):
            return not_finite_message(system, diagram.get_name(), context, values,
                                      where=f"at t = {context.get_time():.3f} s")
    return None


def not_finite_message(system, loop: str, context, values, *, where: str,
                       state=None) -> str:
    """What is not finite, where: the system's state derivative ``values`` in
    ``context`` ``where`` says, at ``state`` (default: the context's), and the input
    that is not finite when one is (the controller's command), else what the plant
    should do."""
    name = f" '{loop}'" if loop else ""
    if state is None:
        state = context.get_continuous_state_vector().CopyToVector()
    head = (f"the loop{name}: its system '{system.get_name()}' gives the state derivative "
            f"{_numbers(values)} {where} (state {_numbers(state)}), not finite")
    for i in range(system.num_input_ports()):
        port = system.get_input_port(i)
        if port.get_data_type() != PortDataType.kVectorValued or not port.HasValue(context):
            continue
        value = np.asarray(port.Eval(context), float)
        if not np.all(np.isfinite(value)):
            return (f"{head}: its input '{port.get_name()}' is {_numbers(value)}: does the "
                    f"controller output NaN or inf there?")
    return (f"{head}, from finite inputs: raise a ValueError of the plant's own in its "
            f"DoCalcTimeDerivatives where its state or inputs leave what it can integrate")


def _numbers(values) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in np.ravel(values)) + "]"
