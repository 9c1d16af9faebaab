"""A classical vision controller for the taxi plant: steer away from the grass.

It counts green pixels in the left and right halves of the lower image and steers
toward the side with less grass. No network, no estimate output (the interface's
only optional port), four numbers in ``controller.parameters``."""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U


class GrassFollower(LeafSystem):
    """color_image (ImageRgba8U) -> steering_angle (rad, positive turns left):
    ``gain_deg`` degrees of steering per unit of grass balance (`grass_balance`) above
    ``bias``; a pixel is grass when its green exceeds its red and its blue by more than
    ``margin`` (of 255); only the image below ``top`` (a share of its height from the
    top) is read."""

    def __init__(self, *, gain_deg=10.0, bias=0.09, margin=8.0, top=0.5):
        super().__init__()
        self._gain, self._bias, self._margin, self._top = gain_deg, bias, margin, top
        self._image = self.DeclareAbstractInputPort("color_image",
                                                    AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, self._steer)

    def grass_balance(self, rgb) -> float:
        """Share of grass pixels on the right minus on the left, below ``top``."""
        low = rgb[int(self._top * rgb.shape[0]):, :, :3].astype(np.int16)
        red, green, blue = low[..., 0], low[..., 1], low[..., 2]
        grass = (green > red + self._margin) & (green > blue + self._margin)
        half = grass.shape[1] // 2
        return float(grass[:, half:].mean() - grass[:, :half].mean())

    def _steer(self, context, output):
        balance = self.grass_balance(self._image.Eval(context).data)
        output.SetAtIndex(0, np.deg2rad(self._gain * (balance - self._bias)))


def make_controller(config):
    """The factory a run file names: ``controller: {factory:
    "examples/grass_follower/grass_follower.py:make_controller", parameters: {...}}``."""
    return GrassFollower(**config.parameters)
