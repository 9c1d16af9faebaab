"""The taxi as an `Application` (`TAXI_APPLICATION`): the closed loop ``reachwatch run``
studies when a run file names none. Any
controller steers the taxiing aircraft (`reachwatch.systems.TaxiPlant`) on the runway
of ``scenario.environment``, seen by the wing camera; it fails when it leaves the
runway (``|px| >= half_width``). Its sweeps and datasets are the taxi's own modules
(they keep the cache keys they had before applications); its real-loop runs (the
check, path labels, missions, recorded runs and the detector's score along runs) are
the generic ones of `reachwatch.reach.loop_runs`."""

import dataclasses as dc

import numpy as np

from reachwatch.diagrams import (StateRenderer, initial_state_vector, load_taxinet,
                                 make_closed_loop_diagram, make_guarded_diagram)
from reachwatch.reach.application import Application
from reachwatch.systems import Environment, RandomEnvironments, TaxiNet
from reachwatch.systems.scene import GROUND_X

from . import fidelity, guarded, guarded_run, plots, sweeps
from .dynamics import OffRunway, dynamics_for
from .grid import AXES, paper_grid
from .taxinet_train import TaxiNetTrainConfig, train_taxinet_ensemble


#: The string the taxi is loaded by (`reachwatch.reach.application.load_application`).
TAXI_APPLICATION = "reachwatch.taxi.application:TaxiApplication"

#: Where the guard stage times the taxi's loops: near the centreline, [px m, py m,
#: theta rad] (runs that stay on the runway for the whole timing).
NEAR_CENTRELINE = np.array([[0.5 * (k % 3), 110.0 + 10.0 * k, np.deg2rad(2.0 * (k % 3))]
                            for k in range(5)])


class RunwayEnvironments:
    """A run file's environments as the taxi's: a runway (the catalog's or the user's),
    hour and sky (`Environment`), random ones drawn as `RandomEnvironments`, with the
    taxi's defaults. Mixed in before `Application` by any application lit and keyed by
    runways (the taxi, the speed car, the cart)."""

    environment_type = Environment
    random_environments_type = RandomEnvironments

    def default_environment(self, role):
        # the incremental stage's held-out environment: KMWH at dusk
        return Environment("KMWH", 17.0, "clear") if role == "incremental" else Environment()

    def default_random_environments(self, role):
        # the monitor study's family is drawn from seed 11; the others draw none
        return RandomEnvironments(seed=11) if role == "monitor" else RandomEnvironments()

    def same_environment(self, a, b):
        # one name, one runway and hour (a runway_spec that spells out a catalog runway
        # is that runway)
        return (a.spec(), a.hour) == (b.spec(), b.hour)

    def environment_content(self, env):
        # the runway spelled out, its name blanked: names change no pixel (an
        # environment of another type, as a subclass may have: as it is)
        if not isinstance(env, Environment):
            return repr(env)
        return repr(dc.replace(env, runway="", runway_spec=dc.replace(env.spec(), name="")))


