"""The worked examples in examples/, end to end at a tiny size."""

import copy
import json
from dataclasses import replace as dc_replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from reachwatch.diagrams import ControllerConfig, ControllerProbe, check_controller, make_controller
from reachwatch.pipeline.cli import main
from reachwatch.pipeline.spec import dump_run_spec, load_run_spec
from reachwatch.taxi import OffRunway

ROOT = Path(__file__).resolve().parents[1]
GRASS = ROOT / "examples" / "grass_follower"


def _tiny(spec):
    """A run file's spec shrunk to test size (the controller and environments kept)."""
    spec.grid, spec.horizon = [5, 3, 5], 4.0
    spec.dataset.samples, spec.dataset.height, spec.dataset.width = 40, 24, 40
    spec.dataset.chunk_size = 16
    spec.detector.detector.height, spec.detector.detector.width = 24, 40
    spec.detector.detector.channels = [4, 8]
    spec.detector.epochs, spec.detector.batch_size, spec.detector.device = 1, 8, "cpu"
    spec.guard.candidates, spec.guard.online_seconds = 1, 0.2
    spec.guard.check_starts, spec.guard.tradeoff_points, spec.guard.noise_starts = 1, 2, 2
    spec.train, spec.test = spec.train[:1], spec.test[:1]
    spec.fidelity.starts, spec.fidelity.max_box_exits = 2, 1.0
    return spec


def test_grass_follower_is_a_controller():
    config = ControllerConfig(factory=f"{GRASS / 'grass_follower.py'}:make_controller",
                              parameters={"gain_deg": 10.0})
    system = make_controller(config)
    assert not system.HasOutputPort("estimate")
    grass, road = np.zeros((20, 40, 3), np.uint8), np.zeros((20, 40, 3), np.uint8)
    grass[..., 1] = 120                        # green everywhere
    road[:] = 90                               # grey everywhere
    half = road.copy()
    half[:, 20:] = grass[:, 20:]               # grass on the right: steer left (positive)
    balance = [system.grass_balance(x) for x in (road, grass, half)]
    assert balance == [0.0, 0.0, 1.0]
    steering, estimate = ControllerProbe(system).outputs(half)
    assert estimate is None and steering[0] == pytest.approx(np.deg2rad(10.0 * (1.0 - 0.09)))


def test_a_system_without_the_ports_is_refused():
    from pydrake.systems.primitives import ConstantVectorSource
    with pytest.raises(ValueError, match="needs an input port 'color_image'"):
        check_controller(ConstantVectorSource([0.0]))
    with pytest.raises(ValueError, match="must be 'package.module:function'"):
        make_controller(ControllerConfig(factory="no_colon_here"))
    with pytest.raises(ValueError, match="cannot import 'not_a_module_xyz'"):
        make_controller(ControllerConfig(factory="not_a_module_xyz:make"))


def _run_to_report(spec, tmp_path):
    """``reachwatch run`` on ``spec`` (written to a file) inline; its output folder."""
    path = tmp_path / "tiny.yaml"
    path.write_text(dump_run_spec(spec))
    out = tmp_path / "out"
    assert main(["-q", "run", "--scenario", str(path), "--out", str(out),
                 "--executor", "inline"]) == 0
    return out


def test_grass_follower_through_reachwatch_run(tmp_path, monkeypatch):
    """Example (a): a classical controller on the taxi plant, run file to report."""
    monkeypatch.chdir(ROOT)                    # the run file's factory path is relative
    spec = _tiny(load_run_spec(GRASS / "run.yaml"))
    spec.guard.environments = []
    # its vision reads any image size: a small camera renders the tiny run faster
    spec.scenario.camera = dc_replace(spec.scenario.camera, width=120, height=64)
    out = _run_to_report(spec, tmp_path)
    report = (out / "report.md").read_text()
    assert "grass_follower" in report and "Table 2" in report
    assert "prediction-error labels" not in report        # no pose estimate: no such baseline
    table = (out / "table2.csv").read_text()
    assert "detector (BRT labels)" in table and "TaxiNet prediction error" not in table
    record = json.loads((out / "stages" / "guard_KSFO_21h_overcast.json").read_text())
    assert set(record["outputs"]["volumes"]) == {"unguarded", "slow_down", "brake", "slow_down+oracle"}


