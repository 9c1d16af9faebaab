"""Fault injection: killed and terminated drivers, truncated and deleted artifacts,
read-only folders, malformed inputs. Each test states the fault and the outcome."""

import json
import logging
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from reachwatch.diagrams import ScenarioError, load_scenario, make_state_feedback_diagram, simulate
from reachwatch.pipeline import cli, console
from reachwatch.pipeline.executors import make_executor
from reachwatch.pipeline.run import run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.brt_stages import sweep_rate
from reachwatch.reach import InlineExecutor, Probe, default_executor, sweep
from reachwatch.taxi import OffRunway, paper_grid
from tiny_run import TINY, taxi_application

TESTS = Path(__file__).resolve().parent
FEEDBACK = Probe(plant="taxi_plant", control_port="p_controller.steering_angle",
                 extra_ports=("state_estimator.estimate",))



def _feedback_factory():
    import functools
    return functools.partial(make_state_feedback_diagram, load_scenario(data=""))


# --- sweeps: progress, labels, bad chunks ---------------------------------------------------

def test_sweep_progress_moves_per_state_and_label_keeps_the_shape(tmp_path, monkeypatch):
    """Before: the bar moved per 1024-state chunk; its label cut the grid shape."""
    sweep_module = sys.modules["reachwatch.reach.sweep"]
    bars = []

    class Bar:
        def __init__(self, total=None, initial=0, desc="", **kw):
            self.n, self.total, self.desc, self.updates = initial, total, desc, []
            bars.append(self)

        def update(self, k):
            self.n += k
            self.updates.append(k)

        def close(self):
            pass
    monkeypatch.setattr(sweep_module, "tqdm", Bar)
    g = paper_grid(10.0, (4, 3, 3))
    table = sweep(_feedback_factory(), g, key="k" * 40, cache_dir=tmp_path, probe=FEEDBACK,
                  executor=InlineExecutor(), chunk_size=1000, label="KMWH_9h_clear 4x3x3")
    assert bars[0].updates == [1] * g.size and bars[0].desc == "sweep KMWH_9h_clear 4x3x3"
    assert table.computed == g.size
    # the spawned pool counts every state it evaluates
    executor = default_executor()
    try:
        table = sweep(_feedback_factory(), g, key="pool", cache_dir=tmp_path, probe=FEEDBACK,
                      executor=executor, chunk_size=1000)
        assert executor.progress_counter.value == g.size and bars[-1].n == g.size
    finally:
        executor.shutdown()
    again = sweep(_feedback_factory(), g, key="pool", cache_dir=tmp_path, probe=FEEDBACK)
    assert again.computed == 0                        # all cached: nothing rendered
    assert sweep_rate({"states": g.size, "rendered": 0, "sweep_seconds": 0.0}) == "cached"
    assert sweep_rate({"states": 36, "rendered": 36, "sweep_seconds": 2.0}) == "18"


def test_chunk_missing_a_port_is_recomputed(tmp_path):
    """Before: a chunk file lacking a port was a KeyError traceback."""
    g = paper_grid(10.0, (4, 3, 3))
    good = sweep(_feedback_factory(), g, key="f", cache_dir=tmp_path, probe=FEEDBACK,
                 executor=InlineExecutor(), chunk_size=12, progress=False)
    chunk = tmp_path / "f" / "chunk_000001.npz"
    with np.load(chunk) as data:
        np.savez(chunk, start=data["start"], stop=data["stop"], port0=data["port0"])  # port1 gone
    again = sweep(_feedback_factory(), g, key="f", cache_dir=tmp_path, probe=FEEDBACK,
                  executor=InlineExecutor(), chunk_size=12, progress=False)
    assert again.computed == 12
    for port in FEEDBACK.ports:
        np.testing.assert_array_equal(again[port], good[port])


@pytest.mark.parametrize("chunk_size", [0, -5, 2.5])
def test_bad_chunk_size_is_an_error(tmp_path, chunk_size):
    with pytest.raises(ValueError, match="chunk_size must be a whole number >= 1"):
        sweep(_feedback_factory(), paper_grid(10.0, (3, 3, 3)), key="x", cache_dir=tmp_path,
              probe=FEEDBACK, executor=InlineExecutor(), chunk_size=chunk_size)


# --- run directories: deleted, truncated, torn, read-only --------------------------------

@pytest.fixture(scope="module")
def solved_run(tmp_path_factory, seed_caches):
    out = seed_caches(tmp_path_factory.mktemp("run"))
    run_pipeline(load_run_spec(data=TINY), out, until="solve", progress=False, log=lambda m: None)
    return out