class TaxiApplication(RunwayEnvironments, Application):
    """The TaxiNet paper's taxiing aircraft (state [px m, py m, theta rad])."""

    name = "taxi"
    spec = TAXI_APPLICATION
    axes = AXES
    axis_units = ("m", "m", "rad")
    open_axes = fidelity.OPEN_AXES
    estimated_state = (0, 2)            # TaxiNet's cross-track error and heading
    heading_axis = 2

    start_word = "on-runway"
    failure_words = "left the runway"
    fail_words = "leave the runway"
    starts_note = "|px| < B; starts already off the runway agree with any BRT"
    box_words = "the paper's box"
    slice_words = "slices at py = {at:g} m"
    reads_keys = ("solved_theta_deg", "solved_py_max", "slice_py")

    def loop_diagram(self, scenario, *, guarded=False):
        return (make_guarded_diagram if guarded else make_closed_loop_diagram)(scenario)

    def probe(self, scenario, *, guarded=False):
        return sweeps.taxi_probe(scenario, guarded=guarded)

    @property
    def own_loop(self) -> bool:
        """Whether the loop is the taxi's own (a subclass may build another, and then
        gets the generic sweeps, renderer, start, run and showcase)."""
        return type(self).loop_diagram is TaxiApplication.loop_diagram

    def loop_factory(self, scenario, *, guarded=False):
        # the taxi's own factory: sweeps keep the keys they had before applications
        return (sweeps._factory(scenario, guarded) if self.own_loop else
                super().loop_factory(scenario, guarded=guarded))

    def resolved(self, scenario):
        return sweeps.resolved(scenario)

    def dynamics(self, scenario):
        return dynamics_for(scenario)

    def failed(self, scenario, states):
        return OffRunway(scenario.environment.half_width)(states)

    def grid(self, scenario, shape, *, theta_deg=28.0, py_max=250.0):
        env = scenario.environment
        end = min(env.spec().length, GROUND_X[1]) if isinstance(env, Environment) else np.inf
        if float(py_max) >= end:
            raise ValueError(f"solved_py_max {float(py_max):g} m lies past the end of "
                             f"{env.name}'s runway as rendered ({end:g} m: its length, or the "
                             f"scene's ground): the camera there sees no runway; lower "
                             f"solved_py_max, or lengthen the runway")
        return paper_grid(env.half_width, tuple(shape), theta_deg=float(theta_deg),
                          py_max=float(py_max))

    def box_exit_share(self, scenario, horizon, *, theta_deg=28.0, py_max=250.0):
        """The share of the check starts (uniform in py over the paper's box) that begin
        closer to the solved box's far end (``py_max``) than the loop travels within
        ``horizon`` at nominal speed, heading at most the paper's 28 deg: those that do
        not fail first leave the box through py."""
        paper = paper_grid(1.0, (2, 2, 2))
        lo, hi = float(paper.lo[1]), float(paper.hi[1])
        speed = scenario.controller.speed
        share = float(np.clip((hi + speed * horizon * np.cos(paper.hi[2]) - py_max) / (hi - lo),
                              0.0, 1.0))
        needed = hi + speed * horizon      # no start can run past it within the horizon
        return {"share": share,
                "problem": f"solved_py_max {py_max:g} m leaves no room downtrack: about "
                           f"{100 * share:.0f} % of the fidelity check's starts would run past "
                           f"it within the {horizon:g} s horizon at {speed:g} m/s",
                "fix": f"Set solved_py_max: {needed:g} (the paper box's end plus the "
                       f"horizon's travel)"}

    def timing_starts(self, scenario, grid):
        return NEAR_CENTRELINE

    def starts(self, scenario, box, count, seed):
        return fidelity.on_runway_starts(box, count, seed,
                                         half_width=scenario.environment.half_width)

    def renderer(self, scenario):
        if not self.own_loop:
            return super().renderer(scenario)
        return StateRenderer(environment=scenario.environment, camera=scenario.camera,
                             shadows=scenario.shadows)   # as the loop renders

    def view_state(self, scenario):
        return np.array([0.0, 150.0, 0.0])      # where the environments figure looked

    def start_state(self, scenario):
        if not self.own_loop:
            return super().start_state(scenario)
        return initial_state_vector(scenario.initial_state)

    def ensemble_estimator(self, checkpoint):
        model, preprocess, _ = load_taxinet(checkpoint)
        return TaxiNet(model=model, preprocess_config=preprocess).estimate

    def ensemble_config(self, scenario, *, samples, epochs):
        return TaxiNetTrainConfig(camera=scenario.camera, samples=samples, epochs=epochs)

    def train_ensemble(self, config, paths, seeds, *, progress=None):
        train_taxinet_ensemble(config, paths, seeds, progress=progress)

    def plot_slices(self, value_functions, *, scenario, at, path, title="", points=None):
        return plots.plot_brt_slices(value_functions, py=at, path=path, title=title,
                                     points=points, half_width=scenario.environment.half_width)

    def plot_failure_sets(self, failures, grid, horizon, *, scenario, at, path, title=""):
        return plots.plot_failure_sets(failures, grid, horizon, py=at, path=path, title=title,
                                       half_width=scenario.environment.half_width)

    # --- the guard (the guard stage, ``reachwatch guard``) -----------------------------
    # the generic table rollouts (`Application.fallback_rollouts`) with the taxi's hooks
    true_estimate = staticmethod(guarded.true_estimate)
    estimate_scale = (10.0, 30.0)          # TaxiNet's output scales (m, deg)
    estimate_columns = ("px_hat_m", "theta_hat_deg")
    carry_estimate = staticmethod(guarded.carry_estimate)

    def fallback_policy(self, scenario):
        return guarded.p_controller_policy(scenario.controller)

    def travelled_along(self, scenario, path):
        """The distance on the ground (px, py) up to each state of ``path``."""
        path = np.asarray(path, float)
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path[:, :2], axis=0),
                                                               axis=1))])

    def simulate_guarded(self, scenario, start, folder, *, meshcat_html=True):
        if not self.own_loop:
            return super().simulate_guarded(scenario, start, folder, meshcat_html=meshcat_html)
        if not np.array_equal(start, initial_state_vector(scenario.initial_state)):
            scenario = guarded_run.starting_at(scenario, start)
        return guarded_run.simulate_guarded(scenario, folder, meshcat_html=meshcat_html)

    # --- incremental training (the incremental stage) ----------------------------------
    controller_words = "TaxiNet"
    fine_tuned_name = "taxinet"

    def check_incremental(self, scenario):
        if scenario.controller.factory:
            raise ValueError("incremental.enabled: incremental training fine-tunes TaxiNet, "
                             "and scenario.controller.factory names another controller; set "
                             "incremental: {enabled: false}")

    def fine_tuned_metadata(self, path):
        return load_taxinet(path)[2]

    def plot_runs(self, runs, *, scenario, path, title=""):
        from reachwatch.diagrams.plots import plot_runway_top_view
        return plot_runway_top_view(runs, half_width=scenario.environment.half_width,
                                    path=path, title=title)

    def fine_tune(self, scenario, checkpoint, datasets, config, path, *, progress=None):
        """TaxiNet fine-tuned on the mined anomalies (`taxi.incremental`)."""
        from .incremental import fine_tune_taxinet, mine_anomalies
        mined = mine_anomalies(datasets, config.anomalies, np.random.default_rng(config.seed))
        return fine_tune_taxinet(checkpoint, mined, config, scenario.camera, path,
                                 progress=progress)
