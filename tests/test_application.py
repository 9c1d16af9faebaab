"""The application interface: the taxi is the default and keeps its keys; a user's
application, named in the run file like a controller factory, is loaded from its
folder, fingerprinted by every file there, and swept by the generic machinery."""

import importlib
import textwrap

import numpy as np
import pytest

from reachwatch.diagrams import CONTROL_PORT, load_scenario
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.reach import InlineExecutor
from reachwatch.reach.application import Application, application_key, load_application
from reachwatch.taxi import on_runway_starts, paper_grid, sweep_closed_loop, taxi_sweep_key
from reachwatch.taxi.application import TAXI_APPLICATION, TaxiApplication
from reachwatch.training.dataset import DatasetSpec, dataset_folder
from tiny_run import taxi_application

RUN = """
train: [{runway: KMWH, hour: 9.0, sky: clear}]
test: [{runway: KSFO, hour: 21.0, sky: clear}]
guard: {candidates: 0, noise_starts: 0}
"""

APP = """
import numpy as np

import helpers
from reachwatch.taxi.application import TAXI_APPLICATION, TaxiApplication


class Rebuilt(TaxiApplication):
    '''The taxi's loop, built through the generic machinery (its own loop_diagram).'''
    name = "rebuilt"

    def loop_diagram(self, scenario, *, guarded=False):
        return super().loop_diagram(scenario, guarded=guarded)

    def failed(self, scenario, states):
        return np.abs(np.asarray(states)[:, 0]) >= helpers.EDGE


class FourAxes(Rebuilt):
    axes = ("px", "py", "theta", "v")


class TwoAxes(Rebuilt):
    axes, open_axes = ("px", "theta"), (1,)    # the taxi's heading_axis 2 is not one of them


class OpenPast(Rebuilt):
    open_axes = (1, 3)


class NoAxes(Rebuilt):
    axes, open_axes, heading_axis = (), (), None


class EstimatesPast(Rebuilt):
    estimated_state = (0, 3)


class WithData(Rebuilt):
    data_files = ("plant.sdf",)


class MissingData(Rebuilt):
    data_files = ("nowhere.sdf",)


def not_one():
    return 42
"""


def _user_app(tmp_path, edge=3.0):
    folder = tmp_path / "app"
    folder.mkdir(exist_ok=True)
    (folder / "loop.py").write_text(textwrap.dedent(APP))
    (folder / "helpers.py").write_text(f"EDGE = {edge}\n")
    return str(folder / "loop.py")


def test_the_taxi_is_the_default_application_and_keeps_its_sweep_keys(tmp_path):
    taxi = load_application(TAXI_APPLICATION)
    assert isinstance(taxi, TaxiApplication)
    # a run file that names none, or names "", studies the taxi; the generic core names
    # no default, the pipeline's is the taxi's own name
    from reachwatch.pipeline.slot_defaults import DEFAULT_APPLICATION
    from tiny_run import TINY
    assert DEFAULT_APPLICATION == TAXI_APPLICATION
    assert load_run_spec(data=TINY).application == TAXI_APPLICATION
    assert load_run_spec(data=TINY + 'application: ""\n').application == TAXI_APPLICATION
    with pytest.raises(ValueError, match="^application: name one, as package.module:name"):
        load_application("")
    # its code is in every fingerprint already (reachwatch's loop code): its key is its
    # name; made directly, it still runs in workers
    assert taxi.key() == {"spec": TAXI_APPLICATION, "code": "", "data": {}}
    assert TaxiApplication()._loaded_as() == TAXI_APPLICATION
    scenario = load_scenario(data="")
    B = scenario.environment.half_width
    grid = taxi.grid(scenario, (5, 3, 5))
    assert grid == paper_grid(B, (5, 3, 5)) and taxi.axes == ("px", "py", "theta")
    assert taxi.grid(scenario, (5, 3, 5), theta_deg=40.0, py_max=300.0) == paper_grid(
        B, (5, 3, 5), theta_deg=40.0, py_max=300.0)
    for guarded in (False, True):       # the sweep keys of before applications
        assert taxi.sweep_key(scenario, grid, guarded=guarded) == taxi_sweep_key(
            scenario, grid, guarded=guarded)
    np.testing.assert_array_equal(taxi.starts(scenario, grid, 20, 7),
                                  on_runway_starts(grid, 20, 7, half_width=B))
    states = np.array([[B - 0.1, 150.0, 0.0], [-B, 150.0, 0.0], [B + 2, 120.0, 0.3]])
    np.testing.assert_array_equal(taxi.failed(scenario, states), [False, True, True])
    # the generic failure rule (the dynamics' target) agrees with the taxi's own
    np.testing.assert_array_equal(Application.failed(taxi, scenario, states), [False, True, True])


