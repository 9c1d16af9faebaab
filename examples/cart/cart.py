"""A cart on a track, seen by its own camera: the plant, the scene and a vision
controller of the cart application (application.py beside it).

State ``[y m, theta rad]``: the cart's offset across the track (positive: left of the
centreline) and its heading relative to the track (positive: turned left). It rolls
at the controller's speed ``v`` and steers like a bicycle of wheelbase ``L``:
y' = v sin(theta), theta' = (v / L) tan(steering). The track is two rails, red on the
left and blue on the right, ``HALF_WIDTH`` m either side of the centreline, on a grey
floor; the scene is the same all along the track, so the position along it is no
state. The cart fails where it reaches a rail (``|y| >= HALF_WIDTH``).

The camera is the run file's ``scenario.camera`` placed on the cart's body frame (x
forward, y left, z up), lit by the environment's hour and sky; the controller is
any of the interface (``color_image`` in, ``steering_angle`` out), here `RailFollower`.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (Box, GeometryInstance, MakeRenderEngineVtk, PerceptionProperties,
                              Rgba, SceneGraph)
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.diagrams import MonitorConfig, add_monitor, export_loop_ports, make_controller
from reachwatch.systems import (AircraftGeometry, lighting_for, make_wing_camera,
                                render_engine_params)

HALF_WIDTH = 0.5        # m from the centreline to each rail
WHEELBASE = 0.4         # m
RENDERER = "vtk"


class Cart(LeafSystem):
    """Inputs ``steering_angle`` (rad), ``speed`` (m/s); outputs ``state`` ``[y, theta]``
    and ``pose`` ``[y, 0, theta]`` (what the camera's frame follows)."""

    def __init__(self):
        super().__init__()
        self.DeclareContinuousState(2)
        self._steering = self.DeclareVectorInputPort("steering_angle", 1)
        self._speed = self.DeclareVectorInputPort("speed", 1)
        self.DeclareVectorOutputPort("state", 2, lambda c, o: o.SetFromVector(self._x(c)))
        self.DeclareVectorOutputPort("pose", 3, lambda c, o: o.SetFromVector(
            [self._x(c)[0], 0.0, self._x(c)[1]]))

    @staticmethod
    def _x(context):
        return context.get_continuous_state_vector().CopyToVector()

    def DoCalcTimeDerivatives(self, context, derivatives):
        y, theta = self._x(context)
        v, phi = self._speed.Eval(context)[0], self._steering.Eval(context)[0]
        if not abs(phi) < np.pi / 2:              # tan turns the other way past it
            raise ValueError(f"Cart: steering_angle {phi:g} rad at t = "
                             f"{context.get_time():.3f} s is not within +-pi/2 rad")
        derivatives.get_mutable_vector().SetFromVector(
            [v * np.sin(theta), v / WHEELBASE * np.tan(phi)])


def add_track(scene_graph):
    """The floor and the two rails, as anchored Drake boxes."""
    source = scene_graph.RegisterSource("track")
    for name, center, size, rgb in (
            ("floor", [50.0, 0.0, -0.01], [200.0, 40.0, 0.02], (0.45, 0.45, 0.42)),
            ("left_rail", [50.0, HALF_WIDTH, 0.03], [200.0, 0.06, 0.06], (0.85, 0.1, 0.1)),
            ("right_rail", [50.0, -HALF_WIDTH, 0.03], [200.0, 0.06, 0.06], (0.1, 0.2, 0.9))):
        instance = GeometryInstance(RigidTransform(center), Box(*size), name)
        properties = PerceptionProperties()
        properties.AddProperty("phong", "diffuse", Rgba(*rgb, 1.0))
        instance.set_perception_properties(properties)
        scene_graph.RegisterAnchoredGeometry(source, instance)


def add_cart_world(builder, *, environment, camera):
    """Adds the cart (named ``cart``), the track and the camera (``camera``) to
    ``builder``; returns ``(cart, camera)``, the cart's inputs unconnected."""
    cart = builder.AddNamedSystem("cart", Cart())
    scene_graph = builder.AddNamedSystem("scene_graph", SceneGraph())
    scene_graph.AddRenderer(RENDERER, MakeRenderEngineVtk(
        render_engine_params(lighting_for(environment))))
    add_track(scene_graph)
    # poses a frame at [px, py, theta] = the cart's [y, 0, theta] (it is not only the taxi's)
    body = builder.AddNamedSystem("cart_body", AircraftGeometry(scene_graph=scene_graph,
                                                                name="cart"))
    sensor = builder.AddNamedSystem("camera", make_wing_camera(
        frame_id=body.frame_id, config=camera, renderer_name=RENDERER))
    builder.Connect(cart.GetOutputPort("pose"), body.get_state_input_port())
    builder.Connect(body.get_geometry_pose_output_port(),
                    scene_graph.get_source_pose_port(body.source_id))
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    return cart, sensor


def make_cart_loop(scenario, monitor: MonitorConfig = None):
    """The cart, its camera, ``scenario.controller`` and a steering hold; with a
    ``monitor`` (a detector checkpoint), its detector and fallback switch command the
    speed. Exports ``state`` (and ``speed``, ``anomaly`` when guarded)."""
    builder = DiagramBuilder()
    cart, camera = add_cart_world(builder, environment=scenario.environment,
                                  camera=scenario.camera)
    controller = builder.AddNamedSystem("rail_follower", make_controller(scenario.controller))
    builder.Connect(camera.color_image_output_port(), controller.GetInputPort("color_image"))
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(scenario.controller.period, 1))
    builder.Connect(hold.get_output_port(), cart.GetInputPort("steering_angle"))
    steering, extra = controller.GetOutputPort("steering_angle"), {}
    if monitor is not None:
        guard = add_monitor(builder, image_port=camera.color_image_output_port(),
                            steering_port=steering, monitor=monitor,
                            controller=scenario.controller,
                            # a history monitor trained with signals reads the estimate
                            # too, where the controller has one, as the recordings did
                            estimate_port=(controller.GetOutputPort("estimate")
                                           if controller.HasOutputPort("estimate") else None))
        steering, speed = (guard.switch.get_steering_angle_output_port(),
                           guard.switch.get_speed_output_port())
        extra = {"speed": speed, "anomaly": guard.anomaly}
    else:
        speed = builder.AddNamedSystem(
            "speed", ConstantVectorSource([scenario.controller.speed])).get_output_port()
    builder.Connect(steering, hold.get_input_port())
    builder.Connect(speed, cart.GetInputPort("speed"))
    export_loop_ports(builder, state=cart.GetOutputPort("state"), **extra)
    return builder.Build()


