"""A slow user diagram for fault-injection tests (importable by spawned sweep workers),
and a driver script that sweeps it."""

import sys
import time

from pydrake.systems.framework import DiagramBuilder, LeafSystem

SECONDS_PER_STATE = 0.01


class SlowController(LeafSystem):
    """Three continuous states; output ``u`` = their sum, computed slowly."""

    def __init__(self):
        super().__init__()
        self.DeclareContinuousState(3)
        self.DeclareVectorOutputPort("u", 1, self._calc)

    def _calc(self, context, output):
        time.sleep(SECONDS_PER_STATE)
        output.SetFromVector([context.get_continuous_state_vector().CopyToVector().sum()])


def slow_factory():
    builder = DiagramBuilder()
    builder.AddNamedSystem("plant", SlowController())
    return builder.Build()


def main(cache_dir):
    from reachwatch.reach import Grid, Probe, sweep
    grid = Grid(lo=[0, 0, 0], hi=[1, 1, 1], shape=[20, 20, 20])
    sweep(slow_factory, grid, key="slow", cache_dir=cache_dir, chunk_size=20, progress=False,
          probe=Probe(plant="plant", control_port="plant.u", extra_ports=()))


if __name__ == "__main__":
    main(sys.argv[1])