def test_the_ensemble_baseline_is_the_applications(tmp_path, monkeypatch):
    """The taxi's members are TaxiNets trained with the config their folder was always
    keyed by; an application without an ensemble baseline says so in one line, and a
    run without seeds never asks it."""
    from reachwatch.pipeline.dataset_stages import ensemble_paths
    from reachwatch.pipeline.spec import EnsembleSpec, RunSpec
    from reachwatch.reach.fingerprint import fingerprint
    fingerprints = importlib.import_module("reachwatch.reach.fingerprint")
    from reachwatch.pipeline.stages import Run
    from reachwatch.taxi.taxinet_train import TaxiNetTrainConfig
    scenario = load_scenario(data="camera: {width: 64, height: 32}\n")
    taxi = load_application(TAXI_APPLICATION)
    config = taxi.ensemble_config(scenario, samples=48, epochs=2)
    assert config == TaxiNetTrainConfig(camera=scenario.camera, samples=48, epochs=2)
    run = Run(RunSpec(scenario=scenario, ensemble=EnsembleSpec(seeds=[3, 5], samples=48,
                                                                epochs=2)), tmp_path / "run")
    paths = [p.relative_to(run.root).as_posix() for p in ensemble_paths(run)]
    own = application_key(taxi)
    assert paths == [f"ensemble/{fingerprint(config, [3, 5], own)[:16]}/member_seed{s}.pt"
                     for s in (3, 5)]
    # members trained under another torch (or another render stack) are not reused
    monkeypatch.setitem(fingerprints.STACK, "torch", "0.0-elsewhere")
    elsewhere = [p.relative_to(run.root).as_posix() for p in ensemble_paths(run)]
    assert elsewhere != paths and [p.rsplit("/", 1)[1] for p in elsewhere] == [
        p.rsplit("/", 1)[1] for p in paths]
    none = r"^the application 'taxi' has no ensemble baseline: set ensemble.seeds: \[\]$"
    with pytest.raises(ValueError, match=none):         # the generic defaults
        Application.ensemble_config(taxi, scenario, samples=1, epochs=1)
    with pytest.raises(ValueError, match=none):
        Application.train_ensemble(taxi, config, [tmp_path / "m.pt"], [1])
    run.application = None                      # not asked: nothing to train
    run.spec.ensemble.seeds = []
    assert ensemble_paths(run) == []