def test_speed_car_through_reachwatch_run(tmp_path, monkeypatch):
    """Example (b) as an application: a 4-state plant through ``reachwatch run`` to a
    report, with its own run file and application and no library edit."""
    monkeypatch.chdir(ROOT)                    # the run file's application path is relative
    spec = _tiny(load_run_spec(ROOT / "examples" / "speed_car" / "run.yaml"))
    spec.grid, spec.horizon, spec.dataset.samples = [3, 3, 3, 3], 2.0, 10
    spec.fidelity.starts = 0                   # the application runs no real loop
    spec.guard.noise_starts = 0                # as its run file says
    out = _run_to_report(spec, tmp_path)
    report = (out / "report.md").read_text()
    assert "speed_car" in report and "| KSFO_21h_overcast | test | 3x3x3x3 | 81 |" in report
    assert "Table 2" in report and (out / "figures" / "overlay_KSFO_21h_overcast.png").is_file()
    # the guard: its speed fallbacks rolled out in the tables of the car's guarded loop
    # (its speed, a state, lags the command they set) and checked in its real loop
    guard = json.loads((out / "stages" / "guard_KSFO_21h_overcast.json").read_text())["outputs"]
    assert set(guard["liveness"]) == {"slow_down", "brake"}
    check = guard["check"]
    assert check["starts"] == 1 and check["fallbacks"]["brake"]["real"]["starts"] == 1
    states = np.load(next((out / "datasets").glob("KMWH_9h_clear_*")) / "states.npy")
    assert states.shape == (10, 4)
    # the car's own loop was swept: its plant and the application's code key the sweep
    record = json.loads((out / "stages" / "sweep_KMWH_9h_clear.json").read_text())
    assert record["key"].startswith("KMWH_9h_clear_3x3x3x3_")


def _speed_car():
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        "speed_car_example", ROOT / "examples" / "speed_car" / "speed_car.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_speed_car_through_sweep_brt_labels_detector_and_switch(tmp_path):
    """Example (b): a 4-state plant (speed lags its command) with the runway camera."""
    from reachwatch.diagrams import MonitorConfig, simulate
    from reachwatch.reach import InlineExecutor
    from reachwatch.systems import DetectorConfig, Environment
    from reachwatch.training.detector_train import DetectorTrainConfig
    car = _speed_car()
    config = car.CarConfig(environment=Environment("KMWH", 9.0, "clear"))
    detector = DetectorTrainConfig(detector=DetectorConfig(height=24, width=40, channels=[4, 8]),
                                   epochs=1, batch_size=8, device="cpu")
    grid, table, value, data, trained = car.study(
        config, tmp_path, shape=(5, 3, 5, 2), horizon=2.0, samples=40, detector=detector,
        executor=InlineExecutor(), progress=False)
    steering = table[car.PROBE.control_port][..., 0]
    assert steering.shape == (5, 3, 5, 2)
    # The image does not see the speed: both speed layers got the same steering.
    np.testing.assert_array_equal(steering[..., 0], steering[..., 1])
    assert value.values.shape == (5, 3, 5, 2)
    # Ground truth at the edges: a state at |px| = B is a failure; slow cars fail less.
    B = config.environment.half_width
    assert value.in_brt([[B, 150.0, 0.0, 3.0]])[0]
    assert np.mean(value.values[..., 1] <= 0) >= np.mean(value.values[..., 0] <= 0)
    np.testing.assert_array_equal(data.labels, value.at(data.states) <= 0)
    assert data.images.shape == (40, 24, 40, 3) and (tmp_path / "detector.pt").is_file()
    # The switch in the car's loop: always flagged, the commanded speed falls and the car
    # slows through its lag; never flagged, the guarded loop is the loop alone.
    x0 = [0.0, 120.0, 0.0, 5.0]
    runs = {}
    for name, threshold in (("always", 0.0), ("never", 1.0)):
        guarded = dc_replace(config, monitor=MonitorConfig(detector=str(tmp_path / "detector.pt"),
                                                           threshold=threshold))
        runs[name] = simulate(car.make_car_loop(guarded), initial_state=x0, duration=1.0,
                              period=0.05, failed=OffRunway(B))
    alone = simulate(car.make_car_loop(config), initial_state=x0, duration=1.0, period=0.05,
                     failed=OffRunway(B))
    assert runs["always"].anomaly.all() and runs["always"].speed[-1] < 5.0
    assert runs["always"].state[-1, 3] < runs["always"].state[0, 3] - 0.05
    assert not runs["never"].anomaly.any()
    np.testing.assert_allclose(runs["never"].state, alone.state)


