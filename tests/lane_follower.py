"""A user's controller over two files, as the tests write it: ``follower.py`` (the
factory, ``follower.py:make``) imports its sibling ``lane_vision.py`` (``OFFSET``, the
constant steering it outputs)."""

FACTORY = """\
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U

import lane_vision


class Offset(LeafSystem):
    def __init__(self):
        super().__init__()
        self.DeclareAbstractInputPort("color_image", AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, self._steer)

    def _steer(self, context, output):
        output.SetAtIndex(0, lane_vision.OFFSET)


def make(config):
    from lane_vision import OFFSET         # an import inside the factory finds it too
    assert OFFSET == lane_vision.OFFSET
    return Offset()
"""
