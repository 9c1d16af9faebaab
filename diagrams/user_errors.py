"""Errors in a user's code (a controller factory, a plant application) said in one
line: the factory, the error and where in the user's own files it arose
(`user_frame`, which the command line uses too, also for an error raised in a worker
process)."""

import re
import sys
import sysconfig
import traceback
from pathlib import Path

from reachwatch.systems.checks import clip


def is_installed(location) -> bool:
    """Whether ``location`` (a module's file or folder) is part of Python or of an
    installed distribution rather than a user's source tree."""
    path = Path(location).resolve()
    if {"site-packages", "dist-packages"} & set(path.parts):
        return True
    paths = sysconfig.get_paths()
    return any(path.is_relative_to(Path(paths[k]).resolve())
               for k in ("stdlib", "platstdlib") if k in paths)


def call_failure(spec: str, error: BaseException, module=None,
                 where="controller.factory") -> ValueError:
    """One line for a user's factory that raised when called: the factory, the error and
    where in the file of ``module`` (the factory's, when it has a file) it arose."""
    file = getattr(module, "__file__", None)
    return factory_failure(spec, error, Path(file).parent if file else None, where,
                    doing="calling it")


def _frames(error: BaseException) -> list:
    """``(file, line, function)`` of ``error``'s traceback, outermost first; raised in a
    worker process (its cause a ``_RemoteTraceback``: the worker's traceback as text),
    the worker's frames of the error itself (not of the exceptions it was raised while
    handling) come after the ones here, innermost last."""
    frames = [(f.filename, f.lineno, f.name) for f in traceback.extract_tb(error.__traceback__)]
    cause = error.__cause__
    if cause is not None and type(cause).__name__ == "_RemoteTraceback":
        text = re.split(r"\n(?:The above exception was the direct cause of the following "
                        r"exception|During handling of the above exception, another "
                        r"exception occurred):", str(cause))[-1]
        frames += [(f, int(n), name) for f, n, name in
                   re.findall(r'File "([^"]+)", line (\d+), in (\S+)', text)]
    return frames


def _ours(path: Path) -> bool:
    """Whether ``path`` is a file of reachwatch's own (of a loaded reachwatch module's
    folder; the user's modules that reachwatch loads are named ``reachwatch_user_*``)."""
    folders = {Path(m.__file__).resolve().parent for name, m in list(sys.modules.items())
               if name.startswith("reachwatch.") and getattr(m, "__file__", None)}
    return path.parent in folders


def user_frame(error: BaseException, folder=None):
    """``(file, line, function)`` where the user's code raised ``error``: the innermost
    frame of its traceback (`_frames`) in ``folder`` (the user's factory's), or, without
    one, the innermost that is neither Python's nor installed (`is_installed`), when it is
    not reachwatch's own (an error raised inside reachwatch is reachwatch's to show with
    its traceback, even when the user's code called it). None when there is none."""
    for filename, line, function in reversed(_frames(error)):
        path = Path(filename)
        if not path.is_file():
            continue                                   # <string>, frozen modules
        path = path.resolve()
        if folder is not None:
            if path.is_relative_to(Path(folder).resolve()):
                return str(path), line, function
            continue
        if is_installed(path):
            continue
        return None if _ours(path) else (str(path), line, function)
    return None


def factory_failure(spec: str, error: BaseException, folder=None, where="controller.factory",
             doing="importing it") -> ValueError:
    """One line naming the factory, the error and where in the user's code it arose."""
    # without the factory's folder (a package's module): its innermost frame in any file
    frame = user_frame(error, folder if folder is not None else Path("/"))
    place = f" at {clip(frame[0], 200)}:{frame[1]}" if frame else ""
    if isinstance(error, SyntaxError) and error.filename:
        place = f" at {clip(error.filename, 200)}:{error.lineno}"
    message = error.msg if isinstance(error, SyntaxError) else error
    if isinstance(error, SystemExit):
        message = f"it called sys.exit({'' if error.code is None else repr(error.code)})"
    hint = (f"; a module it imports must be installed or in {clip(folder, 200)}"
            if isinstance(error, ImportError) and folder is not None else "")
    return ValueError(f"{where} '{clip(spec, 200)}': {doing} failed: "
                      f"{type(error).__name__}: {clip(message, 300)}{place}{hint}")