def test_a_user_application_is_loaded_from_its_folder_and_keyed_by_every_file(tmp_path):
    spec = f"{_user_app(tmp_path)}:Rebuilt"
    app = load_application(spec)
    assert isinstance(app, Application) and app.name == "rebuilt" and app.spec == spec
    scenario = load_scenario(data="")
    grid = app.grid(scenario, (3, 3, 3))
    states = np.array([[2.9, 150.0, 0.0], [3.0, 150.0, 0.0]])
    np.testing.assert_array_equal(app.failed(scenario, states), [False, True])   # helpers.EDGE
    key, sweep_key = app.key(), app.sweep_key(scenario, grid)
    assert key is not None and sweep_key != taxi_sweep_key(scenario, grid)
    # what a sweep does not read leaves its key; the controller does not
    assert app.sweep_key(load_scenario(data="monitor: {threshold: 0.3, strategy: brake}\n"
                                            "duration: 5.0\nseed: 3\n"), grid) == sweep_key
    assert app.sweep_key(load_scenario(data="controller: {speed: 4.0}\n"), grid) != sweep_key
    from reachwatch.reach import ValueFunction
    vf = ValueFunction(grid, np.ones(grid.shape), 1.0, "test")
    assert dataset_folder(tmp_path, scenario, vf, DatasetSpec(), application=app) != \
        dataset_folder(tmp_path, scenario, vf, DatasetSpec(), application=taxi_application())
    # made directly, not loaded by name: refused where workers or keys need its name
    with pytest.raises(ValueError, match="load it with load_application"):
        type(app)().sweep_key(scenario, grid)
    with pytest.raises(ValueError, match="load it with load_application"):
        type(app)().key()
    # its own loop: labels along runs come from the generic runner on that loop, judged by
    # its failure rule (3 m from the centreline, not the runway's edge); the heading is
    # the taxi's axis, which it inherits
    paths = app.real_paths(scenario, states, grid=grid, horizon=0.1, extend=0.1, stride=1,
                           cache_dir=tmp_path, progress=False).fields
    assert paths["failed"].tolist() == [False, True] and app.heading_axis == 2
    assert paths["max_abs_theta"][1] == 0.0 and 0 < paths["max_abs_theta"][0] < 0.1
    assert paths["path_label"][1].tolist() == [1, -1, -1]
    # editing a helper file (not the one named) re-keys its sweeps and its results
    _user_app(tmp_path, edge=4.0)
    edited = load_application(spec)
    np.testing.assert_array_equal(edited.failed(scenario, states), [False, False])
    assert edited.key() != key and edited.sweep_key(scenario, grid) != sweep_key
    # named in a run file; its axes set the grid's length
    assert load_run_spec(data=RUN + f"application: '{spec}'\n").application == spec
    four = spec.replace(":Rebuilt", ":FourAxes")
    with pytest.raises(ValueError, match=r"grid must be 4 sizes \[n_px, n_py, n_theta, n_v\]"):
        load_run_spec(data=RUN + f"application: '{four}'\n")
    load_run_spec(data=RUN + f"application: '{four}'\ngrid: [3, 3, 3, 3]\n")


@pytest.mark.parametrize("name, why", [
    (":Missing", "application: '.*loop.py' has no function 'Missing'"),
    (":not_one", "it returned a int, not a reachwatch.reach.application.Application"),
    ("nowhere.py:Rebuilt", "application: file not found: nowhere.py"),
    (":TwoAxes", r"heading_axis names axis 2, but its state has 2 \(px, theta\)$"),
    (":OpenPast", r"open_axes names axis 3, but its state has 3 \(px, py, theta\)$"),
    (":EstimatesPast", r"estimated_state names axis 3, but its state has 3 \(px, py, theta\)$"),
    (":MissingData", r"application '.*loop.py:MissingData': data_files: cannot read "
                     r".*nowhere.sdf \(No such file or directory\)$"),
    (":NoAxes", r"axes must name each axis of its state \(a tuple of names: \('x', 'y', "
                r"'heading'\)\), got \(\)$"),
])
def test_a_bad_application_is_one_line_naming_the_key(tmp_path, name, why):
    path = _user_app(tmp_path)
    spec = path + name if name.startswith(":") else name
    with pytest.raises(ValueError, match=why) as error:
        load_run_spec(data=RUN + f"application: '{spec}'\n")
    assert "\n" not in str(error.value)


def test_monitor_state_targets_name_axes_of_the_state(tmp_path):
    """``monitor.state_targets`` past the state's axes is refused when the run file
    loads, not in the monitor's training after its runs are recorded."""
    spec = f"{_user_app(tmp_path)}:Rebuilt"
    monitor = "monitor: {kind: history, state_targets: [%s]}\n"
    with pytest.raises(ValueError, match=r"monitor.state_targets: 3 is no axis of the state, "
                                         r"which has 3 \(px, py, theta\)$"):
        load_run_spec(data=RUN + f"application: '{spec}'\n" + monitor % "0, 3")
    load_run_spec(data=RUN + f"application: '{spec}'\n" + monitor % "0, 2")


