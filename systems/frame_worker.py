"""`FrameWorker`: a monitor's per-frame work (its resize and network) in a process of its
own, begun as soon as the tick's frame is rendered, so that it runs on another core while
the loop's controller works on the same frame.

A second thread would not do: the loop calls into Python many times a tick, and a
thread working in Python beside it holds the interpreter's lock between those calls
(measured slower than the work done in turn, docs/results/monitor/2026-12-07.md)."""

import itertools
import logging
import mmap
import os
import pickle
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import weakref
from multiprocessing.connection import Connection
from multiprocessing.reduction import recv_handle, send_handle

import numpy as np

from .checks import clip, warn_once

#: Seconds `FrameWorker` waits for an answer (the first includes its process's start,
#: which imports torch and Drake) before it gives the process up.
ANSWER_TIMEOUT_S = 120.0

_WORKERS = itertools.count()        # each worker's own key for what it says once


class FrameWorker:
    """Runs ``work`` (a picklable callable: one frame, a uint8 array, -> a float array)
    in a Python process of its own, on one thread (``OMP_NUM_THREADS=1``), started at
    the first `begin`. `begin` hands it a frame (through memory both processes map: one
    copy); `result` gives the work's answer for a frame of exactly those pixels
    (compared byte for byte), or None: nothing begun for these pixels, the answer an
    error, or the process gone; the caller then does the work itself, so an answer is
    always the one ``work(frame)`` gives in this process (the same code on the same
    pixels; the work must fix its own thread count, as `HistoryMonitor`'s does, for the
    same numbers).

    It gains when one loop drives it (contexts of one diagram simulated in turn share
    it: each `begin` waits for the other's answer) and the machine has a core to spare.
    The process imports what the work's unpickling needs (for a monitor: torch and
    Drake, about 0.34 GB of its own memory and 2 s before its first answer).
    A process gone, an answer that is an error, or an exception (an interrupt) while a
    frame or an answer is on its way ends the process; the first two are said once (the
    ``reachwatch`` logger). The process ends too when the worker is closed or
    collected, or with this one. ``name`` says whose work it is in what is said;
    ``answered`` counts the frames the process answered."""

    def __init__(self, work, *, name: str):
        try:
            self._work = pickle.dumps(work, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as error:
            raise TypeError(f"{name}: its frame work cannot go to a process of its own: "
                            f"{type(error).__name__}: {clip(error, 200)}") from None
        self._name = name
        self._key = ("frame worker", next(_WORKERS))
        self._lock = threading.Lock()   # loops on threads of one process may share it
        self._process = self._conn = self._finalizer = None
        self._pending = False           # the process works on the frame in `_shared`
        self._shared = None             # the last frame begun, in memory both map
        self._alive = True
        self.answered = 0               # frames whose answer came from the process

    @property
    def alive(self) -> bool:
        """Whether the process (started or not yet) still takes frames."""
        return self._alive

    def begin(self, frame: np.ndarray) -> None:
        """Hands ``frame`` to the process (an answer still pending is read and dropped
        first), starting the process the first time."""
        with self._lock:
            if self._alive:
                self._guarded(self._begin, frame)

    def result(self, frame: np.ndarray):
        """The work's answer for ``frame`` when it is the frame begun last, else None."""
        with self._lock:
            if not (self._alive and self._pending and self._shared.shape == frame.shape
                    and np.array_equal(self._shared, frame)):
                return None                     # a pending one is dropped at the next begin
            answer = self._guarded(self._receive)
        if isinstance(answer, str):
            self._give_up(f"its frame work failed in its own process ({clip(answer, 300)})")
            return None
        if answer is not None:
            self.answered += 1
        return answer

    def close(self) -> None:
        """Ends the process."""
        with self._lock:
            self._alive = self._pending = False
            if self._finalizer is not None:
                self._finalizer()

    def _guarded(self, step, *args):
        """``step(*args)``, the process given up when it is lost on the way, and for
        good when anything else (an interrupt) stops it half done: a frame or an answer
        left on the way would put the answers one frame behind."""
        try:
            return step(*args)
        except (OSError, EOFError, TimeoutError) as error:
            self._give_up(f"its frame work's own process ended ({type(error).__name__}: "
                          f"{clip(error, 200)})")
        except BaseException:
            self._give_up(None)
            raise

    def _begin(self, frame):
        if self._process is None:
            self._start()
        if self._pending:
            self._receive()                     # the process is done with `_shared`
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
        self._pending = True

    def _start(self):
        ours, theirs = socket.socketpair()
        # this process's imports, and one thread for every library that makes its own
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p),
                   OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-c", "from reachwatch.systems.frame_worker import serve; "
                 f"serve({theirs.fileno()})"], pass_fds=(theirs.fileno(),), env=env,
                stdin=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._finalizer = weakref.finalize(self, _stop, self._conn, self._process)
        self._conn.send_bytes(self._work)

    def _receive(self):
        self._pending = None                    # half read, should this stop here
        if not self._conn.poll(ANSWER_TIMEOUT_S):
            raise TimeoutError(f"no answer in {ANSWER_TIMEOUT_S:g} s")
        answer = self._conn.recv()
        self._pending = False
        return answer

    def _give_up(self, message):
        self._alive = self._pending = False
        if message is not None:
            warn_once(f"{self._name}: {message}; frames are worked in the loop from now on",
                      key=self._key)
        if self._finalizer is not None:
            self._finalizer()


def _mapped_frame(shape, dtype):
    """``(array, fd)``: a zeroed array of ``shape`` and ``dtype`` in memory mapped from
    a file that is already removed (Linux's /dev/shm, else the temporary folder), and
    an open descriptor of it to hand the worker's process (then close it): nothing is
    left behind when both are done."""
    folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
    fd, path = tempfile.mkstemp(prefix="reachwatch-frame-", dir=folder)
    try:
        os.unlink(path)
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        os.ftruncate(fd, size)
        return np.ndarray(shape, dtype, buffer=mmap.mmap(fd, size)), fd
    except BaseException:
        os.close(fd)
        raise


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
    the parent is gone; each answer is the work's float array, or an error's text (a
    work that cannot be loaded answers every frame so). An interrupt is the parent's to
    handle (a terminal's Ctrl-C reaches both)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig()
    conn = Connection(fd)
    try:
        data = conn.recv_bytes()
    except (EOFError, OSError):
        return
    try:
        work, failed = pickle.loads(data), None
    except Exception as error:
        work, failed = None, f"loading the work: {type(error).__name__}: {error}"
    frame = None
    try:
        while True:
            message = conn.recv()
            if message is None:
                return
            if message[0] == "map":
                _, shape, dtype = message
                shared = recv_handle(conn)
                size = int(np.prod(shape)) * np.dtype(dtype).itemsize
                frame = np.ndarray(shape, np.dtype(dtype),     # read-only: as it was sent
                                   buffer=mmap.mmap(shared, size, access=mmap.ACCESS_READ))
                os.close(shared)
                continue
            try:
                answer = failed if failed else np.asarray(work(frame))
            except Exception as error:  # said by the parent, which then works the frames
                answer = f"{type(error).__name__}: {error}"
            conn.send(answer)
    except (EOFError, OSError):         # the parent is gone
        return
