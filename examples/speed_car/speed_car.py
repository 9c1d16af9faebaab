"""Example (b): another plant with a camera, through sweep, BRT, labels and detector;
`make_car_loop` puts the detector and its fallback switch in the loop when
``CarConfig.monitor`` names one (the script stops at the trained detector).

A car whose speed is a fourth state: it follows the commanded speed with a
first-order lag, so the guard's slow-down acts through the dynamics, not at once.

State ``[px m, py m, theta rad, v m/s]``: px' = v sin(theta), py' = v cos(theta),
theta' = (v / L) tan(steering), v' = (command - v) / tau. It drives on a catalog runway
under the wing camera, steered by TaxiNet (any controller of the interface would do).

    python examples/speed_car/speed_car.py --out out/speed_car
"""

import argparse
import dataclasses as dc
import functools
from pathlib import Path

import numpy as np
import torch
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold

from reachwatch.diagrams import (ControllerConfig, MonitorConfig, add_monitor, add_world,
                                 export_loop_ports, make_controller, render_at_states)
from reachwatch.reach import Dynamics, Grid, InlineExecutor, Probe, solve_brt, sweep
from reachwatch.systems import DetectorConfig, Environment, resize_for_detector
from reachwatch.training.dataset import LabelledData
from reachwatch.training.detector_train import DetectorTrainConfig, train_detector


class LagCar(LeafSystem):
    """Inputs ``steering_angle`` (rad), ``speed_command`` (m/s); outputs ``state``
    ``[px, py, theta, v]`` and ``pose`` ``[px, py, theta]`` (what the camera follows)."""

    def __init__(self, *, wheelbase=5.0, time_constant=1.0):
        super().__init__()
        self._L, self._tau = wheelbase, time_constant
        self.DeclareContinuousState(4)
        self._steering = self.DeclareVectorInputPort("steering_angle", 1)
        self._command = self.DeclareVectorInputPort("speed_command", 1)
        self.DeclareVectorOutputPort("state", 4, lambda c, o: o.SetFromVector(self._x(c)))
        self.DeclareVectorOutputPort("pose", 3, lambda c, o: o.SetFromVector(self._x(c)[:3]))

    @staticmethod
    def _x(context):
        return context.get_continuous_state_vector().CopyToVector()

    def DoCalcTimeDerivatives(self, context, derivatives):
        px, py, theta, v = self._x(context)
        phi, command = self._steering.Eval(context)[0], self._command.Eval(context)[0]
        if not abs(phi) < np.pi / 2:              # tan turns the other way past it
            raise ValueError(f"LagCar: steering_angle {phi:g} rad at t = "
                             f"{context.get_time():.3f} s is not within +-pi/2 rad")
        derivatives.get_mutable_vector().SetFromVector([
            v * np.sin(theta), v * np.cos(theta), v / self._L * np.tan(phi),
            (command - v) / self._tau])


class LagCarDynamics(Dynamics):
    """The same car for the solver: the swept steering, the nominal speed command
    ``speed``; ``vector_field(..., speed=)`` takes another command per state (what a
    fallback that slows down or brakes sets), which the car's speed lags."""
    state_dim, control_dim = 4, 1

    def __init__(self, *, half_width, speed, wheelbase=5.0, time_constant=1.0):
        self.half_width, self.speed = half_width, speed
        self.wheelbase, self.time_constant = wheelbase, time_constant

    def vector_field(self, x, u, speed=None):
        theta, v = x[..., 2], x[..., 3]
        command = self.speed if speed is None else speed
        return torch.stack([v * torch.sin(theta), v * torch.cos(theta),
                            v / self.wheelbase * torch.tan(u[..., 0]),
                            (command - v) / self.time_constant], dim=-1)

    def control_limits(self):
        """The steering within +-pi/2 rad, where tan turns back."""
        return [-np.pi / 2], [np.pi / 2]

    def target(self, x):
        return self.half_width - x[..., 0].abs()

    def safe_box(self):
        inf = float("inf")
        return [-self.half_width, -inf, -inf, -inf], [self.half_width, inf, inf, inf]


@dc.dataclass
class CarConfig:
    environment: Environment = dc.field(default_factory=Environment)
    controller: ControllerConfig = dc.field(default_factory=ControllerConfig)
    time_constant: float = 1.0
    monitor: MonitorConfig = dc.field(default_factory=MonitorConfig)   # a detector: guarded


