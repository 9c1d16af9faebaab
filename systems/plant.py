"""The taxiing aircraft as a kinematic bicycle (the paper's Eq. 1)."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

#: Wheelbase L (m) of the authors' model: theta' = (v / L) tan(phi).
WHEELBASE_M = 5.0
#: Nominal taxi speed (m/s).
NOMINAL_SPEED_MPS = 5.0
#: The steering angle's bound (rad, open): ``tan(phi)`` turns the other way past it.
MAX_STEERING_RAD = np.pi / 2


def taxi_dynamics(state, steering_angle, speed, wheelbase=WHEELBASE_M):
    """Time derivative of ``state = [px m, py m, theta rad]`` (numpy, broadcasts).

    ``px' = v sin(theta)``, ``py' = v cos(theta)``, ``theta' = (v / L) tan(phi)``
    with ``phi = steering_angle`` (rad) and ``v = speed`` (m/s).
    """
    state = np.asarray(state, dtype=float)
    theta = state[..., 2]
    return np.stack([
        speed * np.sin(theta),
        speed * np.cos(theta),
        speed / wheelbase * np.tan(steering_angle),
    ], axis=-1)


class TaxiPlant(LeafSystem):
    """Crosstrack / downtrack / heading kinematics of a taxiing aircraft.

    .. pydrake_system::

        name: TaxiPlant
        input_ports:
        - steering_angle
        - speed
        output_ports:
        - state

    State ``[px, py, theta]``: crosstrack error px (m, positive left of the
    centreline), downtrack position py (m), heading error theta (rad, positive
    turns towards +px). ``steering_angle`` is in rad, within +-pi/2
    (`MAX_STEERING_RAD`; a ValueError past it), ``speed`` in m/s.
    """

    def __init__(self, *, wheelbase=WHEELBASE_M, initial_state=(0.0, 0.0, 0.0)):
        super().__init__()
        if not wheelbase > 0:
            raise ValueError(f"TaxiPlant: wheelbase must be > 0 m, got {wheelbase}")
        self._wheelbase = float(wheelbase)
        state_index = self.DeclareContinuousState(
            BasicVector(np.asarray(initial_state, dtype=float)), 0, 0, 3)
        self._steering_port = self.DeclareVectorInputPort("steering_angle", 1)
        self._speed_port = self.DeclareVectorInputPort("speed", 1)
        self._state_port = self.DeclareStateOutputPort("state", state_index)

    @property
    def wheelbase(self):
        """Wheelbase L (m)."""
        return self._wheelbase

    def get_steering_angle_input_port(self):
        return self._steering_port

    def get_speed_input_port(self):
        return self._speed_port

    def get_state_output_port(self):
        return self._state_port

    def _read_input(self, port, context):
        value = float(port.Eval(context)[0])
        if not np.isfinite(value):
            raise ValueError(
                f"TaxiPlant: input port '{port.get_name()}' is {value} at "
                f"t = {context.get_time():.3f} s; it must be finite")
        return value

    def DoCalcTimeDerivatives(self, context, derivatives):
        steering = self._read_input(self._steering_port, context)
        if not abs(steering) < MAX_STEERING_RAD:
            raise ValueError(
                f"TaxiPlant: input port 'steering_angle' is {steering:g} rad at "
                f"t = {context.get_time():.3f} s; a wheel angle lies within +-pi/2 rad "
                f"(tan turns the aircraft the other way past it): is it in degrees?")
        speed = self._read_input(self._speed_port, context)
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector(
            taxi_dynamics(x, steering, speed, self._wheelbase))
