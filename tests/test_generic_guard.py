"""The guard's table rollouts for any plant (`reach.guarded_rollouts`): an application
whose dynamics take a speed gets them from the base `Application`; one whose dynamics
do not is told so in one line, and the guard stage skips it."""

import numpy as np
import pytest
import torch

from reachwatch.diagrams import MonitorConfig, load_scenario
from reachwatch.reach import Dynamics, Grid, Probe
from reachwatch.reach.application import Application
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.reach.guarded_rollouts import guarded_rollouts, takes_speed
from reachwatch.reach.liveness import UNGUARDED
from reachwatch.reach.sweep import SweepTable


class Unicycle(Dynamics):
    """``y' = v sin(theta)``, ``theta' = u``: fails at ``|y| >= 1``."""
    state_dim, control_dim = 2, 1

    def __init__(self, speed=2.0, *, with_speed=True):
        self.speed, self.with_speed = speed, with_speed

    def vector_field(self, x, u, speed=None):
        v = self.speed if speed is None else speed
        return torch.stack([v * torch.sin(x[..., 1]), u[..., 0] + 0 * v], dim=-1)

    def target(self, x):
        return 1.0 - x[..., 0].abs()


class NoSpeed(Dynamics):
    state_dim, control_dim, speed = 2, 1, 2.0

    def vector_field(self, x, u):
        return torch.stack([self.speed * torch.sin(x[..., 1]), u[..., 0]], dim=-1)

    def target(self, x):
        return 1.0 - x[..., 0].abs()


class Toy(Application):
    """An application known only by its dynamics and ports (no loop is built here)."""
    name = "toy"
    score_port = "monitor.score"

    def __init__(self, dynamics):
        self._dynamics = dynamics

    def loop_diagram(self, scenario, *, guarded=False):
        raise AssertionError("the table rollouts build no loop")

    def probe(self, scenario, *, guarded=False):
        return Probe(plant="plant", control_port="steer.u", extra_ports=("monitor.score",))

    def dynamics(self, scenario):
        return self._dynamics

    def grid(self, scenario, shape, **widen):
        return Grid(lo=[-1.0, -1.0], hi=[1.0, 1.0], shape=shape)


def _tables(grid, score):
    """No steering anywhere (the heading holds), the detector's score as given."""
    return SweepTable(grid=grid, tables={"steer.u": np.zeros(grid.shape + (1,)),
                                         "monitor.score": np.reshape(score, grid.shape + (1,))},
                      key="hand-made")


def test_speed_fallbacks_roll_out_for_any_plant_that_takes_a_speed():
    scenario = load_scenario(data="")
    scenario.controller.period = 0.1
    scenario.monitor = MonitorConfig(threshold=0.5, brake_deceleration=4.0)
    toy = Toy(Unicycle())
    grid = toy.grid(scenario, [3, 3])
    starts = np.array([[0.5, 0.5], [0.0, 0.0]])      # heading for the edge; along the middle
    assert toy.rolls_out_fallbacks(scenario)
    never = toy.fallback_rollouts(scenario, grid, _tables(grid, np.zeros(9)), 1.0,
                                  ["brake"], starts=starts)
    always = toy.fallback_rollouts(scenario, grid, _tables(grid, np.ones(9)), 1.0,
                                   ["brake", "slow_down"], starts=starts)
    alone = never[UNGUARDED]
    # alone (and never flagged): 2 m/s for 1 s; y = 0.5 + 2 sin(0.5) t reaches 1 at 0.52 s
    assert alone.failed.tolist() == [True, False] and alone.distance[1] == pytest.approx(2.0)
    assert never["brake"].failed.tolist() == alone.failed.tolist()
    # braking at 4 m/s^2, flagged from the first tick: each tick's speed drops by 0.4
    # m/s before it is applied, so 0.1 s x (1.6 + 1.2 + 0.8 + 0.4) m/s = 0.4 m, and y
    # stays below 0.5 + 0.4 sin(0.5) < 1
    braked = always["brake"]
    assert braked.failed.tolist() == [False, False] and braked.stopped.all()
    assert braked.distance == pytest.approx([0.4, 0.4])
    assert braked.flagged_ticks.tolist() == braked.ticks.tolist() == [10, 10]
    assert always["slow_down"].distance[1] < alone.distance[1]


