"""Frames/s of the wing camera's colour port (reused Context, random states), beside
the raw `RenderEngineVtk` rate (`QueryObject.RenderColorImage`, no systems framework)
measured in the same run on the same scene.

    python benchmarks/render.py [--frames N] [--environment KMWH]
"""

import argparse
import time

import numpy as np
from pydrake.geometry import ColorRenderCamera, RenderCameraCore, ClippingRange
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.sensors import CameraInfo

from reachwatch.diagrams import StateRenderer
from reachwatch.systems import CameraConfig, Environment


def random_states(n, rng):
    return np.column_stack([rng.uniform(-11, 11, n), rng.uniform(100, 250, n),
                            np.deg2rad(rng.uniform(-28, 28, n))])


def port_fps(renderer, states):
    renderer.render(states[0])                                   # warm-up
    start = time.perf_counter()
    for x in states:
        renderer.render(x)
    return len(states) / (time.perf_counter() - start)


def raw_fps(renderer, states, config):
    world = renderer.world
    context = renderer.diagram.CreateDefaultContext()
    query = world.scene_graph.get_query_output_port().Eval(
        world.scene_graph.GetMyContextFromRoot(context))
    core = RenderCameraCore("vtk", CameraInfo(config.width, config.height, config.fov_y_rad),
                            ClippingRange(config.near, config.far), RigidTransform())
    camera = ColorRenderCamera(core, False)
    world_frame = world.scene_graph.world_frame_id()
    X_BC = config.X_BC()
    poses = []
    for px, py, theta in states:
        poses.append(RigidTransform(RotationMatrix.MakeZRotation(theta), [py, px, 0]) @ X_BC)
    query.RenderColorImage(camera, world_frame, poses[0])       # warm-up
    start = time.perf_counter()
    for X_WC in poses:
        query.RenderColorImage(camera, world_frame, X_WC)
    return len(states) / (time.perf_counter() - start)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--environment", default="KMWH")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    states = random_states(args.frames, np.random.default_rng(args.seed))
    print(f"render benchmark: {args.environment} 9h clear, {args.frames} random states, best of 3")
    print(f"{'HxW':>8} {'port fps':>9} {'raw fps':>9} {'port/raw':>9}")
    for height, width in [(64, 128), (200, 360)]:
        config = CameraConfig(width=width, height=height)
        renderer = StateRenderer(environment=Environment(args.environment, 9.0, "clear"),
                                 camera=config)
        raw = port = 0.0
        for _ in range(3):      # alternate, keep the best of 3 of each
            raw = max(raw, raw_fps(renderer, states, config))
            port = max(port, port_fps(renderer, states))
        print(f"{height}x{width:<4} {port:9.1f} {raw:9.1f} {port / raw:9.2f}")


if __name__ == "__main__":
    main()
