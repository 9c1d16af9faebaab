"""Honest measurements of the controller under test: estimation error per
environment, and closed-loop failure rates from random starts (real Drake loop)."""

import copy
import dataclasses as dc

import numpy as np

from reachwatch.diagrams import (StateRenderer, load_taxinet, make_closed_loop_diagram,
                                 simulate)
from reachwatch.systems import CameraConfig, TaxiNet

from .dynamics import OffRunway
from .taxinet_data import render_states, sample_states, targets


def paper_box(half_width: float) -> dict:
    """The paper grid's bounds: px in [-(B+1), B+1] m, py in [100, 250] m, theta in
    [-28, 28] deg."""
    return {"px": (-(half_width + 1.0), half_width + 1.0), "py": (100.0, 250.0),
            "theta_deg": (-28.0, 28.0)}


@dc.dataclass
class EnvironmentReport:
    environment: str
    px_mean_m: float
    px_p95_m: float
    theta_mean_deg: float
    theta_p95_deg: float
    failure_rate: float = float("nan")
    starts: int = 0


def estimation_errors_in(environment, *, checkpoint, camera: CameraConfig, samples: int,
                         seed: int) -> dict:
    """TaxiNet's absolute errors on ``samples`` uniform states of ``environment``."""
    model, preprocess_config, _ = load_taxinet(checkpoint)
    taxinet = TaxiNet(model=model, preprocess_config=preprocess_config)
    rng = np.random.default_rng(seed)
    states = sample_states(samples, rng, paper_box(environment.half_width))
    inside = ~OffRunway(environment.half_width)(states)
    images = render_states(StateRenderer(environment=environment, camera=camera), states)
    err = np.abs(taxinet.estimate(images) - targets(states))[inside]
    return {"px_mean_m": float(err[:, 0].mean()), "px_p95_m": float(np.percentile(err[:, 0], 95)),
            "theta_mean_deg": float(err[:, 1].mean()),
            "theta_p95_deg": float(np.percentile(err[:, 1], 95))}


def closed_loop_failure_rate(scenario, *, starts: int, seed: int, duration: float = 8.0,
                             progress=None):
    """Fraction of ``starts`` uniform paper-box start states from which the real
    closed loop leaves the runway within ``duration`` s; also returns the states and
    the per-start outcome."""
    B = scenario.environment.half_width
    off = OffRunway(B)
    rng = np.random.default_rng(seed)
    states = sample_states(starts, rng, paper_box(B))
    diagram = make_closed_loop_diagram(scenario)
    context = diagram.CreateDefaultContext()
    failed = []
    gone = off(states)
    for x, at_start in zip((progress(states) if progress else states), gone):
        if at_start:
            failed.append(True)
            continue
        failed.append(simulate(diagram, initial_state=x, duration=duration, failed=off,
                               period=scenario.controller.period,
                               context=context).failed)
    failed = np.array(failed)
    return float(failed.mean()), states, failed


def evaluate_taxinet(base_scenario, environments, *, checkpoint, samples=200, starts=100,
                     seed=0, duration=8.0, progress=None):
    """One `EnvironmentReport` per environment (``starts = 0`` skips the closed loop)."""
    reports = []
    for env in environments:
        errors = estimation_errors_in(env, checkpoint=checkpoint,
                                      camera=base_scenario.camera, samples=samples, seed=seed)
        report = EnvironmentReport(environment=env.name, **errors)
        if starts:
            scenario = copy.deepcopy(base_scenario)
            scenario.environment = env
            scenario.controller.checkpoint = str(checkpoint)
            report.failure_rate, _, _ = closed_loop_failure_rate(
                scenario, starts=starts, seed=seed, duration=duration, progress=progress)
            report.starts = starts
        reports.append(report)
    return reports


def format_reports(reports) -> str:
    """A Markdown table of `EnvironmentReport` rows."""
    lines = ["| environment | px err mean (m) | px err p95 (m) | theta err mean (deg) | "
             "theta err p95 (deg) | closed-loop failure rate |",
             "|---|---|---|---|---|---|"]
    for r in reports:
        rate = f"{100 * r.failure_rate:.0f}% of {r.starts}" if r.starts else "-"
        lines.append(f"| {r.environment} | {r.px_mean_m:.2f} | {r.px_p95_m:.2f} | "
                     f"{r.theta_mean_deg:.2f} | {r.theta_p95_deg:.2f} | {rate} |")
    return "\n".join(lines)

