"""Render wing-camera images at arbitrary states with one reused Context."""

from pathlib import Path

import cv2
import numpy as np
from pydrake.systems.framework import DiagramBuilder

from reachwatch.systems import CameraConfig, Environment
from reachwatch.systems.checks import warn_once
from reachwatch.systems.files import atomic_write_bytes

from .world import add_world


def check_state(state) -> np.ndarray:
    """``state`` as a float array ``[px m, py m, theta rad]``; raises on bad shape or NaN."""
    x = np.asarray(state, dtype=float)
    if x.shape != (3,):
        raise ValueError(f"a plant state is [px m, py m, theta rad], got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"plant state must be finite, got {x}")
    return x


class StateRenderer:
    """Renders the wing camera of ``environment`` at any plant state.

    Builds the world diagram once; every `render` sets the plant state in the same
    Context and evaluates the camera's colour port (no Simulator, no new Context per frame).
    """

    def __init__(self, *, environment: Environment, camera: CameraConfig = None,
                 shadows: bool = False):
        builder = DiagramBuilder()
        self._world = add_world(builder, environment=environment, camera=camera,
                                shadows=shadows)
        builder.ExportInput(self._world.plant.get_steering_angle_input_port(), "steering_angle")
        builder.ExportInput(self._world.plant.get_speed_input_port(), "speed")
        self._diagram = builder.Build()
        self._context = self._diagram.CreateDefaultContext()
        self._plant_context = self._world.plant.GetMyMutableContextFromRoot(self._context)
        self._camera_context = self._world.camera.GetMyContextFromRoot(self._context)

    @property
    def world(self):
        return self._world

    @property
    def diagram(self):
        return self._diagram

    def render(self, state) -> np.ndarray:
        """RGB image (H, W, 3) uint8 at ``state = [px m, py m, theta rad]`` (a copy)."""
        self._plant_context.SetContinuousState(check_state(state))
        image = self._world.camera.color_image_output_port().Eval(self._camera_context)
        return image.data[..., :3].copy()


def check_frame_size(frame_shape, scenario) -> None:
    """A ValueError in one line when a frame the loop rendered (``frame_shape``, height
    first) is not ``scenario.camera``'s size: what a dataset records as the size its
    detector is trained at, and what a monitor's checkpoint enforces online (a loop that
    builds its camera without ``scenario.camera`` would else be judged at a size it
    never renders). Nothing for a scenario without a camera."""
    camera = getattr(scenario, "camera", None)
    if camera is not None and tuple(frame_shape[:2]) != (camera.height, camera.width):
        raise ValueError(f"the application's loop renders {frame_shape[0]}x{frame_shape[1]} "
                         f"frames, and scenario.camera is {camera.height}x{camera.width}: "
                         f"build the loop's camera from scenario.camera, or set it to the "
                         f"frames' size")


def warn_blank_frames(frames, where: str) -> None:
    """A one-line warning, once a process for ``where``, when frames ``(N, H, W, 3|4)``
    a loop rendered include some of one colour: a renderer that fails (a GL driver, a
    render from another thread) gives such frames without an error, and a table,
    dataset or recording made of them is wrong without a word."""
    rgb = np.asarray(frames)[..., :3].reshape(len(frames), -1, 3)
    blank = int(np.sum(np.all(rgb.max(axis=1) == rgb.min(axis=1), axis=1))) if rgb.size else 0
    if blank:
        what = ("a frame the camera rendered is" if len(rgb) == 1 else
                f"{blank} of {len(rgb)} frames the camera rendered are")
        warn_once(f"{where}: {what} of one colour: a renderer that fails gives such frames "
                  f"without an error; look at one with 'reachwatch render'",
                  key=("blank frames", where))


def render_at_states(diagram, *, plant: str, image_port: str, states,
                     context=None) -> np.ndarray:
    """RGB images ``(N, H, W, 3)`` uint8 of any diagram's camera at ``states``: sets the
    continuous state of the subsystem ``plant`` and evaluates the image port named
    ``"system.port"`` (one reused Context, ``context`` when given, so that calls one
    state at a time share it; no Simulator). For a plant of any state dimension, where
    `StateRenderer` is the taxi's."""
    context = diagram.CreateDefaultContext() if context is None else context
    plant_context = diagram.GetSubsystemByName(plant).GetMyMutableContextFromRoot(context)
    system_name, _, port_name = image_port.partition(".")
    system = diagram.GetSubsystemByName(system_name)
    port, port_context = system.GetOutputPort(port_name), system.GetMyContextFromRoot(context)
    states = np.asarray(states, float)
    if states.ndim != 2 or states.shape[1] != plant_context.num_continuous_states():
        raise ValueError(f"states must be (N, {plant_context.num_continuous_states()}) for "
                         f"'{plant}', got {states.shape}")
    images = []
    for x in states:
        plant_context.SetContinuousState(x)
        images.append(port.Eval(port_context).data[..., :3].copy())
    return np.stack(images)


def write_png(path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image atomically."""
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    return atomic_write_bytes(path, data.tobytes())