def test_the_generic_sweep_of_a_user_application_is_the_taxis_table(tmp_path):
    """A user's application swept through `Application.sweep` (its loop built in the
    worker from the string it was loaded from) gives the taxi's own table."""
    app = load_application(f"{_user_app(tmp_path)}:Rebuilt")
    scenario = load_scenario(data="")
    grid = paper_grid(scenario.environment.half_width, (3, 2, 3))
    mine = app.sweep(scenario, grid, cache_dir=tmp_path / "sweeps", executor=InlineExecutor(),
                     progress=False)
    taxi = sweep_closed_loop(scenario, grid, cache_dir=tmp_path / "sweeps",
                             executor=InlineExecutor(), progress=False)
    assert mine.key != taxi.key and mine.computed == taxi.computed == grid.size
    np.testing.assert_allclose(mine[CONTROL_PORT], taxi[CONTROL_PORT])


def test_the_generic_real_loop_stops_where_the_failure_rule_holds_as_the_taxis(tmp_path):
    """`Application.real_outcomes` by default runs `loop_diagram` and stops at the
    integrator step where the application's failure rule holds: on the taxi's own loop
    and rule it is the taxi's real loop, failure times and ticks alike. With a control
    period longer than the integrator's steps (at most 0.1 s) the run fails between
    ticks."""
    scenario = load_scenario(data="controller: {period: 0.25}\n")
    B = scenario.environment.half_width
    app = load_application(f"{_user_app(tmp_path, edge=B)}:Rebuilt")
    grid = paper_grid(B, (3, 3, 3))
    starts = np.array([[0.0, 150.0, 0.0], [B - 0.5, 150.0, 0.4], [B + 1.0, 150.0, 0.0]])
    mine = app.real_outcomes(scenario, starts, grid=grid, duration=1.0,
                             cache_dir=tmp_path / "mine", progress=False)
    taxi = load_application(TAXI_APPLICATION).real_outcomes(scenario, starts, grid=grid, duration=1.0,
                                            cache_dir=tmp_path / "taxi", progress=False)
    np.testing.assert_array_equal(mine.failed, [False, True, True])
    for field in ("failed", "failure_time", "left_box", "ticks"):
        np.testing.assert_array_equal(mine[field], taxi[field], err_msg=field)
    assert mine["ticks"][0] == 5 and mine["ticks"][2] == 0 and 0 < mine["failure_time"][1] < 1
    between = mine["failure_time"][1] % 0.25
    assert min(between, 0.25 - between) > 1e-6                          # between ticks


def test_a_taxi_subclass_with_its_own_loop_runs_and_starts_by_its_own_rules(tmp_path):
    """`run_from` and `start_state` of a taxi subclass that builds its own loop are the
    generic ones (its failure rule; the middle of its box), as its real-loop runs are:
    not the taxi's runway edge and scenario start."""
    scenario = load_scenario(data="initial_state: {px: 2.0, py: 120.0}\n")
    app = load_application(f"{_user_app(tmp_path, edge=1.0)}:Rebuilt")
    run, failed = app.run_from(scenario, [1.5, 150.0, 0.0], 0.2)    # past its 1 m edge
    assert failed and run.failed and run.failure_time == 0.0 and len(run.time) == 1
    run, failed = load_application(TAXI_APPLICATION).run_from(scenario, [1.5, 150.0, 0.0], 0.2)
    assert not failed and len(run.time) == 5                       # on the runway
    np.testing.assert_array_equal(app.start_state(scenario), app.view_state(scenario))
    np.testing.assert_array_equal(load_application(TAXI_APPLICATION).start_state(scenario),
                                  [2.0, 120.0, 0.0])