class RailFollower(LeafSystem):
    """color_image -> steering_angle: steer towards the middle of the two rails, found
    by colour in the lower ``1 - top`` of the image (one rail seen: away from it; none:
    straight on)."""

    def __init__(self, *, gain_deg=30.0, top=0.4, margin=40.0):
        super().__init__()
        self._gain, self._top, self._margin = np.deg2rad(gain_deg), top, margin
        self._image = self.DeclareAbstractInputPort("color_image",
                                                    AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, self._steer)

    def offset(self, rgb) -> float:
        """Where the track's middle is seen, in [-1 (left edge), 1 (right edge)]."""
        low = rgb[int(self._top * rgb.shape[0]):, :, :3].astype(np.int16)
        r, g, b = low[..., 0], low[..., 1], low[..., 2]
        columns = np.arange(low.shape[1])[None, :] + np.zeros(r.shape)
        left = columns[(r > g + self._margin) & (r > b + self._margin)]
        right = columns[(b > r + self._margin) & (b > g + self._margin)]
        if len(left) and len(right):
            return float((left.mean() + right.mean()) / (low.shape[1] - 1) - 1.0)
        return 1.0 if len(left) else -1.0 if len(right) else 0.0

    def _steer(self, context, output):
        output.SetAtIndex(0, -self._gain * self.offset(self._image.Eval(context).data))


def rail_follower(config):
    """The factory a run file names: ``controller: {factory:
    "examples/cart/cart.py:rail_follower", parameters: {gain_deg: 30}}``."""
    return RailFollower(**config.parameters)
