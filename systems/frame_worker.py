"""`FrameWorker`: a monitor's per-frame work (its resize and network) in a process of its
own, begun as soon as the tick's frame is rendered, so that it runs on another core while
the loop's controller works on the same frame.

A second thread would not do: the loop calls into Python many times a tick, and a
thread working in Python beside it holds the interpreter's lock between those calls
(measured slower than the work done in turn, docs/results/monitor/2026-12-07.md)."""

import logging
import mmap
import os
import pickle
import socket
import subprocess
import sys
import tempfile
import weakref
from multiprocessing.connection import Connection
from multiprocessing.reduction import recv_handle, send_handle

import numpy as np

from .checks import clip, warn_once

#: Seconds `FrameWorker` waits for an answer (the first includes its process's start,
#: which imports torch and Drake) before it gives the process up.
ANSWER_TIMEOUT_S = 120.0


class FrameWorker:
    """Runs ``work`` (a picklable callable: one frame, a uint8 array, -> a float array)
    in a Python process of its own, started here, on one thread (``OMP_NUM_THREADS=1``).
    `begin` hands it a frame (through memory both processes map: one copy); `result`
    gives the work's answer for a frame of exactly those pixels (compared byte for
    byte), or None: nothing begun for these pixels, the answer an error, or the process
    gone; the caller then does the work itself, so an answer is always the one
    ``work(frame)`` gives in this process (the same code on the same pixels; the work
    must fix its own thread count, as `HistoryMonitor`'s does, for the same numbers).

    A process gone or an answer that is an error is said once (the ``reachwatch``
    logger) and the worker stops asking it. The process ends when the worker is closed
    or collected, or with this one. ``name`` says whose work it is in what is said;
    ``answered`` counts the frames the process answered."""

    def __init__(self, work, *, name: str):
        self._name = name
        self._pending = False           # the process works on the frame in `_shared`
        self._shared = None             # the last frame begun, in memory both map
        self._alive = True
        self.answered = 0               # frames whose answer came from the process
        ours, theirs = socket.socketpair()
        # this process's imports, and one thread for every library that makes its own
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p),
                   OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-c", "from reachwatch.systems.frame_worker import serve; "
                 f"serve({theirs.fileno()})"], pass_fds=(theirs.fileno(),), env=env,
                stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._conn.send_bytes(pickle.dumps(work, protocol=pickle.HIGHEST_PROTOCOL))
        self._finalizer = weakref.finalize(self, _stop, self._conn, self._process)

    @property
    def alive(self) -> bool:
        """Whether the process still takes frames."""
        return self._alive

    def begin(self, frame: np.ndarray) -> None:
        """Hands ``frame`` to the process (an answer still pending is read and dropped
        first)."""
        if not self._alive:
            return
        if self._pending:
            self._pending = False
            self._receive()
        try:
            if self._shared is None or self._shared.shape != frame.shape or \
                    self._shared.dtype != frame.dtype:
                self._shared, fd = _mapped_frame(frame.shape, frame.dtype)
                try:
                    self._conn.send(("map", frame.shape, frame.dtype.str))
                    send_handle(self._conn, fd, self._process.pid)
                finally:
                    os.close(fd)
            np.copyto(self._shared, frame)
            self._conn.send(("frame",))
        except OSError as error:
            return self._lost(error)
        self._pending = True

    def result(self, frame: np.ndarray):
        """The work's answer for ``frame`` when it is the frame begun last, else None."""
        if not self._pending or self._shared.shape != frame.shape or \
                not np.array_equal(self._shared, frame):
            return None                         # a pending one is dropped at the next begin
        self._pending = False
        answer = self._receive()
        if isinstance(answer, str):
            self._alive = False
            warn_once(f"{self._name}: its frame work failed in its own process "
                      f"({clip(answer, 300)}); frames are worked in the loop from now on",
                      key=("frame worker", id(self)))
            return None
        if answer is not None:
            self.answered += 1
        return answer

    def close(self) -> None:
        """Ends the process."""
        self._alive = False
        self._finalizer()

    def _receive(self):
        try:
            if not self._conn.poll(ANSWER_TIMEOUT_S):
                raise TimeoutError(f"no answer in {ANSWER_TIMEOUT_S:g} s")
            return self._conn.recv()
        except (OSError, EOFError, TimeoutError) as error:
            self._lost(error)
            return None

    def _lost(self, error):
        self._alive = False
        self._pending = False
        warn_once(f"{self._name}: its frame work's own process ended "
                  f"({type(error).__name__}: {clip(error, 200)}); frames are worked in the "
                  f"loop from now on", key=("frame worker", id(self)))
        self._finalizer()


def _mapped_frame(shape, dtype):
    """``(array, fd)``: a zeroed array of ``shape`` and ``dtype`` in memory mapped from
    a file that is already removed (Linux's /dev/shm, else the temporary folder), and
    an open descriptor of it to hand the worker's process (then close it): nothing is
    left behind when both are done."""
    folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
    fd, path = tempfile.mkstemp(prefix="reachwatch-frame-", dir=folder)
    os.unlink(path)
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    os.ftruncate(fd, size)
    return np.ndarray(shape, dtype, buffer=mmap.mmap(fd, size)), fd


def _stop(conn, process):
    """Ends the process of a `FrameWorker` (no reference to it: a finalizer's)."""
    try:
        conn.send(None)
    except OSError:
        pass
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    conn.close()


def serve(fd: int) -> None:
    """The worker process's loop: the work, then frames until told to stop (None) or
    the parent is gone; each answer is the work's float array, or an error's text."""
    logging.basicConfig()
    conn = Connection(fd)
    work = pickle.loads(conn.recv_bytes())
    frame = None
    while True:
        try:
            message = conn.recv()
            if message is None:
                return
            if message[0] == "map":
                _, shape, dtype = message
                shared = recv_handle(conn)
                size = int(np.prod(shape)) * np.dtype(dtype).itemsize
                frame = np.ndarray(shape, np.dtype(dtype), buffer=mmap.mmap(shared, size))
                os.close(shared)
                continue
        except (EOFError, OSError):
            return
        try:
            conn.send(np.asarray(work(frame)))
        except Exception as error:      # said by the parent, which then works the frames
            conn.send(f"{type(error).__name__}: {error}")
