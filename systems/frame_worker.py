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
import time
import weakref
from multiprocessing.connection import Connection
from multiprocessing.reduction import recv_handle, send_handle

import numpy as np

from .checks import clip, warn_once

#: Seconds `FrameWorker` waits for an answer to a frame before it gives the process up.
ANSWER_TIMEOUT_S = 120.0

_WORKERS = itertools.count()        # each worker's own key for what it says once


class FrameWorker:
    """Runs ``work`` (a picklable callable: one frame, a uint8 array, -> a float array)
    in a Python process of its own, on one thread (``OMP_NUM_THREADS=1``). `begin`
    hands it a frame (through memory both processes map: one copy); `result` gives the
    work's answer for a frame of exactly those pixels (compared byte for byte), or
    None: nothing begun for these pixels, the process not ready yet, the answer an
    error, or the process gone; `work` then does the work here, so an answer is
    always the one ``work(frame)`` gives in this process (the same code on the same
    pixels; the work must fix its own thread count, as `HistoryMonitor`'s does, for the
    same numbers).

    The process starts at the first `begin` (or `start`) and takes frames once it has
    loaded the work: it imports ``reachwatch.systems`` (torch and Drake: about 2 s and
    0.34 GB of its own memory, measured for a monitor) and unpickles the work; until
    then the caller works every frame, and no tick waits for it. It gains when one loop drives it (contexts of one
    diagram simulated in turn share it: each `begin` waits for the other's answer) and
    the machine has a core to spare. A process gone or an answer that is an error is
    said once (the ``reachwatch`` logger) and ends it; so does an exception (an
    interrupt) while a frame or an answer is on its way, which would put the answers
    one frame behind, unsaid. It ends too when the worker is closed or collected, or
    with this process. ``name`` says whose work it is in what is said; ``answered``
    counts the frames the process answered."""

    def __init__(self, work, *, name: str):
        try:
            self._work = pickle.dumps(work, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as error:
            raise TypeError(f"{name}: its frame work cannot go to a process of its own: "
                            f"{type(error).__name__}: {clip(error, 200)}") from None
        self._name = name
        self._local = work              # the same work, done here when no answer comes
        self._key = ("frame worker", next(_WORKERS))
        self._lock = threading.Lock()   # loops on threads of one process may share it
        self._process = self._conn = self._finalizer = None
        self._ready = False             # the process has loaded the work
        self._pending = False           # the process works on the frame in `_shared`
        self._shared = None             # the last frame begun, in memory both map
        self._alive = True
        self.answered = 0               # frames whose answer came from the process

    @property
    def alive(self) -> bool:
        """Whether the process (started or not yet) still takes frames."""
        return self._alive

    def start(self, *, wait: float = 0.0) -> bool:
        """Starts the process if it is not started, and waits up to ``wait`` s for it to
        load the work; returns whether it takes frames now."""
        with self._lock:
            if self._alive:
                self._guarded(self._start_and_wait, float(wait))
            return self._alive and self._ready

    def begin(self, frame: np.ndarray) -> None:
        """Hands ``frame`` to the process (an answer still pending is read and dropped
        first), starting the process the first time; a frame that comes before the
        process is ready is left to the caller."""
        with self._lock:
            if self._alive:
                self._guarded(self._begin, frame)

    def result(self, frame: np.ndarray):
        """The work's answer for ``frame`` when it is the frame begun last, else None."""
        with self._lock:
            if not (self._alive and self._pending and self._shared.shape == frame.shape
                    and self._shared.dtype == frame.dtype
                    and np.array_equal(self._shared, frame)):
                return None                     # a pending one is dropped at the next begin
            answer = self._guarded(self._receive)
            if answer is not None:
                self.answered += 1
            return answer

    def work(self, frame: np.ndarray):
        """The work's answer for ``frame``: the process's, when it answered for exactly
        these pixels (`result`), else the work done here."""
        answer = self.result(frame)
        return self._local(frame) if answer is None else answer

    def close(self) -> None:
        """Ends the process."""
        with self._lock:
            self._alive = self._pending = False
            if self._finalizer is not None:
                self._finalizer()

    def _guarded(self, step, *args):
        """``step(*args)``; the process is given up when it is lost on the way, and at
        once when anything else (an interrupt) stops the step half done."""
        try:
            return step(*args)
        except TimeoutError as error:
            self._give_up(f"its frame work's own process did not answer ({error})")
        except (OSError, EOFError) as error:
            self._give_up(f"its frame work's own process ended ({type(error).__name__}: "
                          f"{clip(error, 200)})")
        except BaseException:
            if self._process is not None:
                self._process.kill()
            self._give_up(None)
            raise

    def _start_and_wait(self, wait):
        if self._process is None:
            self._start()
        deadline = time.monotonic() + wait
        while not self._ready and self._alive:
            if not self._conn.poll(max(0.0, deadline - time.monotonic())):
                return
            self._loaded(self._conn.recv())

    def _begin(self, frame):
        if self._process is None:
            self._start()
        if not self._ready:
            if not self._conn.poll(0):
                return                          # still loading: the caller works this one
            self._loaded(self._conn.recv())
            if not self._alive:
                return
        if self._pending:
            self._receive()                     # the process is done with `_shared`
            if not self._alive:
                return
        if self._shared is None or self._shared.shape != frame.shape or \
                self._shared.dtype != frame.dtype:
            raw, fd = _mapped(frame.nbytes)
            self._shared = raw.view(frame.dtype).reshape(frame.shape)
            try:
                self._conn.send(("map", frame.shape, frame.dtype.str))
                send_handle(self._conn, fd, self._process.pid)
            finally:
                os.close(fd)
        np.copyto(self._shared, frame)
        self._conn.send(("frame",))
        self._pending = True

    def _loaded(self, message):
        if message == "ready":
            self._ready = True
        else:
            self._give_up(f"its frame work failed in its own process ({clip(message, 300)})")

    def _start(self):
        """Starts the process (its own session: a terminal's Ctrl-C is this process's to
        handle), handing it the work through a file it inherits."""
        ours, theirs = socket.socketpair()
        work, fd = _mapped(len(self._work))
        work[:] = np.frombuffer(self._work, np.uint8)
        os.lseek(fd, 0, os.SEEK_SET)
        # this process's imports, and one thread for every library that makes its own
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p),
                   OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-c", "from reachwatch.systems.frame_worker import serve; "
                 f"serve({theirs.fileno()}, {fd}, {len(self._work)})"],
                pass_fds=(theirs.fileno(), fd), env=env, stdin=subprocess.DEVNULL,
                start_new_session=True)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
            os.close(fd)
        self._conn = Connection(ours.detach())
        self._finalizer = weakref.finalize(self, _stop, self._conn, self._process)

    def _receive(self):
        if not self._conn.poll(ANSWER_TIMEOUT_S):
            raise TimeoutError(f"no answer in {ANSWER_TIMEOUT_S:g} s")
        answer = self._conn.recv()
        self._pending = False
        if isinstance(answer, str):
            self._give_up(f"its frame work failed in its own process ({clip(answer, 300)})")
            return None
        return answer

    def _give_up(self, message):
        self._alive = self._pending = False
        if message is not None:
            warn_once(f"{self._name}: {message}; frames are worked in the loop from now on",
                      key=self._key)
        if self._finalizer is not None:
            self._finalizer()


