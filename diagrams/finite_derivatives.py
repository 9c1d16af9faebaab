"""A loop's Python plants refuse a state derivative that is not finite, in one line.

Drake's error-controlled integrators step for ever on a NaN state derivative
(RobotLocomotion/drake#12647): a run hangs at the time it turned NaN, with no word of
where. `start_simulator` calls `check_finite_derivatives` on every loop it runs, so a
derivative that turns NaN or inf between control ticks (a division by zero, a root of
a negative number, at a state or an input the plant was not written for) stops the run
at the integrator's trial step with a ValueError naming the loop, the system, the time
and the state. A plant written in C++ (a pydrake class, such as ``MultibodyPlant``) is
not seen: its derivative is computed where Python cannot look."""

import inspect
import math
import weakref

import numpy as np
from pydrake.systems.framework import Diagram, LeafSystem, PortDataType

#: The systems `check_finite_derivatives` has wrapped (each once).
_CHECKED = weakref.WeakSet()


def leaf_systems(diagram: Diagram) -> list:
    """The leaf systems of ``diagram``, its sub-diagrams' included."""
    found = []
    for system in diagram.GetSystems():
        found += leaf_systems(system) if isinstance(system, Diagram) else [system]
    return found


def check_finite_derivatives(diagram: Diagram) -> int:
    """Makes each leaf system of ``diagram`` with continuous state whose
    ``DoCalcTimeDerivatives`` is written in Python check what it computes, once per
    system, and returns how many are checked. The check reads the derivative after the
    system's own method (its class's, looked up at each call) and raises a ValueError
    in one line when it is not finite. It holds its system weakly (a callback holding it
    strongly would keep the whole diagram alive, `reachwatch.systems.ports.weak_callback`)."""
    loop = diagram.get_name()
    checked = 0
    for system in leaf_systems(diagram):
        if not system.num_continuous_states():
            continue
        if not inspect.isfunction(getattr(type(system), "DoCalcTimeDerivatives", None)):
            continue                # a C++ system's own: not seen
        checked += 1
        if system not in _CHECKED:
            system.DoCalcTimeDerivatives = _checked_derivatives(system, loop)
            _CHECKED.add(system)
    return checked


def _checked_derivatives(system: LeafSystem, loop: str):
    ref = weakref.ref(system)

    def calc(context, derivatives):
        me = ref()
        type(me).DoCalcTimeDerivatives(me, context, derivatives)
        values = derivatives.CopyToVector()
        # the sum first: a tenth of the cost of a tick of the cheapest loop (a plant on
        # its true state) was the check; it is finite when every value is, and when it
        # is not (an overflow of finite values too) every value is looked at
        if not math.isfinite(values.sum()) and not np.all(np.isfinite(values)):
            raise ValueError(not_finite_message(me, loop, context, values))
    return calc


def not_finite_message(system, loop: str, context, values) -> str:
    """The one line `check_finite_derivatives` raises: where, and the input that is not
    finite when one is (the controller's command), else what the plant should do."""
    name = f" '{loop}'" if loop else ""
    state = context.get_continuous_state_vector().CopyToVector()
    head = (f"the loop{name}: its system '{system.get_name()}' gave the state derivative "
            f"{_numbers(values)} at t = {context.get_time():.3f} s (state {_numbers(state)}), "
            f"not finite")
    for i in range(system.num_input_ports()):
        port = system.get_input_port(i)
        if port.get_data_type() != PortDataType.kVectorValued or not port.HasValue(context):
            continue
        value = np.asarray(port.Eval(context), float)
        if not np.all(np.isfinite(value)):
            return (f"{head}: its input '{port.get_name()}' is {_numbers(value)}: does the "
                    f"controller output NaN or inf there?")
    return (f"{head}, from finite inputs: Drake's integrator would step for ever on it; "
            f"raise a ValueError of the plant's own in its DoCalcTimeDerivatives where its "
            f"state or inputs leave what it can integrate")


def _numbers(values) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in np.ravel(values)) + "]"
