import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from reachwatch.systems import TaxiPlant, taxi_dynamics


def _derivatives(plant, state, phi, v):
    context = plant.CreateDefaultContext()
    context.SetContinuousState(state)
    plant.get_steering_angle_input_port().FixValue(context, [phi])
    plant.get_speed_input_port().FixValue(context, [v])
    return plant.EvalTimeDerivatives(context).CopyToVector()


@pytest.mark.parametrize("state, phi, v", [
    ([0.0, 100.0, 0.0], 0.0, 5.0),
    ([3.0, 120.0, 0.3], -0.2, 5.0),
    ([-7.5, 200.0, -0.45], 0.35, 2.5),
])
def test_derivatives_match_formula(state, phi, v):
    plant = TaxiPlant()
    px, py, theta = state
    expected = [v * np.sin(theta), v * np.cos(theta), v / 5.0 * np.tan(phi)]
    np.testing.assert_allclose(_derivatives(plant, state, phi, v), expected, atol=1e-12)
    np.testing.assert_allclose(taxi_dynamics(state, phi, v), expected, atol=1e-12)


def test_at_nominal_speed_heading_rate_is_tan_phi():
    # at v = 5 m/s and L = 5 m, theta' = tan(phi), the paper's u.
    d = _derivatives(TaxiPlant(), [0.0, 0.0, 0.0], 0.3, 5.0)
    assert d[2] == pytest.approx(np.tan(0.3))


def test_ports_are_named():
    plant = TaxiPlant()
    assert plant.get_input_port(0).get_name() == "steering_angle"
    assert plant.get_input_port(1).get_name() == "speed"
    assert plant.get_output_port(0).get_name() == "state"
    assert plant.GetInputPort("speed") is not None


@pytest.mark.parametrize("port", ["steering_angle", "speed"])
def test_non_finite_input_names_the_port(port):
    plant = TaxiPlant()
    context = plant.CreateDefaultContext()
    plant.get_steering_angle_input_port().FixValue(context, [0.0])
    plant.get_speed_input_port().FixValue(context, [5.0])
    plant.GetInputPort(port).FixValue(context, [np.nan])
    with pytest.raises(ValueError, match=port):
        plant.EvalTimeDerivatives(context)


@pytest.mark.parametrize("steering", [np.pi / 2, -2.0, 10.0, 1e6])
def test_a_steering_angle_past_a_quarter_turn_is_refused(steering):
    """tan(phi) past +-pi/2 turns the aircraft the other way (1e6 rad, "left", turned it
    right): such a command is a controller's mistake (degrees, most often), named, not
    simulated."""
    plant = TaxiPlant()
    context = plant.CreateDefaultContext()
    plant.get_steering_angle_input_port().FixValue(context, [steering])
    plant.get_speed_input_port().FixValue(context, [5.0])
    with pytest.raises(ValueError, match=r"'steering_angle' is .* rad at t = 0.000 s; a "
                                         r"wheel angle lies within \+-pi/2 rad"):
        plant.EvalTimeDerivatives(context)
    plant.get_steering_angle_input_port().FixValue(context, [np.pi / 2 - 1e-3])
    assert plant.EvalTimeDerivatives(context).CopyToVector()[2] > 0


def test_bad_wheelbase_rejected():
    with pytest.raises(ValueError, match="wheelbase"):
        TaxiPlant(wheelbase=0.0)


def test_simulated_straight_line_and_constant_turn():
    builder = DiagramBuilder()
    plant = builder.AddSystem(TaxiPlant(initial_state=[1.0, 100.0, 0.2]))
    steer = builder.AddSystem(ConstantVectorSource([0.0]))
    speed = builder.AddSystem(ConstantVectorSource([5.0]))
    builder.Connect(steer.get_output_port(), plant.get_steering_angle_input_port())
    builder.Connect(speed.get_output_port(), plant.get_speed_input_port())
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(2.0)
    x = plant.GetMyContextFromRoot(simulator.get_context()).get_continuous_state_vector()
    np.testing.assert_allclose(x.CopyToVector(),
                               [1.0 + 10 * np.sin(0.2), 100.0 + 10 * np.cos(0.2), 0.2],
                               atol=1e-6)
