"""Adaptive refinement of a swept table: known answers for the cell arithmetic, only
new nodes evaluated, resumable, and a better BRT than the coarse table for a loop
whose controller is not linear between the coarse nodes."""

import functools

import numpy as np
import pytest
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem

from reachwatch.reach import Grid, InlineExecutor, Probe, sign_agreement, solve_brt, sweep
from reachwatch.reach.refine import (cell_nodes, finer_grid, refine_adaptively, refine_table,
                                     uncertain_cells)
from test_reach_nd import DoubleIntegrator, _Plant

PROBE = Probe(plant="plant", control_port="controller.u")
CALLS = []


class _WigglyController(LeafSystem):
    """u = -p - 0.6 v + 0.3 + a sin(w p): a coarse grid's interpolation misses the
    wiggle. Counts its evaluations in CALLS."""

    def __init__(self, amplitude, frequency):
        super().__init__()
        self.a, self.w = amplitude, frequency
        self.x = self.DeclareVectorInputPort("x", 2)
        self.DeclareVectorOutputPort("u", 1, self._calc)

    def _calc(self, context, output: BasicVector):
        CALLS.append(1)
        p, v = self.x.Eval(context)
        output.SetFromVector([law(p, v, self.a, self.w)])


def law(p, v, a, w):
    return -p - 0.6 * v + 0.3 + a * np.sin(w * p)


def make_loop(amplitude, frequency):
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem("plant", _Plant())
    controller = builder.AddNamedSystem("controller", _WigglyController(amplitude, frequency))
    builder.Connect(plant.get_output_port(), controller.get_input_port())
    builder.Connect(controller.get_output_port(), plant.get_input_port())
    return builder.Build()


def test_cell_arithmetic_known_answers():
    g = Grid(lo=[0.0], hi=[4.0], shape=[5])
    fine = finer_grid(g)
    assert fine.shape == (9,) and np.allclose(fine.axes[0][::2], g.axes[0])
    values = np.array([-3.0, -1.0, 0.5, 3.0, 5.0])
    assert uncertain_cells(g, values, band=0.0).tolist() == [False, True, False, False]
    assert uncertain_cells(g, values, band=1.0).tolist() == [True, True, True, False]
    output = np.array([[0.0], [0.1], [0.2], [2.0], [2.1]])
    assert uncertain_cells(g, values, band=0.0, output=output, variation=1.0).tolist() == [
        False, True, True, False]
    assert cell_nodes(np.array([False, True, False, False])).tolist() == [
        False, False, True, True, True, False, False, False, False]
    two = cell_nodes(np.array([[True, False], [False, False]]))
    assert two.shape == (5, 5) and two.sum() == 9 and two[:3, :3].all()
    with pytest.raises(ValueError, match="factor must be a whole number >= 2"):
        finer_grid(g, 1)
    with pytest.raises(ValueError, match="do not match the grid"):
        uncertain_cells(g, values[:4], band=1.0)


def test_refinement_evaluates_only_new_nodes_and_resumes(tmp_path):
    factory = functools.partial(make_loop, 0.5, 9.0)
    g = Grid(lo=[-1.2, -2.0], hi=[1.2, 2.0], shape=[5, 5], names=("p", "v"))
    coarse = sweep(factory, g, probe=PROBE, cache_dir=tmp_path, executor=InlineExecutor(),
                   progress=False)
    cells = np.zeros((4, 4), bool)
    cells[1, 2] = cells[2, 2] = True                   # two neighbours: 15 fine nodes, 6 old
    CALLS.clear()
    fine = refine_table(factory, coarse, cells, probe=PROBE, cache_dir=tmp_path, chunk_size=4,
                        executor=InlineExecutor(), progress=False)
    assert fine.grid.shape == (9, 9) and fine.computed == 9 and len(CALLS) == 9
    p, v = fine.grid.mesh()
    exact = law(p, v, 0.5, 9.0)
    got = fine["controller.u"][..., 0]
    np.testing.assert_allclose(got[fine.rendered], exact[fine.rendered])
    assert fine.rendered.sum() == 25 + 9
    interpolated = g.interpolate(coarse["controller.u"], fine.grid.states())[:, 0].reshape(9, 9)
    np.testing.assert_allclose(got[~fine.rendered], interpolated[~fine.rendered])
    assert not np.allclose(got[fine.rendered], interpolated[fine.rendered])
    # cached: nothing evaluated again; a lost chunk is evaluated again, alone
    CALLS.clear()
    assert refine_table(factory, coarse, cells, probe=PROBE, cache_dir=tmp_path, chunk_size=4,
                        executor=InlineExecutor(), progress=False).computed == 0
    folder = next(d for d in tmp_path.iterdir() if d.name.startswith("evaluate_states"))
    (folder / "chunk_000001.npz").unlink()
    again = refine_table(factory, coarse, cells, probe=PROBE, cache_dir=tmp_path, chunk_size=4,
                         executor=InlineExecutor(), progress=False)
    assert again.computed == 4 and len(CALLS) == 4
    np.testing.assert_array_equal(again["controller.u"], fine["controller.u"])
    # a second level evaluates neither the coarse nodes nor the first level's
    CALLS.clear()
    finer = refine_table(factory, fine, np.ones((8, 8), bool), probe=PROBE, cache_dir=tmp_path,
                         executor=InlineExecutor(), progress=False)
    assert finer.computed == 17 * 17 - 34 and finer.rendered.all()
    with pytest.raises(ValueError, match=r"cells shaped \(3, 3\) do not match"):
        refine_table(factory, coarse, np.ones((3, 3), bool), probe=PROBE, cache_dir=tmp_path)


def test_adaptive_refinement_beats_the_coarse_table_for_fewer_renders(tmp_path):
    factory = functools.partial(make_loop, 0.6, 12.0)
    g = Grid(lo=[-1.2, -2.0], hi=[1.2, 2.0], shape=[9, 9], names=("p", "v"))
    dyn = DoubleIntegrator()

    def solve(table):
        return solve_brt(table.grid, dyn, table["controller.u"], horizon=2.0, period=0.05,
                         device="cpu")

    coarse = sweep(factory, g, probe=PROBE, cache_dir=tmp_path, executor=InlineExecutor(),
                   progress=False)
    levels = refine_adaptively(factory, coarse, probe=PROBE, solve=solve, levels=2, band=0.15,
                               variation=1.5, cache_dir=tmp_path, executor=InlineExecutor(),
                               progress=False)
    assert [lv.table.grid.shape for lv in levels] == [(9, 9), (17, 17), (33, 33)]
    # the truth: a BRT from the exact controller on the finest grid
    truth_grid = levels[-1].table.grid
    p, v = truth_grid.mesh()
    truth = solve_brt(truth_grid, dyn, law(p, v, 0.6, 12.0)[..., None], horizon=2.0,
                      period=0.05, device="cpu")
    states = np.random.default_rng(0).uniform(g.lo, g.hi, size=(4000, 2))
    reference = truth.at(states)
    agreement = [sign_agreement(lv.solution.at(states), reference) for lv in levels]
    assert agreement[2] > agreement[0] + 0.02 and agreement[2] > 0.98
    assert levels[-1].rendered < 0.7 * truth_grid.size