def test_an_applications_ensemble_folder_is_keyed_by_its_code(tmp_path):
    """The ensemble baseline's folder is keyed by the config, the seeds, the software
    stack and the application's key (its code: its `train_ensemble`)."""
    from types import SimpleNamespace
    from reachwatch.pipeline.dataset_stages import ensemble_paths
    from reachwatch.reach.fingerprint import fingerprint

    class Fake:
        def __init__(self, key):
            self.code = key

        def key(self):
            return self.code

        def ensemble_config(self, scenario, *, samples, epochs):
            return {"samples": samples, "epochs": epochs}

    def folder(key, seeds=(0, 1)):
        spec = SimpleNamespace(ensemble=SimpleNamespace(seeds=list(seeds), samples=8, epochs=1),
                               scenario=None)
        run = SimpleNamespace(spec=spec, application=Fake(key), path=lambda p: tmp_path / p)
        paths = ensemble_paths(run)
        assert len({p.parent for p in paths}) == min(len(seeds), 1) and len(paths) == len(seeds)
        return paths[0].parent if paths else None

    assert folder({"code": "a"}) == tmp_path / "ensemble" / fingerprint(
        {"samples": 8, "epochs": 1}, [0, 1], fingerprint({"code": "a"})[:16])[:16]
    assert len({folder({"code": "a"}), folder({"code": "b"})}) == 2
    assert folder({"code": "a"}) == folder({"code": "a"})
    assert folder({"code": "a"}, seeds=()) is None


def test_the_stopping_time_is_the_applications():
    """The monitor study's lead: the controller's speed over the deceleration by
    default; the speed car's speed lags its command and may start at 6 m/s."""
    import re
    from pathlib import Path
    scenario = load_scenario(data="controller: {speed: 5.0}\n")
    assert load_application(TAXI_APPLICATION).stopping_time(scenario, 3.0) == pytest.approx(5.0 / 3.0)
    root = Path(__file__).resolve().parents[1]
    spec = re.search(r"^application: *(\S+)", (root / "examples/speed_car/run.yaml").read_text(),
                     re.M).group(1)
    import os
    here = os.getcwd()
    os.chdir(root)
    try:
        car = load_application(spec)
    finally:
        os.chdir(here)
    assert car.stopping_time(scenario, 3.0) == pytest.approx(6.0 / 3.0 + 1.0)


def test_a_camera_port_the_loop_lacks_is_one_line_naming_the_attribute(monkeypatch):
    """The default renderer (datasets' images) reads the loop's ``camera_port``: one the
    loop lacks is one line naming the attribute, not Drake's error inside a worker."""
    import copy
    from pathlib import Path
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    car = load_application("examples/speed_car/application.py:SpeedCar")
    assert type(car).renderer is Application.renderer
    application = copy.copy(car)
    application.camera_port = "nose_camera.color_image"
    with pytest.raises(ValueError, match=r"^the application 'speed_car': its loop has no output "
                                         r"port 'nose_camera.color_image' \(its camera_port\); "
                                         r"set camera_port to the loop's 'system.port'$"):
        application.renderer(load_scenario(data=""))


def test_a_loop_that_renders_another_size_than_scenario_camera_is_one_line(monkeypatch,
                                                                             tmp_path):
    """The speed car builds its camera without ``scenario.camera``: a run file that sets
    another size gets one line at its dataset's first chunk, not a detector recorded as
    trained at a size its loop never renders (refused by every guarded sweep after)."""
    import dataclasses as dc
    from pathlib import Path
    from reachwatch.training.dataset_images import ImageSource, ImageTools, render_chunk
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    car = load_application("examples/speed_car/application.py:SpeedCar")
    scenario = car.resolved(load_scenario(data=""))
    state = car.view_state(scenario)[None]
    tools = ImageTools.build(car, scenario)
    source = ImageSource(None, scenario, (), 48, 80, "key", tools)
    assert render_chunk(source, state)["images"].shape == (1, 48, 80, 3)
    other = dc.replace(scenario, camera=dc.replace(scenario.camera, height=100, width=180))
    with pytest.raises(ValueError, match=r"^the application's loop renders 200x360 frames, and "
                                         r"scenario.camera is 100x180: build the loop's camera "
                                         r"from scenario.camera"):
        render_chunk(dc.replace(source, scenario=other), state)
    # and a monitor study's recordings of it, at their first frame
    with pytest.raises(ValueError, match=r"renders 200x360 frames, and scenario.camera is "
                                         r"100x180"):
        car.recorded_runs(other, state, duration=0.1, height=16, width=24,
                          cache_dir=tmp_path / "rec", progress=False)


