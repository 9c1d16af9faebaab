"""An application that draws no slices of its own gets the default figure
(`reach.slices.plot_value_slices`): grids of one, two and four axes, with points."""

import numpy as np
import pytest

from reachwatch.reach import Grid, ValueFunction
from reachwatch.reach.application import Application
from reachwatch.reach.slices import plot_value_slices


@pytest.mark.parametrize("shape", [[9], [9, 7], [9, 7, 5, 3]])
def test_the_default_slice_figure_draws_any_grid(tmp_path, shape):
    grid = Grid(lo=[-1.0] * len(shape), hi=[1.0] * len(shape), shape=shape)
    values = np.abs(grid.mesh()[0]) - 0.5               # the BRT: |x0| >= 0.5
    vf = ValueFunction(grid, values, 1.0, "test")
    points = [("starts", np.zeros((3, len(shape))), "r.")]
    path = plot_value_slices({"a": vf, "b": vf}, path=tmp_path / "slices.png", title="t",
                             points=points)
    assert path.stat().st_size > 1000 and path.read_bytes()[:4] == b"\x89PNG"


def test_an_application_without_plot_slices_draws_the_default(tmp_path):
    """`Application.plot_slices` itself (what an application that does not define it
    runs) writes the figure; it did raise, after the sweeps and the solve."""
    grid = Grid(lo=[-1.0, -1.0], hi=[1.0, 1.0], shape=[5, 5])
    vf = ValueFunction(grid, grid.mesh()[0], 1.0, "test")
    path = Application.plot_slices(None, {"BRT": vf}, scenario=None, at=0.0,
                                   path=tmp_path / "brt.png")
    assert path.is_file()
