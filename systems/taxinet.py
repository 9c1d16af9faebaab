"""The vision-based controller under test: `TaxiNet` (image -> estimate) followed by
the `ProportionalController` (estimate -> steering angle)."""

import numpy as np
import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from .models import PreprocessConfig, preprocess, preprocess_batched

#: The authors' P-controller gains: phi_deg = -0.74 * px_hat - 0.44 * theta_hat_deg.
PX_GAIN_DEG_PER_M = -0.74
THETA_GAIN = -0.44


class TaxiNet(LeafSystem):
    """Estimates crosstrack and heading error from the wing-camera image.

    .. pydrake_system::

        name: TaxiNet
        input_ports:
        - color_image
        output_ports:
        - estimate

    ``color_image`` is Drake's `ImageRgba8U`; ``estimate`` is
    ``[px_hat m, theta_hat deg]``. ``image_size = (height, width)``, when given,
    is enforced: a checkpoint trained on one size is not silently fed another.
    """

    def __init__(self, *, model: torch.nn.Module, preprocess_config: PreprocessConfig,
                 image_size=None):
        super().__init__()
        self._model = model.eval()
        self._preprocess = preprocess_config.validate()
        self._image_size = tuple(image_size) if image_size is not None else None
        self._prepared = {}         # frame pointer -> (pixels, estimate): `prepare_batch`
        self._image_port = self.DeclareAbstractInputPort(
            "color_image", AbstractValue.Make(ImageRgba8U()))
        self._estimate_port = self.DeclareVectorOutputPort("estimate", 2,
                                                           self._calc_estimate)

    def get_color_image_input_port(self):
        return self._image_port

    def get_estimate_output_port(self):
        return self._estimate_port

    @torch.no_grad()
    def estimate(self, images_rgb: np.ndarray) -> np.ndarray:
        """``(N, H, W, 3)`` uint8 RGB (or RGBA) -> ``(N, 2)`` [px_hat m, theta_hat deg]."""
        x = preprocess_batched(images_rgb, self._preprocess)
        return self._model(x).double().numpy()

    def _frame(self, context) -> np.ndarray:
        rgba = self._image_port.Eval(context).data
        if self._image_size is not None and rgba.shape[:2] != self._image_size:
            raise ValueError(
                f"TaxiNet: input port 'color_image' got a {rgba.shape[0]}x{rgba.shape[1]} "
                f"image, but this model was trained on {self._image_size[0]}x"
                f"{self._image_size[1]} (height x width); set the camera size to match")
        return rgba

    @torch.no_grad()
    def prepare_batch(self, pairs):
        """The batch entry point of `reachwatch.diagrams.lockstep`. ``pairs``: ``(TaxiNet,
        its Context)`` in several loops at the same tick (a Context None: nothing). The
        frames are preprocessed as one batch (the same numbers per frame as one at a
        time); each frame then goes through its own system's network alone, since a
        batched matrix product may differ from a single one in the last bits. Until its
        next call, each system's ``estimate`` output returns its result for a frame of
        exactly these pixels."""
        for system, _ in pairs:
            system._prepared = {}
        pairs = [(system, system._frame(context)) for system, context in pairs
                 if context is not None]
        groups = {}                                  # one batch per preprocessing
        for system, view in pairs:
            groups.setdefault((repr(system._preprocess), view.shape), []).append((system, view))
        for group in groups.values():
            frames = np.stack([view for _, view in group])      # copies, to check against
            x = preprocess(torch.from_numpy(frames), group[0][0]._preprocess)
            for i, ((system, view), frame) in enumerate(zip(group, frames)):
                alone = torch.cat([x[i:i + 1]])     # as `estimate` has it: same strides,
                system._prepared[view.ctypes.data] = (  # and so the same conv kernel
                    frame, system._model(alone).double().numpy()[0])

    def _calc_estimate(self, context, output):
        rgba = self._frame(context)
        frame, estimate = self._prepared.get(rgba.ctypes.data, (None, None))
        if frame is None or not np.array_equal(frame, rgba):
            estimate = self.estimate(rgba[None])[0]
        output.SetFromVector(estimate)


class ProportionalController(LeafSystem):
    """The authors' P-controller on the estimate (degrees inside, radians out).

    .. pydrake_system::

        name: ProportionalController
        input_ports:
        - estimate
        output_ports:
        - steering_angle

    ``phi_deg = px_gain * px_hat + theta_gain * theta_hat_deg``; ``steering_angle`` is
    ``phi`` in rad. No saturation unless ``max_steering_deg`` is given (the authors
    had none).
    """

    def __init__(self, *, px_gain=PX_GAIN_DEG_PER_M, theta_gain=THETA_GAIN,
                 max_steering_deg=None):
        super().__init__()
        self._gains = np.array([px_gain, theta_gain], dtype=float)
        self._limit = None if max_steering_deg is None else float(max_steering_deg)
        self._estimate_port = self.DeclareVectorInputPort("estimate", 2)
        self._steering_port = self.DeclareVectorOutputPort("steering_angle", 1,
                                                           self._calc_steering)

    def get_estimate_input_port(self):
        return self._estimate_port

    def get_steering_angle_output_port(self):
        return self._steering_port

    def steering_deg(self, estimate) -> np.ndarray:
        """phi (deg) for ``estimate = [..., 2]`` [px_hat m, theta_hat deg]."""
        phi = np.asarray(estimate, dtype=float) @ self._gains
        return phi if self._limit is None else np.clip(phi, -self._limit, self._limit)

    def _calc_steering(self, context, output):
        output.SetAtIndex(0, np.deg2rad(self.steering_deg(self._estimate_port.Eval(context))))


class TrueStateEstimator(LeafSystem):
    """A perfect "estimator": the plant state as ``[px m, theta deg]``. Privileged
    information (no camera): for comparisons, tests and controllers without vision.

    .. pydrake_system::

        name: TrueStateEstimator
        input_ports:
        - state
        output_ports:
        - estimate
    """

    def __init__(self):
        super().__init__()
        self._state_port = self.DeclareVectorInputPort("state", 3)
        self._estimate_port = self.DeclareVectorOutputPort("estimate", 2, self._calc_estimate)

    def get_state_input_port(self):
        return self._state_port

    def get_estimate_output_port(self):
        return self._estimate_port

    def _calc_estimate(self, context, output):
        px, _, theta = self._state_port.Eval(context)
        output.SetFromVector([px, np.rad2deg(theta)])