def test_a_plant_without_a_speed_is_told_in_one_line():
    scenario = load_scenario(data="monitor: {threshold: 0.5}\n")
    toy = Toy(NoSpeed())
    grid = toy.grid(scenario, [3, 3])
    assert takes_speed(Unicycle()) and not takes_speed(NoSpeed())
    assert not toy.rolls_out_fallbacks(scenario)
    with pytest.raises(ValueError, match=r"^NoSpeed cannot be rolled out at the fallback's "
                                         r"speed: give it .*speed=None\) that uses") as e:
        toy.fallback_rollouts(scenario, grid, _tables(grid, np.ones(9)), 1.0, ["brake"])
    assert "\n" not in str(e.value)


def test_steering_fallbacks_need_the_applications_hooks():
    """``oracle`` steers with `Application.fallback_policy` of `true_estimate`; an
    application that defines neither is refused in one line, not rolled out wrong. A
    monitor with neither a checkpoint nor a threshold is refused too."""
    toy = Toy(Unicycle())
    grid = toy.grid(load_scenario(data=""), [3, 3])
    with pytest.raises(ValueError, match="^monitor.threshold: the monitor names no checkpoint"):
        toy.fallback_rollouts(load_scenario(data=""), grid, _tables(grid, np.ones(9)), 1.0,
                              ["brake"])
    scenario = load_scenario(data="monitor: {threshold: 0.5}\n")
    with pytest.raises(ValueError, match="steering 'oracle' needs a policy"):
        toy.fallback_rollouts(scenario, grid, _tables(grid, np.ones(9)), 1.0,
                              ["slow_down+oracle"])
    with pytest.raises(ValueError, match="needs the controller's estimate"):
        toy.fallback_rollouts(scenario, grid, _tables(grid, np.ones(9)), 1.0,
                              ["slow_down+dead_reckoning"])
    toy.fallback_policy = lambda scenario: (lambda estimate: -2.0 * estimate[:, 1])
    toy.true_estimate = lambda states: np.asarray(states, float)
    runs = toy.fallback_rollouts(scenario, grid, _tables(grid, np.ones(9)), 1.0,
                                 ["slow_down+oracle"], starts=np.array([[0.5, 0.5]]))
    assert not runs["slow_down+oracle"].failed[0] and runs[UNGUARDED].failed[0]
    plain = guarded_rollouts(grid, Unicycle(), np.zeros(9), np.ones(9), steering="oracle",
                             policy=lambda e: -2.0 * e[:, 1], truth=lambda x: x,
                             starts=np.array([[0.5, 0.5]]), horizon=1.0, period=0.1)
    assert plain.failed.tolist() == [False]


def test_the_guard_is_checked_before_anything_is_swept():
    """`Application.check_guard`: what the guard stage would ask of an application that
    lacks it is refused in one line naming the run-file key; the taxi has it all."""
    from reachwatch.reach.application import load_application
    scenario = load_scenario(data="controller: {speed: 2.0}\n")    # the toy's dynamics' speed
    toy = Toy(Unicycle())
    toy.check_guard(scenario, ["slow_down", "brake"])
    for strategies, key, hooks in ((["slow_down+oracle"], r"guard.strategies\[0\]",
                                    "fallback_policy and true_estimate"),
                                   (["brake", "slow_down+dead_reckoning"],
                                    r"guard.strategies\[1\]",
                                    "fallback_policy and carry_estimate")):
        with pytest.raises(ValueError, match=rf"^{key}: '.*' needs the application's {hooks}, "
                                             rf"and 'toy' defines none; leave it out$"):
            toy.check_guard(scenario, strategies)
    # the stage is skipped for a plant without a speed, unless it was asked for
    Toy(NoSpeed()).check_guard(scenario, ["slow_down+oracle"])
    with pytest.raises(ValueError, match="^NoSpeed cannot be rolled out"):
        Toy(NoSpeed()).check_guard(scenario, ["brake"], skipped=False)
    load_application(TAXI_APPLICATION).check_guard(scenario, ["slow_down+oracle", "slow_down+dead_reckoning"])


def test_a_run_file_asking_the_cart_for_a_steering_fallback_is_refused(monkeypatch):
    from pathlib import Path
    from reachwatch.pipeline.spec import load_run_spec
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    load_run_spec(data=text)
    with pytest.raises(ValueError, match="guard.strategies\\[1\\]: 'slow_down\\+oracle' needs the "
                                         "application's fallback_policy and true_estimate"):
        load_run_spec(data=text.replace("strategies: [slow_down, brake]",
                                        "strategies: [slow_down, slow_down+oracle]"))