def test_cart_through_reachwatch_run(tmp_path, monkeypatch):
    """Example (c): a plant of one's own (a 2-state cart on a track, its own scene of
    Drake boxes, camera and vision controller) through ``reachwatch run`` to a report,
    by the public Application interface alone."""
    monkeypatch.chdir(ROOT)                    # the run file's paths are relative
    spec = _tiny(load_run_spec(ROOT / "examples" / "cart" / "run.yaml"))
    spec.grid, spec.horizon, spec.dataset.samples = [5, 5], 2.0, 10
    spec.scenario.camera.height, spec.scenario.camera.width = 24, 48
    spec.monitor.kind = "history"              # the monitor study runs the cart's loop too
    spec.validate()                            # (tests/test_monitor_study.py runs it)
    spec.monitor.kind = "detector"
    out = _run_to_report(spec, tmp_path)
    report = (out / "report.md").read_text()
    assert report.startswith("# reachwatch run 'cart'")
    assert "| KMWH_21h_clear | test | 5x5 | 25 |" in report
    assert "Table 2" in report and (out / "figures" / "overlay_KMWH_21h_clear.png").is_file()
    # the guard: the generic table rollouts of the cart's speed fallbacks, checked in its
    # real loop from the same starts
    guard = json.loads((out / "stages" / "guard_KMWH_21h_clear.json").read_text())["outputs"]
    assert set(guard["liveness"]) == {"slow_down", "brake"}
    check = guard["check"]["fallbacks"]["brake"]
    assert guard["check"]["starts"] == 1 and check["real"]["starts"] == 1
    assert "same_distance_failure_set" in check["real"]      # the generic missions' distance
    # the detector's variation between nodes, fitted on the cart's own real runs
    noise = guard["check"]["score_noise"]
    assert noise["runs"] == 2 and noise["left_out"] == 0 and noise["ticks"] > 2, noise
    assert np.isfinite(noise["sigma"]) and "table_with_noise" in check
    assert "Not run: the application 'cart' has no fallback rollouts" not in report
    assert "fraction of grid starts that reach a rail within 2 s" in report
    states = np.load(next((out / "datasets").glob("KMWH_9h_clear_*")) / "states.npy")
    assert states.shape == (10, 2) and np.all(np.abs(states[:, 0]) <= 0.5)
    # the real-loop check ran the cart's own loop from 2 starts per environment
    record = json.loads((out / "stages" / "fidelity_KMWH_21h_clear.json").read_text())
    assert record["outputs"]["starts"] == 2 and record["outputs"]["frames"] > 0
    # the report speaks of the cart, not the taxi (the run file itself names runways)
    text = report.split("## Configuration")[0]
    for words in ("runway", "TaxiNet", "aircraft", "paper's box", "py = ", "max |theta|"):
        assert words not in text, words
    assert "left the box': runs leaving the solved box in theta," in text
    assert "the real loop reached a rail" in text and "Grid [5, 5] over the track (y" in text
    # the environments figure is the cart's camera: both rails in view
    sheet = cv2.imread(str(out / "figures" / "environments.png"))[:, :48].astype(int)
    b, g, r = sheet[..., 0], sheet[..., 1], sheet[..., 2]
    assert ((r > g + 40) & (r > b + 40)).any() and ((b > r + 40) & (b > g + 40)).any()
    # the generic showcase: the cart alone and braking, with the run's detector flagging
    # every tick, from one start; drawn against time (the cart defines no plot_runs)
    from reachwatch.reach.application import load_application
    cart = load_application(spec.application)
    trained = json.loads((out / "stages" / "train.json").read_text())["outputs"]
    shown = dc_replace(spec.scenario, environment=spec.test[0], duration=1.0)
    shown.monitor = dc_replace(shown.monitor, detector=str(out / trained["detector"]),
                               threshold=0.0).with_fallback("brake")
    alone, guarded, paths = cart.simulate_guarded(shown, [0.1, 0.0], tmp_path / "shown")
    assert len(alone.time) == len(guarded.time) == 11 and not alone.failed
    assert np.all(np.asarray(guarded.anomaly).ravel()[1:] >= 0.5)
    speed = np.asarray(guarded.speed).ravel()
    assert speed[0] == shown.controller.speed and speed[-1] < speed[1] < speed[0]
    assert [p.name for p in paths] == ["guarded_KMWH_21h_clear.png"] and paths[0].is_file()
    # the same from the command line, on the run file with the run's detector
    assert main(["simulate", "--run", str(ROOT / "examples" / "cart" / "run.yaml"),
                 "--loop", "guarded", "--start", "0.1", "0.0", "--out", str(tmp_path / "cli"),
                 "--set", f"scenario.monitor.detector={out / trained['detector']}",
                 "--set", "scenario.monitor.threshold=0.0", "--set", "scenario.duration=1.0",
                 "--set", "scenario.monitor.strategy=brake", "--set", "scenario.camera.height=24",
                 "--set", "scenario.camera.width=48"]) == 0
    assert (tmp_path / "cli" / "guarded_KMWH_21h_clear.png").is_file()
    # the generic score-noise fit runs on a copy: the caller's monitor stays as it was
    before = copy.deepcopy(shown.monitor)
    grid = cart.grid(shown, (5, 5))
    starts = cart.starts(shown, grid, 3, 0)
    fitted, fit = cart.real_score_noise(shown, grid, np.full(grid.shape, 0.5), starts,
                                        duration=1.0, cache_dir=tmp_path / "noise",
                                        progress=False)
    # every run of two ticks or more fitted on or cut at the box's edge (past it the
    # table has no score); a run failing before its second tick has nothing to fit
    ticks = cart.score_runs(shown, starts, duration=1.0, cache_dir=tmp_path / "noise",
                            progress=False)["ticks"]
    assert shown.monitor == before and fit["left_out"] == 0 and np.sum(ticks >= 2) >= 2
    assert fit["runs"] <= np.sum(ticks >= 2) <= fit["runs"] + fit["cut_at_box"], (fit, ticks)
    assert 10 <= fit["ticks"] <= 33 and np.isfinite(fitted.sigma)