def add_frame_worker(system, *, work, image_port, period: float, name: str) -> FrameWorker:
    """A `FrameWorker` of ``work`` for ``system`` (a LeafSystem), which hands it the
    frame on ``image_port`` at a publish event every ``period`` s (the control tick's,
    when the frame is rendered); read the answer with `FrameWorker.work`."""
    worker = FrameWorker(work, name=name)
    system.DeclarePeriodicPublishEvent(
        period, 0.0, lambda context: worker.begin(image_port.Eval(context).data))
    return worker


def _mapped(size: int):
    """``(bytes, fd)``: ``size`` zeroed bytes (uint8) in memory mapped from a file that
    is already removed (Linux's /dev/shm, else the temporary folder), and an open
    descriptor of it to hand the worker's process (then close it): nothing is left
    behind when both are done."""
    folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
    fd, path = tempfile.mkstemp(prefix="reachwatch-frame-", dir=folder)
    try:
        os.unlink(path)
        size = max(int(size), 1)
        if hasattr(os, "posix_fallocate"):
            # the blocks taken now: a full /dev/shm is an OSError here, not a SIGBUS
            # when the memory is first written
            os.posix_fallocate(fd, 0, size)
        else:
            os.ftruncate(fd, size)
        return np.frombuffer(mmap.mmap(fd, size), np.uint8), fd
    except BaseException:
        os.close(fd)
        raise


def _stop(conn, process):
    """Ends the process of a `FrameWorker` (no reference to it: a finalizer's): told to
    stop, then its end of the connection closed (it stops at either), then killed if it
    has not within 10 s."""
    try:
        conn.send(None)
    except OSError:
        pass
    conn.close()
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def serve(fd: int, work_fd: int, size: int) -> None:
    """The worker process's loop: loads the work (``size`` bytes from ``work_fd``),
    says it is ready (or why not, and stops), then answers frames until told to stop
    (None) or the parent is gone; each answer is the work's float array, or an error's
    text."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig()
    conn = Connection(fd)
    try:
        with os.fdopen(work_fd, "rb") as file:
            work = pickle.loads(file.read(size))
    except Exception as error:
        try:
            conn.send(f"loading the work: {type(error).__name__}: {error}")
        except OSError:
            pass
        return
    frame = None
    try:
        conn.send("ready")
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
                answer = np.asarray(work(frame))
            except Exception as error:  # said by the parent, which then works the frames
                answer = f"{type(error).__name__}: {error}"
            conn.send(answer)
    except (EOFError, OSError):         # the parent is gone
        return
