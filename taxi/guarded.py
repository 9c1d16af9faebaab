"""The taxi's guarded loop rolled out in its swept tables (`reach.guarded_rollouts`):
what the generic rollouts need from the taxi, namely its dynamics, its ports, the
P-controller the fallback steers with, the true ``[px m, theta deg]`` of a state (the
``oracle`` steering) and the aircraft's kinematics carrying an estimate forward (the
``dead_reckoning`` steering)."""

import functools

import numpy as np

from reachwatch.diagrams import CONTROL_PORT, DETECTOR, ESTIMATE_PORT
from reachwatch.reach import guarded_rollouts as generic
from reachwatch.reach.liveness import UNGUARDED
from reachwatch.systems import ProportionalController, propagate_estimate

from .dynamics import dynamics_for

SCORE_PORT = f"{DETECTOR}.score"

__all__ = ["SCORE_PORT", "UNGUARDED", "fallback_rollouts", "guarded_rollouts",
           "p_controller_policy", "true_estimate"]


def true_estimate(states) -> np.ndarray:
    """What TaxiNet estimates, at its true value: ``[px m, theta deg]`` of ``(n, 3)``
    states."""
    states = np.asarray(states, float)
    return np.stack([states[:, 0], np.rad2deg(states[:, 2])], axis=-1)


def guarded_rollouts(grid, dynamics, steering_table, score_table=None, **settings):
    """`reach.guarded_rollouts.guarded_rollouts` of the taxi: the ``oracle`` steering
    reads `true_estimate`, and ``dead_reckoning`` carries an estimate forward by the
    aircraft's kinematics (`systems.propagate_estimate` at ``dynamics.wheelbase``)."""
    return generic.guarded_rollouts(
        grid, dynamics, steering_table, score_table, truth=true_estimate,
        carry=functools.partial(propagate_estimate, wheelbase=dynamics.wheelbase), **settings)


def p_controller_policy(controller):
    """The taxi fallback's policy: the P-controller of ``controller`` (a
    `ControllerConfig`'s gains) on ``(n, 2)`` estimates ``[px m, theta deg]``, in rad."""
    p = ProportionalController(px_gain=controller.px_gain, theta_gain=controller.theta_gain)
    return lambda estimate: np.deg2rad(p.steering_deg(estimate))


def fallback_rollouts(scenario, grid, tables, horizon, fallbacks, **settings) -> dict:
    """`reach.guarded_rollouts.fallback_rollouts` of the taxi's guarded sweep
    (`sweep_guarded`) in ``scenario``: its dynamics, control period, monitor, ports,
    P-controller policy and the taxi's `guarded_rollouts` hooks. ``settings``:
    ``threshold``, ``starts``, ``mission_limit``, ``scores``, ``alone``, ``score_noise``,
    ``seed``, as there."""
    dynamics = dynamics_for(scenario)
    return generic.fallback_rollouts(
        tables, grid, horizon, fallbacks, dynamics=dynamics,
        period=scenario.controller.period, monitor=scenario.monitor,
        control_port=CONTROL_PORT, score_port=SCORE_PORT, estimate_port=ESTIMATE_PORT,
        policy=p_controller_policy(scenario.controller), truth=true_estimate,
        carry=functools.partial(propagate_estimate, wheelbase=dynamics.wheelbase), **settings)
