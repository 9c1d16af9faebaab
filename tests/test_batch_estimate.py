"""A controller's batch ``estimate(images)`` must return one row per image; a method of
that name that takes one image is refused in one line, not broadcast into every row."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.training.dataset_images import estimator


class _Estimating(LeafSystem):
    def __init__(self, rows: bool):
        super().__init__()
        self._rows = rows
        self.DeclareAbstractInputPort("color_image", AbstractValue.Make(ImageRgba8U()))
        self.DeclareVectorOutputPort("steering_angle", 1, lambda c, o: o.SetAtIndex(0, 0.0))
        self.DeclareVectorOutputPort("estimate", 2, lambda c, o: o.SetFromVector([1.0, 2.0]))

    def estimate(self, images):
        return np.tile([1.0, 2.0], (len(images), 1)) if self._rows else np.array([1.0, 2.0])


def test_a_batch_estimate_of_one_row_per_image_is_used():
    estimate, size = estimator(_Estimating(rows=True))
    assert size == 2 and estimate(np.zeros((3, 8, 8, 3), np.uint8)).shape == (3, 2)


def test_a_single_image_estimate_method_is_refused():
    estimate, _ = estimator(_Estimating(rows=False))
    with pytest.raises(ValueError, match=r"returned shape \(2,\) for 3 images.*\(3, 2\)"):
        estimate(np.zeros((3, 8, 8, 3), np.uint8))


def test_an_ensemble_member_of_another_width_is_refused_in_one_line():
    """The ensemble baseline takes two numbers per image (`ensemble_estimator`'s
    contract); a member returning three is refused naming it, not broadcast."""
    from reachwatch.training.dataset_images import ImageTools, render_chunk

    class _Renderer:
        def render(self, state):
            return np.zeros((8, 8, 4), np.uint8)

    class _Source:
        height, width, scenario = 4, 4, None
        tools = ImageTools(_Renderer(), lambda images: np.zeros((len(images), 0)), 0,
                           [lambda images: np.zeros((len(images), 3))])
    with pytest.raises(ValueError, match=r"ensemble member 0: .* returned shape \(2, 3\) for "
                                         r"2 images; the ensemble baseline takes \(2, 2\)"):
        render_chunk(_Source(), np.zeros((2, 3)))
