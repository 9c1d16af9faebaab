"""The taxi's guarded loop rolled out in its swept tables (`reach.guarded_rollouts`):
the hooks the generic rollouts take from the taxi's application, namely the
P-controller the fallback steers with, the true ``[px m, theta deg]`` of a state (the
``oracle`` steering) and the aircraft's kinematics carrying an estimate forward (the
``dead_reckoning`` steering)."""

import functools

import numpy as np

from reachwatch.diagrams import DETECTOR
from reachwatch.reach import guarded_rollouts as generic
from reachwatch.reach.liveness import UNGUARDED
from reachwatch.systems import WHEELBASE_M, ProportionalController, propagate_estimate

SCORE_PORT = f"{DETECTOR}.score"

__all__ = ["SCORE_PORT", "UNGUARDED", "carry_estimate", "taxi_fallback_rollouts",
           "taxi_guarded_rollouts", "p_controller_policy", "true_estimate"]


def true_estimate(states) -> np.ndarray:
    """What TaxiNet estimates, at its true value: ``[px m, theta deg]`` of ``(n, 3)``
    states."""
    states = np.asarray(states, float)
    return np.stack([states[:, 0], np.rad2deg(states[:, 2])], axis=-1)


def taxi_guarded_rollouts(grid, dynamics, steering_table, score_table=None, **settings):
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


#: An estimate ``[px m, theta deg]`` carried forward by the aircraft's kinematics over a
#: period (the ``dead_reckoning`` steering): `systems.propagate_estimate` at the taxi
#: dynamics' wheelbase.
carry_estimate = functools.partial(propagate_estimate, wheelbase=float(WHEELBASE_M))


def taxi_fallback_rollouts(scenario, grid, tables, horizon, fallbacks, **settings) -> dict:
    """`Application.fallback_rollouts` of the taxi (`TaxiApplication`) as a function:
    the generic rollouts of its guarded sweep (`sweep_guarded`) in ``scenario`` with its
    dynamics, ports, the P-controller the fallback steers with (`p_controller_policy`),
    `true_estimate` and `carry_estimate`. ``settings``: ``threshold``, ``starts``,
    ``mission_limit``, ``scores``, ``alone``, ``score_noise``, ``seed``, as there."""
    from .application import TaxiApplication
    return TaxiApplication().fallback_rollouts(scenario, grid, tables, horizon, fallbacks,
                                               **settings)
