"""The data files a user's code reads from its own folder, and a warning for those no
cache key covers. An audit hook (`sys.addaudithook`) sees each file Python opens
(``open``, ``os.open``: numpy, torch, pickle and PIL read so) in the thread that runs
the user's code (`FolderReads.recording`); C-level opens (OpenCV's ``imread``, HDF5)
and threads of the user's own are not seen."""

import contextlib
import multiprocessing
import os
import sys
import threading
import warnings
from pathlib import Path

from reachwatch.systems.checks import clip

_LOCK = threading.Lock()
_HOOK = []          # [True] once `_record_reads` is installed (hooks cannot be removed)
_RUNNING = threading.local()    # per thread: the `FolderReads` recording now, innermost last
_WARNED = set()     # the files `warn_unkeyed` has warned of (real paths)


def _record_reads(event: str, args):
    """The audit hook: a file opened for reading inside the folder of a `FolderReads`
    recording in this thread, its ``.py`` files and ``__pycache__`` aside, is added to
    its ``read``. Never raises; returns at once when nothing records."""
    if event != "open":
        return
    running = getattr(_RUNNING, "folders", None)
    if not running:
        return
    try:
        path, mode, flags = args
        if path is None or isinstance(path, int):
            return
        if mode is not None:
            if any(c in mode for c in "wax+"):
                return
        elif flags & (os.O_WRONLY | os.O_RDWR):
            return
        path = os.path.realpath(os.fsdecode(path))      # the folder is a real path too
        if path.endswith((".py", ".pyc")) or f"{os.sep}__pycache__{os.sep}" in path:
            return
        for folder in running:
            if path.startswith(folder.prefix):
                folder.read.add(path)
    except Exception:       # noqa: BLE001  (a hook must not break the open it watches)
        pass


class FolderReads:
    """The files under ``folder`` opened for reading while `recording` (``read``: real
    paths)."""

    def __init__(self, folder):
        self.prefix = os.path.join(os.path.realpath(folder), "")
        self.read = set()

    @contextlib.contextmanager
    def recording(self):
        with _LOCK:
            if not _HOOK:
                sys.addaudithook(_record_reads)
                _HOOK.append(True)
        running = _RUNNING.__dict__.setdefault("folders", [])
        running.append(self)
        try:
            yield
        finally:
            running.remove(self)


def _data_file(path: str, folder: str) -> bool:
    """Whether ``path``, read from ``folder``, is one of its data files: a file that
    still exists, outside hidden folders, ``__pycache__``, virtual environments and
    installed packages' metadata."""
    below = Path(folder)
    for part in Path(os.path.relpath(path, folder)).parts[:-1]:
        below = below / part
        if (part.startswith(".") or part in ("__pycache__", "site-packages")
                or part.endswith((".dist-info", ".egg-info"))
                or (below / "pyvenv.cfg").exists()):
            return False
    return os.path.isfile(path)


def warn_unkeyed(spec: str, reads: FolderReads, keyed=()):
    """A warning, once per process for each file, naming a data file of ``reads`` (the
    folder of the controller factory ``spec``) that no key covers (``keyed``: the paths
    whose content is keyed, the controller's checkpoint and data files): an edit to it would be
    answered from the caches. Said by the driver, not by the worker processes it
    starts."""
    if multiprocessing.parent_process() is not None:
        return
    keyed = {os.path.realpath(p) for p in keyed if p}
    with _LOCK:
        new = sorted(p for p in reads.read - keyed - _WARNED if _data_file(p, reads.prefix))
        _WARNED.update(new)
    for path in new:
        warnings.warn(f"controller.factory '{clip(spec, 200)}' read "
                      f"{clip(os.path.relpath(path, reads.prefix), 200)} from its folder: not "
                      f"its code, so no key covers it, and a sweep or run after an edit to it "
                      f"is answered from the caches; name the controller's data files in "
                      f"controller.data_files (or its network's weights in "
                      f"controller.checkpoint), whose content is keyed", UserWarning,
                      stacklevel=4)