def test_the_cart_without_guard_strategies_runs_the_defaults_it_can(monkeypatch):
    """A run file that leaves ``guard.strategies`` out: the default loses the steering
    fallbacks the application has no hooks for, in one line, before anything is swept
    (it was refused naming ``guard.strategies[2]``, a key the file never wrote)."""
    from pathlib import Path
    from reachwatch.pipeline.run import fit_guard
    from reachwatch.pipeline.spec import load_run_spec
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    spec, said = load_run_spec(data=text.replace("strategies: [slow_down, brake], ", "")), []
    fit_guard(spec, None, said.append)
    assert spec.guard.strategies == ["slow_down", "brake"]
    assert said == ["guard.strategies: the default without slow_down+dead_reckoning (it needs "
                    "the application's fallback_policy and carry_estimate, and 'cart' defines "
                    "none); slow_down+oracle (it needs the application's fallback_policy and "
                    "true_estimate, and 'cart' defines none)"]


def test_an_application_without_an_ensemble_has_none_by_default_and_refuses_seeds(monkeypatch):
    """The run file's default ``ensemble.seeds`` ([1..5]) ask an application without an
    ensemble baseline for none; seeds a run file names are refused when it is loaded, not
    after the sweeps and solves (when the dataset stage computed its key)."""
    from pathlib import Path
    from reachwatch.pipeline.spec import load_run_spec
    from reachwatch.reach.application import load_application
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    assert "ensemble: {seeds: []}" in text
    assert load_run_spec(data=text.replace("ensemble: {seeds: []}", "")).ensemble.seeds == []
    with pytest.raises(ValueError, match=r"ensemble.seeds: the application 'cart' has no "
                                         r"ensemble baseline \(it defines no ensemble_config\); "
                                         r"set ensemble.seeds: \[\]$"):
        load_run_spec(data=text.replace("ensemble: {seeds: []}", "ensemble: {seeds: [1, 2]}"))
    taxi = ("name: t\ntrain: [{runway: KMWH, hour: 9.0, sky: clear}]\n"
            "test: [{runway: KSFO, hour: 17.0, sky: clear}]\n")
    assert load_application(TAXI_APPLICATION).has_ensemble()
    assert load_run_spec(data=taxi).ensemble.seeds == [1, 2, 3, 4, 5]


@pytest.mark.parametrize("key, value", [("solved_theta_deg", 60), ("solved_py_max", 400),
                                        ("slice_py", 100)])
def test_a_taxi_box_key_the_application_does_not_read_is_refused(monkeypatch, key, value):
    """The cart's grid takes no widening and its slices no ``at``: a run file setting the
    taxi's box or slice keys for it is refused in one line (they were ignored)."""
    from pathlib import Path
    from reachwatch.pipeline.spec import load_run_spec
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)                         # the run file's paths are relative
    text = (root / "examples" / "cart" / "run.yaml").read_text()
    with pytest.raises(ValueError, match=rf"{key}: the application 'cart' does not read it "
                                         rf"\(its reads_keys\); leave it out$"):
        load_run_spec(data=text + f"{key}: {value}\n")


def test_the_speed_car_reads_slice_py_and_takes_it(monkeypatch):
    from pathlib import Path
    from reachwatch.pipeline.spec import load_run_spec
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    text = (root / "examples" / "speed_car" / "run.yaml").read_text()
    assert load_run_spec(data=text + "slice_py: 200\n").slice_py == 200
    with pytest.raises(ValueError, match="solved_py_max: the application 'speed_car' does not "
                                         "read it"):
        load_run_spec(data=text + "solved_py_max: 300\n")


def test_an_application_steered_by_the_built_in_taxinet_is_told_so(monkeypatch):
    from pathlib import Path
    from reachwatch.pipeline.run import check_controller_builds
    from reachwatch.pipeline.spec import load_run_spec
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    said = []
    check_controller_builds(load_run_spec(
        data=(root / "examples" / "speed_car" / "run.yaml").read_text()), said.append)
    assert said == ["scenario.controller.factory is not set: a loop of 'speed_car' that "
                    "builds scenario.controller is steered by the built-in TaxiNet (name your "
                    "controller's factory to run another)"]
    said.clear()                                  # the taxi's own: nothing to say
    check_controller_builds(load_run_spec(data="name: t\ntrain: [{runway: KMWH, hour: 9.0, "
                                               "sky: clear}]\ntest: [{runway: KSFO, hour: "
                                               "17.0, sky: clear}]\n"), said.append)
    assert said == []
