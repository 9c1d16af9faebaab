"""The cart on a track (cart.py) as an application of ``reachwatch run``: a plant of
your own, with its own scene, camera and controller, studied through the public
`Application` interface alone.

    reachwatch run --scenario examples/cart/run.yaml --out out/cart

(from the repository root: the run file's paths are relative to the working
directory). This file's folder is importable while it loads, so it imports the cart
from cart.py beside it, and an edit to either file re-keys the run.

What an application says, method by method: the loop (`loop_diagram`, `probe`), the
plant for the solver (`dynamics`: its ``target`` > 0 is the safe set), the failure rule
(`failed`), the box states are labelled and checked on (`grid`), where starts are
drawn (`starts`), how images are made (`renderer`) and how the state space is drawn
(`plot_slices`). The real-loop check uses the generic `real_outcomes` (the cart's loop,
judged by `failed` at every integrator step), and the monitor study (``monitor: {kind:
history}``) the generic `recorded_runs` and `missions`, which read the loop's camera
(`camera_port`) and the controller's steering (`probe`'s control port). The guard stage
rolls the fallbacks out in the guarded sweep's tables by the generic
`fallback_rollouts` (the cart's dynamics take the speed the fallback sets), checks
them in the cart's real loop (the generic `missions`), fits the detector's variation
between nodes on real runs (the generic `real_score_noise`) and shows one start alone
and guarded (the generic `simulate_guarded`, drawn against time). There is no ensemble
baseline (set ``ensemble.seeds: []``)."""

import matplotlib.pyplot as plt
import numpy as np
import torch
from pydrake.systems.framework import DiagramBuilder

from reachwatch.diagrams import DETECTOR, render_at_states
from reachwatch.diagrams.plots import save_figure
from reachwatch.reach import Dynamics, Grid, Probe
from reachwatch.reach.application import Application
from reachwatch.taxi.application import RunwayEnvironments

from cart import HALF_WIDTH, WHEELBASE, add_cart_world, make_cart_loop    # beside it

#: The headings the grid spans (rad either side of the track's direction).
MAX_HEADING = np.deg2rad(40.0)


class CartDynamics(Dynamics):
    """The cart for the solver, at the controller's speed: safe while ``|y| < HALF_WIDTH``."""
    state_dim, control_dim = 2, 1

    def __init__(self, speed):
        self.speed = speed

    def vector_field(self, x, u, speed=None):
        """``speed`` (m/s per state) overrides the controller's: the guard's rollouts
        drive the cart at the speed its fallback sets."""
        v = self.speed if speed is None else speed
        return torch.stack([v * torch.sin(x[..., 1]), v / WHEELBASE * torch.tan(u[..., 0])],
                           dim=-1)

    def control_limits(self):
        """The steering within +-pi/2 rad, where tan turns back."""
        return [-np.pi / 2], [np.pi / 2]

    def target(self, x):
        return HALF_WIDTH - x[..., 0].abs()

    def safe_box(self):
        return [-HALF_WIDTH, -float("inf")], [HALF_WIDTH, float("inf")]


class CartRenderer:
    """The cart's camera alone (no controller): ``render([y, theta])`` is its image."""

    def __init__(self, scenario):
        builder = DiagramBuilder()
        add_cart_world(builder, environment=scenario.environment, camera=scenario.camera)
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()

    def render(self, state):
        return render_at_states(self.diagram, plant="cart", image_port="camera.color_image",
                                states=np.asarray(state, float)[None], context=self.context)[0]


class CartApplication(RunwayEnvironments, Application):
    """Its environments are the taxi's (`RunwayEnvironments`): a runway's hour and sky
    light the track, the runway sets the sun's bearing."""
    name = "cart"
    axes = ("y", "theta")
    axis_units = ("m", "rad")
    open_axes = (1,)        # a run may turn past the grid's headings without failing
    # the report's words for the cart (where the taxi's say "left the runway", ...)
    failure_words = "reached a rail"
    fail_words = "reach a rail"
    box_words = "the track (y from rail to rail, |theta| <= 40 deg)"
    camera_port = "camera.color_image"      # what the monitor study records

    def loop_diagram(self, scenario, *, guarded=False):
        return make_cart_loop(scenario, scenario.monitor if guarded else None)

    def probe(self, scenario, *, guarded=False):
        return Probe(plant="cart", control_port="rail_follower.steering_angle",
                     extra_ports=(f"{DETECTOR}.score",) if guarded else ())

    def dynamics(self, scenario):
        return CartDynamics(scenario.controller.speed)

    def failed(self, scenario, states):
        return np.abs(np.asarray(states, float)[:, 0]) >= HALF_WIDTH

    def grid(self, scenario, shape, **widen):
        """y from rail to rail, theta +-40 deg (the run file's widening is the taxi's)."""
        return Grid(lo=[-HALF_WIDTH, -MAX_HEADING], hi=[HALF_WIDTH, MAX_HEADING],
                    shape=shape, names=self.axes)

    def starts(self, scenario, box, count, seed):
        """Uniform in the box, between the rails (a start on a rail has already failed)."""
        lo, hi = (box.lo, box.hi) if hasattr(box, "lo") else box
        lo, hi = np.array(lo, float), np.array(hi, float)
        lo[0], hi[0] = max(lo[0], -HALF_WIDTH), min(hi[0], HALF_WIDTH)
        return lo + np.random.default_rng(seed).uniform(size=(count, 2)) * (hi - lo)

    def renderer(self, scenario):
        return CartRenderer(scenario)

    def plot_slices(self, value_functions, *, scenario, at, path, title="", points=None):
        """The whole (y, theta) plane (``at`` is unused: there is no third axis): the
        BRT grey, the rails dashed."""
        items = list(value_functions.items())
        fig, axes = plt.subplots(1, len(items), figsize=(4.0 * len(items), 3.6), squeeze=False)
        for ax, (label, vf) in zip(axes[0], items):
            y, theta = vf.grid.axes[0], np.rad2deg(vf.grid.axes[1])
            v = vf.values.T
            if v.min() <= 0:
                ax.contourf(y, theta, v, levels=[v.min() - 1, 0.0], colors=["0.7"])
            for s in (-1, 1):
                ax.axvline(s * HALF_WIDTH, color="tab:red", ls="--", lw=1)
            for name, states, style in points or []:
                states = np.asarray(states).reshape(-1, 2)
                ax.plot(states[:, 0], np.rad2deg(states[:, 1]), style, ms=3, label=name)
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("y (m)")
            ax.set_ylabel("theta (deg)")
        if title:
            fig.suptitle(title, fontsize=10)
        fig.tight_layout()
        return save_figure(fig, path)
