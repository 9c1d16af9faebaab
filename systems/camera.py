"""The aircraft's geometry frame and the wing camera (Drake `RgbdSensor`)."""

import dataclasses as dc

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (ClippingRange, ColorRenderCamera, DepthRange,
                              DepthRenderCamera, FramePoseVector, GeometryFrame,
                              RenderCameraCore, SceneGraph)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import CameraInfo, RgbdSensor

from .bounds import bounded, check_bounds
from .ports import weak_callback


def _make_pose_vector():
    return AbstractValue.Make(FramePoseVector())


#: The farthest a camera's clipping range reaches (m).
MAX_RANGE = 1e5


@dc.dataclass
class CameraConfig:
    """The right-wing camera of the authors' X-Plane setup, as their public code places it.

    Offsets are from the aircraft reference point, which sits ``reference_height``
    above the ground; ``yaw_out_deg`` turns the camera outward (right), and
    ``pitch_down_deg`` tilts it down. Image size in pixels, FOV horizontal.
    """
    width: int = bounded(360, 8, 4096, whole=True, unit="px")
    height: int = bounded(200, 8, 4096, whole=True, unit="px")
    fov_x_deg: float = bounded(80.0, 1.0, 170.0, unit="deg")
    right: float = bounded(2.17, -100.0, 100.0, unit="m")
    up: float = bounded(0.42, -100.0, 100.0, unit="m")
    forward: float = bounded(0.0, -100.0, 100.0, unit="m")
    reference_height: float = bounded(1.5, -100.0, 100.0, unit="m")
    yaw_out_deg: float = bounded(5.0, -180.0, 180.0, unit="deg")
    pitch_down_deg: float = bounded(5.0, -90.0, 90.0, unit="deg")
    near: float = bounded(0.5, 0.0, MAX_RANGE, low_open=True, high_open=True, unit="m",
                          note="< far")
    far: float = bounded(3000.0, 0.0, MAX_RANGE, low_open=True, unit="m", note="> near")

    def validate(self):
        check_bounds(self, "camera.")
        if not self.near < self.far:
            raise ValueError(f"camera.near must be < camera.far, got near {self.near}, far "
                             f"{self.far}")
        return self

    @property
    def fov_y_rad(self) -> float:
        """Vertical FOV (rad), what Drake's `CameraInfo` takes."""
        half_x = np.deg2rad(self.fov_x_deg) / 2
        return 2.0 * np.arctan(np.tan(half_x) * self.height / self.width)

    def X_BC(self) -> RigidTransform:
        """Camera pose in the aircraft body frame (x forward, y left, z up).

        Drake's camera frame looks along +z with +x right and +y down."""
        look_forward = RotationMatrix(np.array([[0.0, 0.0, 1.0],
                                                [-1.0, 0.0, 0.0],
                                                [0.0, -1.0, 0.0]]))
        R = (RotationMatrix.MakeZRotation(-np.deg2rad(self.yaw_out_deg)) @ look_forward
             @ RotationMatrix.MakeXRotation(-np.deg2rad(self.pitch_down_deg)))
        return RigidTransform(R, [self.forward, -self.right, self.reference_height + self.up])


class AircraftGeometry(LeafSystem):
    """Poses the aircraft's body frame in a `SceneGraph` from the plant state.

    .. pydrake_system::

        name: AircraftGeometry
        input_ports:
        - state
        output_ports:
        - geometry_pose

    ``state = [px m, py m, theta rad]`` puts the body origin at world
    ``(py, px, 0)`` yawed by theta (world: x downtrack, y left, z up).
    """

    def __init__(self, *, scene_graph: SceneGraph, name: str = "aircraft"):
        super().__init__()
        self._source_id = scene_graph.RegisterSource(name)
        self._frame_id = scene_graph.RegisterFrame(self._source_id,
                                                   GeometryFrame(f"{name}_body"))
        self._state_port = self.DeclareVectorInputPort("state", 3)
        self._pose_port = self.DeclareAbstractOutputPort(
            "geometry_pose", _make_pose_vector, weak_callback(self._calc_pose))

    @property
    def source_id(self):
        return self._source_id

    @property
    def frame_id(self):
        return self._frame_id

    def get_state_input_port(self):
        return self._state_port

    def get_geometry_pose_output_port(self):
        return self._pose_port

    def _calc_pose(self, context, output):
        px, py, theta = self._state_port.Eval(context)
        poses = output.get_mutable_value()
        poses.clear()
        poses.set_value(self._frame_id,
                        RigidTransform(RotationMatrix.MakeZRotation(theta), [py, px, 0.0]))


def make_wing_camera(*, frame_id, config: CameraConfig, renderer_name: str) -> RgbdSensor:
    """Drake `RgbdSensor` on the aircraft frame; only its colour port is meant to be
    evaluated (ports are lazy, so depth is never rendered unless asked for)."""
    config.validate()
    core = RenderCameraCore(renderer_name,
                            CameraInfo(config.width, config.height, config.fov_y_rad),
                            ClippingRange(config.near, config.far), RigidTransform())
    # the depth port is never rendered here, but its range must lie inside the clipping
    # range whatever near and far are (60 m deep from 0.51 m with the defaults)
    nearest = config.near + min(0.01, (config.far - config.near) / 4)
    depth = DepthRenderCamera(core, DepthRange(
        nearest, min(config.far, max(60.0, nearest + 1.0))))
    sensor = RgbdSensor(frame_id, config.X_BC(), ColorRenderCamera(core, False), depth)
    sensor.set_name("wing_camera")
    return sensor
