"""The speed car (speed_car.py) as an application of ``reachwatch run``: a 4-state
plant ([px m, py m, theta rad, v m/s], its speed lagging the command) under the wing
camera on a catalog runway, steered by the run file's controller. It fails where it
leaves the runway (|px| >= half-width), judged at every integrator step in its real
loop (the generic one). Its dynamics take the speed command a fallback sets (the car's
speed lags it), so the guard stage rolls the speed fallbacks out in the guarded
sweep's tables and checks them in the car's real loop; like the real loop's, the
guard's distances and stops count the commanded speed.

    reachwatch run --scenario examples/speed_car/run.yaml --out out/speed_car

(from the repository root: the run file's path to this file is relative to the
working directory). This file's folder is importable while it loads, so it imports
its plant from speed_car.py beside it, and an edit to either file re-keys the run."""

import matplotlib.pyplot as plt
import numpy as np

from reachwatch.diagrams import DETECTOR, MonitorConfig
from reachwatch.diagrams.plots import save_figure
from reachwatch.reach import Probe
from reachwatch.reach.application import Application
from reachwatch.taxi.application import RunwayEnvironments

from speed_car import PROBE, CarConfig, LagCarDynamics, car_grid, make_car_loop  # beside it

#: The speed's lag behind its command (s).
TIME_CONSTANT = 1.0


class SpeedCar(RunwayEnvironments, Application):
    """On the taxi's runways, with its environments (`RunwayEnvironments`)."""
    name = "speed_car"
    reads_keys = ("slice_py",)      # its slices' py; its box is its own (no widening)
    axes = ("px", "py", "theta", "v")
    open_axes = (1, 2, 3)

    def loop_diagram(self, scenario, *, guarded=False):
        return make_car_loop(CarConfig(
            environment=scenario.environment, controller=scenario.controller,
            time_constant=TIME_CONSTANT,
            monitor=scenario.monitor if guarded else MonitorConfig()))

    def probe(self, scenario, *, guarded=False):
        return Probe(plant=PROBE.plant, control_port=PROBE.control_port,
                     extra_ports=(f"{DETECTOR}.score",) if guarded else ())

    def dynamics(self, scenario):
        return LagCarDynamics(half_width=scenario.environment.half_width,
                              speed=scenario.controller.speed, time_constant=TIME_CONSTANT)

    def stopping_time(self, scenario, deceleration):
        """From the box's top speed (6 m/s, as fast as a start may go), the speed
        command braked at ``deceleration``, and the speed one time constant behind it."""
        return max(6.0, scenario.controller.speed) / deceleration + TIME_CONSTANT

    def grid(self, scenario, shape, **widen):
        """px across the runway, py 100-250 m, theta +-28 deg, v 0-6 m/s (the run file's
        widening of the taxi's box does not apply)."""
        return car_grid(scenario.environment.half_width, tuple(shape))

    def plot_slices(self, value_functions, *, scenario, at, path, title="", points=None):
        """theta (deg) against px (m) at the py nearest ``at`` and the speed nearest the
        nominal one: the BRT grey, the runway's edges dashed."""
        items = list(value_functions.items())
        fig, axes = plt.subplots(1, len(items), figsize=(4.2 * len(items), 3.8), squeeze=False)
        B = scenario.environment.half_width
        for ax, (label, vf) in zip(axes[0], items):
            grid = vf.grid
            j = int(np.argmin(np.abs(grid.axes[1] - at)))
            k = int(np.argmin(np.abs(grid.axes[3] - scenario.controller.speed)))
            px, theta = grid.axes[0], np.rad2deg(grid.axes[2])
            v = vf.values[:, j, :, k].T
            if v.min() <= 0:
                ax.contourf(px, theta, v, levels=[v.min() - 1, 0.0], colors=["0.7"])
            for s in (-1, 1):
                ax.axvline(s * B, color="tab:red", ls="--", lw=1)
            for name, states, style in points or []:
                states = np.asarray(states).reshape(-1, 4)
                near = np.abs(states[:, 1] - grid.axes[1][j]) <= max(grid.spacing[1], 10.0)
                ax.plot(states[near, 0], np.rad2deg(states[near, 2]), style, ms=3, label=name)
            ax.set_title(f"{label}: py = {grid.axes[1][j]:.0f} m, v = {grid.axes[3][k]:.1f} m/s",
                         fontsize=9)
            ax.set_xlabel("px (m)")
            ax.set_ylabel("theta (deg)")
        if title:
            fig.suptitle(title, fontsize=10)
        fig.tight_layout()
        return save_figure(fig, path)