def test_any_applications_loop_runs_through_reachwatch_simulate(tmp_path, monkeypatch, capsys):
    """``reachwatch simulate --run``: the cart's loop (a run file's application) from a
    start of its own state, stopped where it fails, its table headed by the cart's axes."""
    monkeypatch.chdir(ROOT)                    # the run file's paths are relative
    run = ["simulate", "--run", "examples/cart/run.yaml", "--set", "scenario.duration=1.0"]
    assert main(run + ["--start", "0.4", "0.69", "--out", str(tmp_path)]) == 0
    data = np.load(tmp_path / "KMWH_21h_clear_trajectory.npz")
    assert list(data["axes"]) == ["y", "theta"] and data["state"].shape[1] == 2
    assert data["failed"] and data["time"][-1] <= data["failure_time"] < data["time"][-1] + 0.1 + 1e-9
    assert np.all(np.abs(data["state"][:-1, 0]) < 0.5)      # on the track until its last tick
    table = np.loadtxt(tmp_path / "KMWH_21h_clear_trajectory.csv", delimiter=",", skiprows=1)
    assert (tmp_path / "KMWH_21h_clear_trajectory.csv").read_text().startswith("t_s,y_m,theta_deg\n")
    assert np.allclose(table[:, 2], np.rad2deg(data["state"][:, 1]), atol=1e-6)
    assert (tmp_path / "KMWH_21h_clear_trajectory.png").stat().st_size > 1000
    # another environment of the run file, from the application's own start
    assert main(run + ["--env", "KMWH_9h_clear", "--out", str(tmp_path / "a")]) == 0
    data = np.load(tmp_path / "a" / "KMWH_9h_clear_trajectory.npz")
    assert not data["failed"] and len(data["time"]) == 11
    assert np.allclose(data["state"][0], [0.0, 0.0])        # the middle of the cart's box
    capsys.readouterr()
    assert main(run + ["--start", "0.1", "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "--start: 1 value for run file examples/cart/run.yaml, whose 'cart' state has " \
           "2 (y, theta)" in err and err.count("\n") == 1
    assert not (tmp_path / "b").exists()                 # refused before any output


TUNED_CART = '''
from pathlib import Path
from reachwatch.reach.application import load_application

CartApplication = type(load_application("examples/cart/application.py:CartApplication"))


class TunedCart(CartApplication):
    """The cart with a fine-tuning of its own: it writes what it was given."""
    def fine_tune(self, scenario, checkpoint, datasets, config, path, *, progress=None):
        mined = sum(int((d.labels == 1).sum()) for _, d in datasets)
        Path(path).write_text(f"{checkpoint!r} tuned on {mined} of {len(datasets)} datasets")
        return {"mined_states": mined, "replayed_states": 0, "fine_tune_seconds": 0.5}
'''


def test_any_application_fine_tunes_through_the_incremental_stage(tmp_path, monkeypatch):
    """The incremental stage for an application other than the taxi: its `fine_tune`
    gets the training datasets and writes the checkpoint the loop is swept and solved
    with again; the report says what it returned, in the application's words; the
    cart itself, which defines no fine-tuning, is refused in one line."""
    monkeypatch.chdir(ROOT)                    # the run file's paths are relative
    (tmp_path / "tuned_cart.py").write_text(TUNED_CART)
    spec = _tiny(load_run_spec(ROOT / "examples" / "cart" / "run.yaml"))
    spec.grid, spec.horizon, spec.dataset.samples = [5, 5], 2.0, 10
    spec.scenario.camera.height, spec.scenario.camera.width = 24, 48
    spec.guard.candidates = spec.guard.noise_starts = spec.guard.check_starts = 0
    spec.fidelity.starts = 0
    spec.incremental.enabled, spec.incremental.environment = True, spec.test[0]
    with pytest.raises(ValueError, match=r"^incremental.enabled: the application 'cart' "
                                         r"defines no fine_tune; set incremental: "
                                         r"\{enabled: false\}$"):
        spec.validate()
    spec.application = f"{tmp_path / 'tuned_cart.py'}:TunedCart"
    spec.validate()
    out = _run_to_report(spec, tmp_path)
    inc = json.loads((out / "stages" / "incremental.json").read_text())["outputs"]
    train = tuple(f"{e.name}_" for e in spec.training_environments())
    labels = [np.load(d / "labels.npy") for d in (out / "datasets").iterdir()
              if d.name.startswith(train)]
    mined = sum(int((v == 1).sum()) for v in labels)
    assert len(labels) == len(train) and inc["environment"] == "KMWH_21h_clear"
    assert inc["fine_tune"]["mined_states"] == mined
    assert inc["fine_tune"]["fine_tune_seconds"] == 0.5
    assert (out / inc["checkpoint"]).read_text() == f"'' tuned on {mined} of {len(train)} datasets"
    assert Path(inc["checkpoint"]).name.startswith("controller_")
    # its metadata beside it, and nothing half-written left
    assert json.loads((out / f"{inc['checkpoint']}.json").read_text())["mined_states"] == mined
    assert not list((out / "incremental").glob("*.partial"))
    assert inc["after_record"]["brt_fraction"] == inc["after"]
    report = (out / "report.md").read_text()
    assert f"controller fine-tuned on {mined} anomalous states mined from the training" in report
    # the starred start's runs, for an application that says nothing more: stopped where
    # it reaches a rail, and no figure
    from reachwatch.reach.application import load_application
    tuned = load_application(spec.application)
    scenario = dc_replace(spec.scenario, environment=spec.test[0])
    run, failed = tuned.run_from(scenario, [0.4, 0.69], 1.0)
    assert failed and run.time[-1] <= run.failure_time < run.time[-1] + 0.1 + 1e-9
    assert np.all(np.abs(run.state[:-1, 0]) < 0.5)          # on the track until its last tick
    assert tuned.plot_runs([(run, "x")], scenario=scenario, path=tmp_path / "r.png") is None


def test_speed_car_guards_with_a_history_monitor_reading_the_controllers_signals(tmp_path):
    """The speed car's guarded loop offers a history monitor the same online signals a
    recording stores (the controller's estimate, then its steering)."""
    import torch
    from reachwatch.diagrams import MonitorConfig, save_checkpoint
    from reachwatch.systems import Environment, HistoryMonitorConfig, HistoryRiskModel
    config = HistoryMonitorConfig(height=16, width=24, channels=[4], features=4, signals=3,
                                  signal_mean=[0.0] * 3, signal_std=[1.0] * 3)
    torch.manual_seed(0)
    path = tmp_path / "history.pt"
    save_checkpoint(path, kind="history_monitor", model=HistoryRiskModel(config).eval(),
                    model_config=config, preprocess_config=None,
                    metadata={"calibration": [1.0, 0.0], "threshold": 0.5})
    car = _speed_car()
    diagram = car.make_car_loop(car.CarConfig(environment=Environment("KMWH", 9.0, "clear"),
                                              monitor=MonitorConfig(detector=str(path))))
    signals = diagram.GetSubsystemByName("monitor_signals")
    assert signals.get_output_port(0).size() == 3


BLIND_CART = '''
from reachwatch.reach.application import load_application

CartApplication = type(load_application("examples/cart/application.py:CartApplication"))


class BlindCart(CartApplication):
    """The cart whose "guarded" loop is its loop alone: it exports no speed, no flags."""
    def loop_diagram(self, scenario, *, guarded=False):
        return super().loop_diagram(scenario, guarded=False)
'''


def test_a_guarded_loop_without_speed_and_flags_is_refused_not_read_as_never_flagging(
        tmp_path, monkeypatch):
    """A guarded real run is judged by the speed and flags its loop exports: a loop that
    exports neither is a one-line error, not a run that never flagged at full speed."""
    from reachwatch.reach.application import load_application
    monkeypatch.chdir(ROOT)                    # the application's path is relative
    (tmp_path / "blind_cart.py").write_text(BLIND_CART)
    blind = load_application(f"{tmp_path / 'blind_cart.py'}:BlindCart")
    spec = load_run_spec(ROOT / "examples" / "cart" / "run.yaml")
    scenario = dc_replace(spec.scenario, environment=spec.test[0])
    scenario.camera.height, scenario.camera.width = 24, 48
    alone = blind.mission_rollouts(scenario, None, 0.3, np.array([[0.1, 0.0]]))
    assert alone["ticks"].tolist() == [3]
    with pytest.raises(ValueError, match=r"^the application 'cart': its guarded loop exports "
                                         r"no 'speed' and 'anomaly' .*judged by$"):
        blind.mission_rollouts(scenario, "brake", 0.3, np.array([[0.1, 0.0]]))
    # the guarded showcase (and `reachwatch simulate --loop guarded`) refuses it before
    # either loop runs
    from reachwatch.reach import loop_runs
    ran = []
    monkeypatch.setattr(loop_runs, "run_until_failed", lambda *a, **k: ran.append(a))
    with pytest.raises(ValueError, match=r"^the application 'cart': its guarded loop exports "
                                         r"no 'speed' and 'anomaly' .*figure reads$"):
        blind.simulate_guarded(scenario, [0.1, 0.0], tmp_path)
    assert not ran and not list(tmp_path.glob("*.png"))