def _rerun(out, until="solve"):
    log = []
    run_pipeline(load_run_spec(data=TINY), out, until=until, progress=False, log=log.append)
    return log


def _copy(src, dst):
    import shutil
    shutil.copytree(src, dst)
    return dst


def test_deleted_and_truncated_outputs_rerun_their_stage(solved_run, tmp_path):
    """Before: with brt/ deleted every stage said "up to date"; a truncated .npz later
    failed with a raw BadZipFile traceback."""
    out = _copy(solved_run, tmp_path / "run")
    assert not any("running" in m for m in _rerun(out))
    values = sorted((out / "brt").glob("*.npz"))
    values[0].unlink()
    log = _rerun(out)
    assert any("running: its output brt/" in m and "is missing" in m for m in log), log
    assert values[0].is_file()
    data = values[1].read_bytes()
    values[1].write_bytes(data[:len(data) // 2])
    log = _rerun(out)
    assert any("changed size" in m for m in log), log
    assert values[1].read_bytes() == data            # rebuilt identically
    figure = sorted((out / "figures").glob("brt_*.png"))[0]
    figure.write_bytes(figure.read_bytes()[::-1])     # same size, other bytes
    assert any("changed content" in m for m in _rerun(out))
    from reachwatch.reach import ValueFunction
    values[1].write_bytes(data[:100])
    with pytest.raises(ValueError, match="not a readable value function: BadZipFile"):
        ValueFunction.load(values[1])


@pytest.mark.parametrize("content", ['"done"', '{"key": "abc"}', "{ torn", "[]"])
def test_malformed_records_rerun_their_stage(solved_run, tmp_path, content):
    """Before: a record holding "done" or lacking outputs was a traceback."""
    out = _copy(solved_run, tmp_path / "run")
    record = sorted((out / "stages").glob("solve_*.json"))[0]
    record.write_text(content)
    log = _rerun(out)
    assert any(f"record {record} is corrupt" in m for m in log), log
    assert json.loads(record.read_text())["stage"] == record.stem


def test_read_only_run_directory(solved_run, tmp_path, monkeypatch):
    """Before: a read-only run directory was a traceback even with nothing to do."""
    from reachwatch.pipeline import stages
    out = _copy(solved_run, tmp_path / "run")
    writes = []
    monkeypatch.setattr(stages, "atomic_write_bytes", lambda *a, **k: writes.append(a))
    assert not any("running" in m for m in _rerun(out)) and writes == []   # nothing written
    monkeypatch.undo()
    (out / "stages" / "dataset.json").unlink(missing_ok=True)
    if os.geteuid() != 0:
        out.chmod(0o555)
    else:                       # root writes anywhere: fake the permission check instead
        monkeypatch.setattr(stages.os, "access", lambda path, mode: Path(path) != out)
    try:
        with pytest.raises(ValueError, match=f"the run directory {out} is not writable, and "
                                             f"the run needs it to run stage dataset"):
            _rerun(out, until="dataset")
    finally:
        out.chmod(0o755)


def test_stage_keys_do_not_depend_on_wall_time(tmp_path):
    """Before: the detector checkpoint held train_seconds, so identical runs had other
    checkpoint hashes and stage keys."""
    from reachwatch.diagrams import file_hash
    from reachwatch.reach import solve_brt
    from reachwatch.taxi import TaxiDynamics
    from reachwatch.training.dataset import DatasetSpec, build_dataset, load_dataset
    from reachwatch.training.detector_train import DetectorTrainConfig, train_detector
    from reachwatch.systems import DetectorConfig
    grid = paper_grid(10.0, (5, 3, 5))
    px, _, th = grid.mesh()
    vf = solve_brt(grid, TaxiDynamics(half_width=10.0),
                   np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th) + 8.0), horizon=2.0, device="cpu")
    spec = DatasetSpec(samples=16, height=24, width=40, chunk_size=16)
    data = [load_dataset(build_dataset(tmp_path, load_scenario(data=""), vf, spec, progress=False, application=taxi_application()))]
    config = DetectorTrainConfig(detector=DetectorConfig(height=24, width=40, channels=[4, 8]),
                                 epochs=1, batch_size=8, device="cpu")
    first = train_detector(data, config, tmp_path / "a.pt")
    time.sleep(0.2)
    train_detector(data, config, tmp_path / "b.pt")
    assert "train_seconds" in first
    assert file_hash(tmp_path / "a.pt") == file_hash(tmp_path / "b.pt")


