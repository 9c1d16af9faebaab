"""Fault injection with real processes: a sweep's spawned worker dies with its driver
(SIGKILL, SIGTERM, Ctrl-C), and the CLI stops on signals with one line saying what
was kept. Linux only (reads /proc)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from reachwatch.pipeline import cli

TESTS = Path(__file__).resolve().parent


# --- workers die with their driver -------------------------------------------------------

def _children(pid):
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def _alive(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _default_sigint():
    # A shell without job control starts background jobs with SIGINT ignored, and Python
    # then installs no Ctrl-C handler: give the driver the terminal default back.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_driver(cache, command=None):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen(command or [sys.executable, str(TESTS / "fault_helpers.py"), str(cache)],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True, preexec_fn=_default_sigint)
    deadline = time.time() + 120
    while time.time() < deadline:                 # the worker has written its first chunk
        if list(Path(cache).rglob("chunk_*.npz")):
            break
        assert process.poll() is None, process.communicate()
        time.sleep(0.2)
    else:
        process.kill()
        pytest.fail("the sweep never wrote a chunk")
    workers = [k for k in _children(process.pid) if _alive(k)]
    assert workers, "no spawned worker found"
    return process, workers


def _assert_workers_stop(workers, cache, within=10.0):
    deadline = time.time() + within
    while time.time() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers), "a sweep worker outlived its driver"
    count = len(list(Path(cache).rglob("chunk_*.npz")))
    time.sleep(1.0)
    assert len(list(Path(cache).rglob("chunk_*.npz"))) == count, "chunks still being written"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT])
def test_sweep_worker_dies_with_its_driver(tmp_path, sig):
    """Before: SIGTERM/SIGKILL left the spawned worker running and writing chunks."""
    process, workers = _start_driver(tmp_path)
    if sig == signal.SIGINT:
        os.killpg(process.pid, sig)                  # a terminal's Ctrl-C reaches the group
    else:
        os.kill(process.pid, sig)
    process.wait(30)
    _assert_workers_stop(workers, tmp_path)
    done = len(list(tmp_path.rglob("chunk_*.npz")))
    assert 0 < done < 400                           # finished chunks are kept


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig, word, code", [(signal.SIGTERM, "terminated", 143),
                                             (signal.SIGINT, "interrupted", 130)])
def test_cli_stops_on_signals_with_one_line_saying_what_was_kept(tmp_path, sig, word, code):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("environment: {runway: KMWH}\n")
    cache = tmp_path / "cache"
    command = [sys.executable, "-m", "reachwatch.pipeline.cli", "sweep", "--scenario",
               str(scenario), "--shape", "30", "30", "30", "--chunk-size", "16",
               "--cache", str(cache), "--out", str(tmp_path / "out")]
    process, workers = _start_driver(cache, command)
    if sig == signal.SIGINT:
        os.killpg(process.pid, sig)
    else:
        os.kill(process.pid, sig)
    _, err = process.communicate(timeout=60)
    assert process.returncode == code, err
    lines = [line for line in err.splitlines() if "Traceback" in line or word in line]
    assert lines == [f"reachwatch sweep: {word}; {cli.KEPT}"], err
    _assert_workers_stop(workers, cache)


_STUCK = """
import signal, sys, threading, time
from reachwatch.pipeline import cli
cli.STOP_GRACE_S = float(sys.argv[1])
signal.signal(signal.SIGTERM, cli._stop)
try:
    print("ready", flush=True)
    time.sleep(60)
except cli.Terminated:
    threading.Event().wait(60)      # unwinding hangs (e.g. a lock a dead thread held)
"""


@pytest.mark.parametrize("grace, signals, message", [
    (1.0, 1, "still stopping 1 s after the signal"), (60.0, 2, "stopped again")])
def test_a_stop_that_hangs_while_unwinding_still_exits(grace, signals, message):
    """After a stop signal the process exits within `STOP_GRACE_S` even when unwinding
    hangs, and at once on a second signal, saying so in one line."""
    process = subprocess.Popen([sys.executable, "-c", _STUCK, str(grace)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "ready"
    started = time.time()
    for _ in range(signals):
        process.send_signal(signal.SIGTERM)
        time.sleep(0.5)
    _, err = process.communicate(timeout=30)
    assert process.returncode == 143 and time.time() - started < 20
    assert err.strip() == f"reachwatch: {message}; exiting now; {cli.KEPT}"