def test_real_loop_runs_are_keyed_without_the_scenarios_start_duration_and_seed(tmp_path,
                                                                                monkeypatch):
    """Runs of the loop alone or watched set their own starts and duration: a run file
    that changes ``scenario.duration``, ``initial_state`` or ``seed`` reuses their
    caches (as sweeps do), and one that changes the loop does not."""
    from reachwatch.reach.application import sweep_scenario
    from reachwatch.reach.fingerprint import fingerprint
    taxi = load_application(TAXI_APPLICATION)
    plain = load_scenario(data="")
    other = load_scenario(data="duration: 3.0\nseed: 7\n"
                               "initial_state: {px: 1.0, py: 120.0, theta_deg: 2.0}\n")
    for keyed in (taxi.without_monitor, taxi._watching, sweep_scenario):
        assert fingerprint(keyed(plain)) == fingerprint(keyed(other))
    assert (other.duration, other.seed) == (3.0, 7)            # the caller's, untouched
    # and the guarded runs with a fallback: the scenario their rollouts are keyed by
    import reachwatch.reach.outcomes as outcomes
    keyed = []

    def stand_in(rollout, starts, **kwargs):
        keyed.append(fingerprint(rollout))
        raise StopIteration
    monkeypatch.setattr(outcomes, "map_states", stand_in)
    for scenario in (plain, other):
        with pytest.raises(StopIteration):
            taxi.missions(scenario, np.zeros((1, 3)), fallback="brake", duration=1.0,
                          cache_dir=tmp_path)
    assert len(keyed) == 2 and keyed[0] == keyed[1]
    slower = load_scenario(data="controller: {period: 0.1}\n")
    assert fingerprint(taxi.without_monitor(plain)) != fingerprint(taxi.without_monitor(slower))


def test_the_guard_showcase_builds_the_loop_as_the_cached_missions_do(monkeypatch, tmp_path):
    """`mission_rollouts` (the showcase, not cached) and `missions` (cached) run the same
    loop: both without the scenario's run settings, so the showcase and the check
    cannot differ by them."""
    import reachwatch.reach.loop_runs as loop_runs
    import reachwatch.reach.outcomes as outcomes
    showcase, cached = [], []

    def run_here(ref, scenario, fallback, duration, states, mission_limit=None):
        showcase.append(scenario)
        raise RuntimeError("captured")

    def cache(rollout, starts, **kwargs):
        cached.append(rollout.args[1])            # the scenario the runs would build
        raise RuntimeError("captured")
    monkeypatch.setattr(loop_runs, "loop_missions", run_here)
    monkeypatch.setattr(outcomes, "map_states", cache)
    taxi = load_application(TAXI_APPLICATION)
    scenario = load_scenario(data="duration: 3.0\nseed: 7\n"
                                  "initial_state: {px: 1.0, py: 120.0, theta_deg: 2.0}\n")
    for fallback in ("brake", None):
        for call in (lambda: taxi.mission_rollouts(scenario, fallback, 1.0, np.zeros((1, 3))),
                     lambda: taxi.missions(scenario, np.zeros((1, 3)), duration=1.0,
                                           fallback=fallback, cache_dir=tmp_path,
                                           progress=False)):
            with pytest.raises(RuntimeError, match="captured"):
                call()
    assert len(showcase) == len(cached) == 2
    for a, b in zip(showcase, cached):
        assert (a.duration, a.seed, a.initial_state) == (b.duration, b.seed, b.initial_state)
        assert (a.duration, a.seed) == (10.0, 0)