def test_truncated_dataset_array_names_the_file(tmp_path):
    """Before: a truncated memmap failed with numpy's message and no file name."""
    from reachwatch.reach import solve_brt
    from reachwatch.taxi import TaxiDynamics
    from reachwatch.training.dataset import DatasetSpec, build_dataset, load_dataset
    grid = paper_grid(10.0, (5, 3, 5))
    vf = solve_brt(grid, TaxiDynamics(half_width=10.0), np.zeros(grid.shape), horizon=1.0,
                   device="cpu")
    spec = DatasetSpec(samples=12, height=16, width=24, chunk_size=12)
    folder = build_dataset(tmp_path, load_scenario(data=""), vf, spec, progress=False, application=taxi_application())
    images = folder / "images.npy"
    images.write_bytes(images.read_bytes()[:500])
    with pytest.raises(ValueError, match=f"{images} is unreadable.*delete {folder}"):
        load_dataset(folder)
    with pytest.raises(ValueError, match=f"{images} is unreadable.*delete {folder}"):
        build_dataset(tmp_path, load_scenario(data=""), vf, spec, progress=False, application=taxi_application())   # resuming
    (folder / "manifest.json").write_text("{ torn")
    with pytest.raises(ValueError, match=f"{folder} is not a readable reachwatch dataset"):
        load_dataset(folder)


# --- malformed inputs ------------------------------------------------------------------------

@pytest.mark.parametrize("text, message", [
    ("environment: {hour: 9.0, hour: 21.0}\n", "line 1: key 'hour' is written twice"),
    ("# only a comment\n\n", "is empty; write '{}' for all defaults"),
    (b"\x89PNG\r\n\x1a\n\x00\x00binary", "not a text YAML file"),
    (b"\xff\xfe junk", "not a UTF-8 text YAML file"),
    ("controller: {period: 0.0}\n", "controller.period must be a finite number in \\(0, 10\\] s"),
    ("controller: {period: .inf}\n", "controller.period must be a finite number in \\(0, 10\\] s"),
])
def test_bad_scenario_files(tmp_path, text, message):
    path = tmp_path / "s.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ScenarioError, match=message.replace("{", r"\{").replace("}", r"\}")):
        load_scenario(path)
    assert cli.main(["render", "--scenario", str(path), "--out", str(tmp_path)]) == 2


