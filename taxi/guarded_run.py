"""The showcase run of the guarded loop: the controller alone and guarded from one start,
with a plot, the trajectories and a Meshcat replay."""

import copy
from pathlib import Path

import numpy as np

from reachwatch.diagrams import (Scenario, initial_state_vector, make_closed_loop_diagram,
                                 make_guarded_diagram, simulate)
from reachwatch.diagrams.scenario import InitialState
from reachwatch.diagrams.plots import plot_guarded_run
from reachwatch.diagrams.replay import meshcat_replay_html
from reachwatch.systems.files import atomic_write_bytes

from .dynamics import OffRunway


def starting_at(scenario: Scenario, start) -> Scenario:
    """A copy of ``scenario`` starting at ``start`` ([px m, py m, theta rad])."""
    scenario = copy.deepcopy(scenario)
    scenario.initial_state = InitialState(px=float(start[0]), py=float(start[1]),
                                          theta_deg=float(np.rad2deg(start[2])))
    return scenario


def simulate_guarded(scenario: Scenario, out: Path, *, meshcat_html=True):
    """Nominal and guarded runs from the scenario's start; Fig.-6 plot, trajectories
    (.npz) and a standalone Meshcat replay (.html) of the guarded run. The replay is
    recorded after both runs, by a Meshcat server that is closed once the HTML is
    written (`meshcat_replay_html`)."""
    x0 = initial_state_vector(scenario.initial_state)
    B = scenario.environment.half_width
    if not scenario.monitor.detector:
        raise ValueError("monitor.detector: the guarded loop needs a detector checkpoint")
    diagrams = make_closed_loop_diagram(scenario), make_guarded_diagram(scenario)  # inputs load
    nominal, guarded = (simulate(d, initial_state=x0, duration=scenario.duration,
                                 period=scenario.controller.period, failed=OffRunway(B))
                        for d in diagrams)
    fallback = scenario.monitor.fallback.name
    name = f"{scenario.environment.name}_{fallback.replace('+', '_')}"
    paths = [plot_guarded_run(nominal, guarded, half_width=B, path=out / f"guarded_{name}.png",
                              title=f"{scenario.environment.name}: alone "
                                    f"{'fails' if nominal.failed else 'stays on'}; guarded "
                                    f"({fallback}) "
                                    f"{'fails' if guarded.failed else 'stays on'}"
                                    f"{' (stopped)' if guarded.speed.ravel()[-1] <= 0 else ''}")]
    np.savez(out / f"guarded_{name}.npz", nominal_state=nominal.state, state=guarded.state,
             speed=guarded.speed, anomaly=guarded.anomaly, time=guarded.time)
    paths.append(out / f"guarded_{name}.npz")
    if meshcat_html:
        html = meshcat_replay_html(scenario, guarded.time, guarded.state)
        paths.append(atomic_write_bytes(out / f"guarded_{name}.html", html.encode()))
    return nominal, guarded, paths