def test_an_applications_data_files_are_keyed_by_their_content(tmp_path):
    """A file the loop reads that is not Python (a plant model, a mesh) and that the
    application names in data_files: before, no key covered an edit to it."""
    spec = f"{_user_app(tmp_path)}:WithData"
    sdf = tmp_path / "app" / "plant.sdf"
    sdf.write_text("<sdf mass='1.0'/>")
    app = load_application(spec)
    scenario = load_scenario(data="")
    grid = app.grid(scenario, (3, 3, 3))
    key, sweep_key = app.key(), app.sweep_key(scenario, grid)
    sdf.write_text("<sdf mass='2.0'/>")
    assert app.key() != key and app.sweep_key(scenario, grid) != sweep_key
    sdf.write_text("<sdf mass='1.0'/>")
    assert app.key() == key


def test_dynamics_at_another_speed_than_the_controllers_are_refused_by_the_guard_tables(
        tmp_path):
    """Before: the guard's tables rolled out at the dynamics' speed, its real loop at
    scenario.controller.speed, and their rows disagreed without a word."""
    from reachwatch.taxi.dynamics import TaxiDynamics

    class Slower(TaxiApplication):
        def dynamics(self, scenario):
            return TaxiDynamics(half_width=scenario.environment.half_width, speed=3.0)
    scenario = load_scenario(data="controller: {speed: 5.0}\n")
    with pytest.raises(ValueError, match=r"its dynamics\(scenario\).speed is 3, and "
                                         r"scenario.controller.speed 5: the guard's tables"):
        Slower().check_guard(scenario, ["brake"])
    TaxiApplication().check_guard(scenario, ["brake"])


def test_data_files_are_found_beside_the_file_the_application_is_loaded_from(tmp_path):
    """An application class in a helper module of its folder: the helper is out of
    sys.modules once loaded, and its data files were looked for in the wrong folder."""
    folder = tmp_path / "plant_app"
    folder.mkdir()
    (folder / "plant.py").write_text(
        "from reachwatch.taxi.application import TaxiApplication\n\n\n"
        "class WithModel(TaxiApplication):\n    data_files = ('model.sdf',)\n")
    (folder / "app.py").write_text("from plant import WithModel\n\n\n"
                                   "def make():\n    return WithModel()\n")
    (folder / "model.sdf").write_text("<sdf/>")
    app = load_application(f"{folder / 'app.py'}:make")
    key = app.key()
    (folder / "model.sdf").write_text("<sdf mass='2'/>")
    assert app.key() != key


def test_a_solved_box_past_the_rendered_runway_is_refused():
    """Before: states beyond the runway's end, or the scene's ground (3,000 m), rendered
    grass or sky and were labelled as on the runway."""
    app = TaxiApplication()
    short = load_scenario(data="environment: {runway_spec: {length: 400.0}}\n")
    with pytest.raises(ValueError, match=r"solved_py_max 500 m lies past the end of "
                                         r"CUSTOM_9h_clear's runway as rendered \(400 m"):
        app.grid(short, (3, 3, 3), py_max=500.0)
    app.grid(short, (3, 3, 3), py_max=290.0)
    with pytest.raises(ValueError, match=r"as rendered \(3000 m"):
        app.grid(load_scenario(data="environment: {runway: PAEI}\n"), (3, 3, 3), py_max=3300.0)


def test_a_run_whose_solved_box_passes_an_environments_runway_stops_before_any_stage(tmp_path):
    from reachwatch.pipeline.run import run_pipeline
    spec = load_run_spec(data=RUN.replace(
        "test: [{runway: KSFO, hour: 21.0, sky: clear}]",
        "test: [{runway: X, hour: 21.0, sky: clear, runway_spec: {name: SHORT, length: 400.0}}]"
    ) + "solved_py_max: 450.0\n")
    with pytest.raises(ValueError, match=r"solved_py_max 450 m lies past the end of "
                                         r"SHORT_21h_clear's runway as rendered"):
        run_pipeline(spec, tmp_path / "out", until="sweep", progress=False, log=lambda m: None)
    assert not list((tmp_path / "out").glob("sweeps/*"))