@pytest.mark.parametrize("edit, message", [
    (("epochs: 1", "epochs: 0"), "detector.epochs must be a whole number in [1, 100000]"),
    (("batch_size: 8", "batch_size: 8\n  validation_fraction: 1.5"),
     "detector.validation_fraction must be a finite number in [0, 1)"),
    (("batch_size: 8", "batch_size: 8\n  target_recall: 2.0"), "detector.target_recall must be a finite number in [0, 1]"),
    (("batch_size: 8", "batch_size: 8\n  validation_fraction: 0.0"), "needs a validation split"),
    (("horizon: 4.0", "horizon: .inf"), "horizon must be a finite number in (0, 120] s"),
    (("horizon: 4.0", "horizon: 0.0"), "horizon must be a finite number in (0, 120] s"),
    (("chunk_size: 16", "chunk_size: 0"), "dataset.chunk_size must be a whole number in [1, 100000]"),
    (("online_seconds: 0.2", "online_seconds: 0.0"), "guard.online_seconds must be"),
    (("ensemble: {seeds: [1, 2], samples: 48", "ensemble: {seeds: [1, 2], samples: 0"),
     "ensemble.samples must be a whole number in [1, 1000000]"),
])
def test_bad_run_files_are_named_and_exit_2(tmp_path, edit, message):
    assert edit[0] in TINY
    path = tmp_path / "run.yaml"
    path.write_text(TINY.replace(*edit))
    with pytest.raises(ScenarioError, match=message.replace("[", r"\[").replace("(", r"\(")
                       .replace(")", r"\)")):
        load_run_spec(path)
    assert cli.main(["run", "--scenario", str(path), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()             # nothing created for a bad run file


@pytest.mark.parametrize("state", [[np.nan, 110.0, 0.0], [0.0, np.inf, 0.0], [0.0, 110.0]])
def test_simulate_rejects_bad_start_states(state):
    diagram = make_state_feedback_diagram(load_scenario(data=""))
    with pytest.raises(ValueError, match="initial state must be a vector of finite numbers|has 3 continuous states .*, the initial state 2"):
        simulate(diagram, initial_state=state, duration=1.0, period=0.05, failed=OffRunway(10.0))


@pytest.mark.parametrize("argv, message", [
    (["brt", "--drake-starts", "-3"], "--drake-starts: '-3' is not a whole number >= 0"),
    (["sweep", "--chunk-size", "0"], "--chunk-size: '0' is not a whole number >= 1"),
    (["sweep", "--chunk-size", "-5"], "--chunk-size: '-5' is not a whole number >= 1"),
    (["brt", "--horizon", "inf"], "--horizon: 'inf' is not a finite number > 0"),
    (["brt", "--solved-theta-deg", "200"],
     "--solved-theta-deg: '200' is not a number of degrees in [28, 180]"),
    (["sweep", "--solved-py-max", "120"], "--solved-py-max: '120' is not a finite number of metres >= 250"),
    (["guard", "--scenario", "x", "--horizon", "0"], "--horizon: '0' is not a finite number > 0"),
    (["guard", "--scenario", "x", "--fallbacks", "slow_down+gps"],
     "--fallbacks: fallback 'slow_down+gps': write a speed strategy"),
])
def test_bad_numbers_on_the_command_line_fail_before_any_work(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as stop:
        cli.main(argv + ["--out", str(tmp_path / "o")])
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_unreachable_dask_scheduler_is_one_clear_error():
    pytest.importorskip("dask.distributed")
    import socket
    with socket.socket() as s:               # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.time()
    with pytest.raises(ValueError, match=f"no Dask scheduler answered at tcp://127.0.0.1:{port}: "
                                         f"connection refused"):
        make_executor(f"dask://127.0.0.1:{port}", connect_timeout=1.0)
    assert time.time() - started < 20
    with pytest.raises(ValueError, match="^--executor dask://no-such-host.invalid:8786: cannot "
                                         "resolve the host 'no-such-host.invalid'"):
        make_executor("dask://no-such-host.invalid:8786", connect_timeout=1.0)



def test_a_service_that_is_not_a_dask_scheduler_is_one_clear_error():
    """Something that accepts the connection and never speaks Dask (a web server where
    the scheduler should be, say): Dask's timeout does not cover the handshake; one line
    within the timeout and 5 s."""
    pytest.importorskip("dask.distributed")
    import socket
    import threading
    listener = socket.create_server(("127.0.0.1", 0))
    port, held = listener.getsockname()[1], []

    def accept():
        try:
            while True:
                held.append(listener.accept()[0])      # accepted, never answered
        except OSError:
            pass
    threading.Thread(target=accept, daemon=True).start()
    started = time.time()
    try:
        with pytest.raises(ValueError, match=rf"^--executor dask://127.0.0.1:{port}: .*"
                                             rf"tcp://127.0.0.1:{port}.*(answer|scheduler)"):
            make_executor(f"dask://127.0.0.1:{port}", connect_timeout=1.0)
    finally:
        listener.close()
        for connection in held:
            connection.close()
    assert time.time() - started < 15

# --- CLI hygiene ---------------------------------------------------------------------------

def test_version_and_quiet_and_verbose(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("reachwatch ")
    with pytest.raises(SystemExit) as stop:
        cli.main(["-q", "-v", "render", "--out", "x"])      # mutually exclusive
    assert stop.value.code == 2 and "not allowed with" in capsys.readouterr().err
    console.setup(-1)
    assert not console.progress_enabled() and not console.log.isEnabledFor(logging.INFO)
    console.setup(1)
    assert console.progress_enabled() and console.log.isEnabledFor(logging.DEBUG)
    console.setup(0)


def test_warnings_become_one_line(capsys):
    console.setup(0)
    saved = warnings.showwarning
    try:
        console.setup(0)
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = console._warning_line
            warnings.warn("graphviz 'dot' not found; wrote only the .dot file", UserWarning)
    finally:
        warnings.showwarning = saved
    err = capsys.readouterr().err
    assert err == "warning: graphviz 'dot' not found; wrote only the .dot file\n"


def test_bad_detector_never_opens_meshcat(tmp_path, monkeypatch):
    """Before: a bad detector file started a Meshcat server on port 7000 first."""
    from reachwatch.taxi import guarded_run
    opened = []
    monkeypatch.setattr(guarded_run, "meshcat_replay_html", lambda *a: opened.append(1))
    bad = tmp_path / "detector.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        # refused as the scenario loads: its threshold would be the checkpoint's
        scenario = load_scenario(data=f"monitor: {{detector: {bad}}}\nduration: 0.2\n")
        guarded_run.simulate_guarded(scenario, tmp_path)
    assert opened == []
