"""Closed loops in lockstep (`reachwatch.diagrams.lockstep`): several runs advanced
together, the controller fed their frames as one batch, give exactly the runs one at a
time gives."""

import dataclasses as dc

import numpy as np
import pytest
import torch

from reachwatch.diagrams import (load_scenario, make_closed_loop_diagram,
                                 make_state_feedback_diagram, save_checkpoint, simulate)
from reachwatch.diagrams.closed_loop import start_simulator
from reachwatch.diagrams.lockstep import batch_systems, loop_copies, simulate_lockstep
from reachwatch.systems import PreprocessConfig, TaxiNet, TaxiNetConfig, build_taxinet
from reachwatch.reach import loop_runs
from reachwatch.reach.application import ApplicationRef
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.taxi import OffRunway, fidelity
from reachwatch.taxi.grid import paper_grid

#: Starts on the runway; the third leaves it within a few ticks, so its copy of the
#: loop takes the next start while the others run on.
STARTS = [[0.5, 110.0, 0.02], [-3.0, 120.0, -0.1], [9.7, 130.0, 0.3], [0.0, 140.0, 0.0],
          [-8.0, 150.0, -0.3]]
FIELDS = ("time", "state", "estimate", "failed", "failure_time")


@pytest.fixture(scope="module")
def tiny_scenario(tmp_path_factory):
    """A 32x64 camera and a seeded random TaxiNet for it (its estimates move with the
    image, which is all lockstep needs)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("lockstep") / "taxinet_32x64.pt"
    save_checkpoint(path, kind="taxinet", model=build_taxinet(TaxiNetConfig(), PreprocessConfig()),
                    model_config=TaxiNetConfig(), preprocess_config=PreprocessConfig(),
                    metadata={"image_size": [32, 64]})
    return load_scenario(data=f"camera: {{width: 64, height: 32}}\n"
                              f"controller: {{checkpoint: {path}}}\n")


def _same(a, b):
    return all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), equal_nan=True)
               for f in FIELDS)


def test_lockstep_runs_equal_one_at_a_time_and_the_controller_sees_batches(
        tiny_scenario, monkeypatch):
    B = tiny_scenario.environment.half_width
    settings = dict(duration=0.4, period=0.05, failed=OffRunway(B))
    diagram = make_closed_loop_diagram(tiny_scenario)
    alone = [simulate(diagram, initial_state=x, **settings) for x in STARTS]
    batches, singles = [], []
    prepare, estimate = TaxiNet.prepare_batch, TaxiNet.estimate
    monkeypatch.setattr(TaxiNet, "prepare_batch", lambda self, pairs: (
        batches.append(sum(c is not None for _, c in pairs)), prepare(self, pairs))[1])
    monkeypatch.setattr(TaxiNet, "estimate", lambda self, images: (
        singles.append(len(images)), estimate(self, images))[1])
    loops = loop_copies(lambda: make_closed_loop_diagram(tiny_scenario), 3)
    together = simulate_lockstep(loops, initial_states=STARTS, **settings)
    assert alone[2].failed and not alone[0].failed
    assert len(together) == len(alone) == len(STARTS)
    assert all(_same(a, b) for a, b in zip(alone, together))
    assert max(batches) == 3 and not singles          # every estimate came from a batch
    assert sum(batches) == sum(len(run.time) for run in alone)


def test_a_taxinet_batch_equals_one_frame_at_a_time():
    """Preprocessed as one batch, then each frame through the network alone: the same
    bits as one frame at a time, for the MLP and the CNN; a frame that changed after
    the batch is computed afresh."""
    rng = np.random.default_rng(0)
    for config, preprocess in ((TaxiNetConfig(), PreprocessConfig()),
                               (TaxiNetConfig(arch="cnn", channels=[4, 8]),
                                PreprocessConfig(kind="resize", height=16, width=32,
                                                 grayscale=False))):
        torch.manual_seed(1)
        model = build_taxinet(config, preprocess)
        systems = [TaxiNet(model=model, preprocess_config=preprocess) for _ in range(3)]
        contexts = [s.CreateDefaultContext() for s in systems]
        frames = rng.integers(0, 256, (3, 40, 72, 4), dtype=np.uint8)
        for system, context, frame in zip(systems, contexts, frames):
            system.get_color_image_input_port().FixValue(context, _image(frame))
        systems[0].prepare_batch(list(zip(systems, contexts)))
        for system, context, frame in zip(systems, contexts, frames):
            assert np.array_equal(system.get_estimate_output_port().Eval(context),
                                  system.estimate(frame[None])[0])
        other = rng.integers(0, 256, (40, 72, 4), dtype=np.uint8)
        systems[1].get_color_image_input_port().FixValue(contexts[1], _image(other))
        assert np.array_equal(systems[1].get_estimate_output_port().Eval(contexts[1]),
                              systems[1].estimate(other[None])[0])


def _image(rgba):
    from pydrake.common.value import AbstractValue
    from pydrake.systems.sensors import ImageRgba8U
    image = ImageRgba8U(rgba.shape[1], rgba.shape[0])
    image.mutable_data[...] = rgba
    return AbstractValue.Make(image)


def test_a_loop_without_batch_entry_points_runs_one_system_at_a_time(tiny_scenario):
    B = tiny_scenario.environment.half_width
    loops = loop_copies(lambda: make_state_feedback_diagram(tiny_scenario), 2)
    assert batch_systems(loops[0][0]) == []
    settings = dict(duration=1.0, period=0.05, failed=OffRunway(B))
    together = simulate_lockstep(loops, initial_states=STARTS, **settings)
    alone = [simulate(loops[0][0], initial_state=x, **settings) for x in STARTS]
    assert len(together) == len(STARTS)
    assert all(_same(a, b) for a, b in zip(alone, together))
    mixed = [loops[0], loop_copies(lambda: make_closed_loop_diagram(tiny_scenario), 1)[0]]
    with pytest.raises(ValueError, match="differ"):
        simulate_lockstep(mixed, initial_states=STARTS, **settings)


def test_real_loop_runs_do_not_depend_on_lockstep_nor_torch_threads(tiny_scenario, monkeypatch):
    """The real-loop rollouts and paths (`reach.loop_runs`, here the taxi's) and the
    taxi's missions (their stop test keeps state per run) give the same arrays one run at
    a time on torch's threads and two at a time on `LOOP_TORCH_THREADS` (1, restored
    after); a start off the runway is skipped."""
    scenario = dc.replace(tiny_scenario)
    B = scenario.environment.half_width
    grid = paper_grid(B, (3, 3, 3))
    starts = np.array(STARTS[1:4] + [[B + 1.0, 100.0, 0.0]])
    before, seen = torch.get_num_threads(), []
    prepare = TaxiNet.prepare_batch
    monkeypatch.setattr(TaxiNet, "prepare_batch", lambda self, pairs: (
        seen.append(torch.get_num_threads()), prepare(self, pairs))[1])
    runs, taxi = {}, ApplicationRef(TAXI_APPLICATION)
    for lockstep, threads in ((1, 0), (2, 1)):
        monkeypatch.setattr(loop_runs, "LOOP_TORCH_THREADS", threads)
        runs[lockstep] = (
            loop_runs.loop_rollouts(taxi, scenario, 0.3, grid, starts, lockstep=lockstep),
            loop_runs.loop_paths(taxi, scenario, 0.2, 0.1, 2, grid, starts, lockstep=lockstep),
            fidelity.mission_rollouts(scenario, None, 0.2, starts, mission_limit=1.5,
                                      lockstep=lockstep))
    assert seen and set(seen) == {1} and torch.get_num_threads() == before
    for one, two in zip(runs[1], runs[2]):
        assert one.keys() == two.keys()
        for name in one:
            assert np.array_equal(one[name], two[name], equal_nan=True), name
    ticks = runs[1][0]["ticks"]
    assert ticks[0] == 7 and 0 < ticks[1] < 7 and ticks[-1] == 0
    with pytest.raises(ValueError, match="lockstep must be a whole number"):
        loop_runs.loop_rollouts(taxi, scenario, 0.3, grid, starts, lockstep=0)


def test_a_reused_context_starts_afresh_but_keeps_its_render_engine(tiny_scenario):
    """A run on a reused Context equals one on a fresh Context, and starting it resets
    every system but the SceneGraph, whose geometry state (render engines) stays: a
    geometry removed in the Context is still gone after the start (resetting the
    SceneGraph too cloned the render engine for every run)."""
    B = tiny_scenario.environment.half_width
    settings = dict(duration=0.3, period=0.05, failed=OffRunway(B))
    diagram = make_closed_loop_diagram(tiny_scenario)
    context = diagram.CreateDefaultContext()
    fresh = simulate(diagram, initial_state=STARTS[0], **settings)
    simulate(diagram, initial_state=STARTS[1], context=context, **settings)
    assert _same(simulate(diagram, initial_state=STARTS[0], context=context, **settings), fresh)
    scene_graph = diagram.GetSubsystemByName("scene_graph")
    scene_context = scene_graph.GetMyMutableContextFromRoot(context)

    def geometries():
        return scene_graph.get_query_output_port().Eval(scene_context).inspector()

    first = geometries().GetAllGeometryIds()[0]
    source = next(s for s in geometries().GetAllSourceIds()
                  if geometries().BelongsToSource(first, s))
    count = len(geometries().GetAllGeometryIds())
    scene_graph.RemoveGeometry(context=scene_context, source_id=source, geometry_id=first)
    start_simulator(diagram, initial_state=STARTS[0], context=context)
    assert len(geometries().GetAllGeometryIds()) == count - 1


def test_a_runs_error_is_not_hidden_by_a_batch_hook_failing_on_its_release():
    """The runs end with every batch entry point called with Contexts None; a hook that
    fails there does not replace the error that ended the runs."""
    from pydrake.systems.framework import DiagramBuilder, LeafSystem
    from reachwatch.diagrams.closed_loop import export_loop_ports

    class Batched(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclareContinuousState(1)
            self.DeclareVectorOutputPort("state", 1, lambda c, o: o.SetFromVector(
                c.get_continuous_state_vector().CopyToVector()))

        def prepare_batch(self, pairs):
            for _, context in pairs:
                context.get_time()            # a hook written without the None case

    def loop():
        builder = DiagramBuilder()
        plant = builder.AddNamedSystem("plant", Batched())
        export_loop_ports(builder, state=plant.GetOutputPort("state"))
        return builder.Build()

    def broken_rule(states):
        raise RuntimeError("the failure rule broke")
    with pytest.raises(RuntimeError, match="the failure rule broke"):
        simulate_lockstep(loop_copies(loop, 2), initial_states=[[0.0], [1.0]], duration=0.2,
                          period=0.05, failed=broken_rule)