def make_car_loop(config: CarConfig):
    """The car, the runway world and its camera, the controller, a steering hold; with a
    detector in ``config.monitor``, the AnomalyDetector and FallbackSwitch command the speed.
    Exports ``state`` (and ``speed``, ``anomaly`` when guarded)."""
    builder = DiagramBuilder()
    car = builder.AddNamedSystem("car", LagCar(time_constant=config.time_constant))
    world = add_world(builder, environment=config.environment, pose_port=car.GetOutputPort("pose"))
    controller = builder.AddNamedSystem("controller", make_controller(config.controller))
    builder.Connect(world.camera.color_image_output_port(), controller.GetInputPort("color_image"))
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(config.controller.period, 1))
    builder.Connect(hold.get_output_port(), car.GetInputPort("steering_angle"))
    extra = {}
    if config.monitor.detector:
        monitor = add_monitor(builder, image_port=world.camera.color_image_output_port(),
                              steering_port=controller.GetOutputPort("steering_angle"),
                              estimate_port=(controller.GetOutputPort("estimate")
                                             if controller.HasOutputPort("estimate") else None),
                              monitor=config.monitor, controller=config.controller)
        builder.Connect(monitor.switch.get_steering_angle_output_port(), hold.get_input_port())
        builder.Connect(monitor.switch.get_speed_output_port(), car.GetInputPort("speed_command"))
        extra = {"speed": monitor.switch.get_speed_output_port(), "anomaly": monitor.anomaly}
    else:
        speed = builder.AddNamedSystem("speed", ConstantVectorSource([config.controller.speed]))
        builder.Connect(controller.GetOutputPort("steering_angle"), hold.get_input_port())
        builder.Connect(speed.get_output_port(), car.GetInputPort("speed_command"))
    export_loop_ports(builder, state=car.GetOutputPort("state"), **extra)
    return builder.Build()


PROBE = Probe(plant="car", control_port="controller.steering_angle")


def car_grid(half_width, shape):
    """px across the runway, py 100-250 m, theta +-28 deg, v 0-6 m/s."""
    return Grid(lo=[-half_width, 100.0, -np.deg2rad(28), 0.0],
                hi=[half_width, 250.0, np.deg2rad(28), 6.0], shape=shape,
                names=("px", "py", "theta", "v"))


def study(config: CarConfig, out, *, shape=(9, 5, 9, 4), horizon=8.0, samples=400,
          detector=DetectorTrainConfig(), executor=None, progress=True):
    """Sweep, BRT, labelled images, a trained detector. Returns what each step made."""
    out = Path(out)
    B = config.environment.half_width
    grid = car_grid(B, shape)
    table = sweep(functools.partial(make_car_loop, config), grid, probe=PROBE,
                  cache_dir=out / "sweeps", executor=executor, progress=progress)
    dynamics = LagCarDynamics(half_width=B, speed=config.controller.speed,
                              time_constant=config.time_constant)
    value = solve_brt(grid, dynamics, table[PROBE.control_port], horizon=horizon,
                      period=config.controller.period)
    rng = np.random.default_rng(0)
    states = grid.lo + rng.uniform(size=(samples, 4)) * (grid.hi - grid.lo)
    frames = render_at_states(make_car_loop(config), plant="car",
                              image_port="wing_camera.color_image", states=states)
    data = LabelledData.from_arrays(
        images=resize_for_detector(frames, detector.detector), states=states,
        values=value.at(states), environment=config.environment.name,
        camera_size=frames.shape[1:3])
    trained = train_detector([data], detector, out / "detector.pt")
    return grid, table, value, data, trained


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    config = CarConfig(environment=Environment("KSFO", 21.0, "overcast"))
    detector = DetectorTrainConfig(detector=DetectorConfig(height=48, width=80), epochs=4)
    grid, _, value, data, trained = study(config, args.out, detector=detector,
                                          executor=InlineExecutor())
    print(f"BRT: {100 * value.brt_fraction:.1f} % of the {'x'.join(map(str, grid.shape))} grid; "
          f"{int(data.labels.sum())} of {len(data.labels)} images labelled anomalous; "
          f"detector threshold {trained['threshold']:.3g}, checkpoint {Path(args.out) / 'detector.pt'}")


if __name__ == "__main__":
    main()
