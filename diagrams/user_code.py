"""A user's controller code: loading a factory named as ``path/to/file.py:function``
or ``package.module:function``, with the file's folder importable while it loads and
while the factory runs (in any process, nothing left in ``sys.path`` or
``sys.modules``), compiled from source; and its fingerprint (`factory_code_hash`),
which covers every ``.py`` file of that folder, or of a user's package, so an edit
anywhere in the controller's code changes the key of its sweeps."""

import contextlib
import functools
import hashlib
import importlib
import importlib.abc
import importlib.machinery
import importlib.metadata
import importlib.util
import inspect
import json
import multiprocessing
import os
import re
import sys
import sysconfig
import threading
import traceback
import warnings
from pathlib import Path

from reachwatch.systems.checks import clip, is_file
from reachwatch.systems.files import check_keyed, local_copy, remember_keyed


#: Bounds on the folder of a controller's files, all of whose ``.py`` files are read
#: at every resolution (a factory file left in a home directory is a mistake).
MAX_SOURCE_ENTRIES = 10_000     # files and folders looked at
MAX_SOURCE_FILES = 1_000        # .py files
MAX_SOURCE_BYTES = 20 << 20     # their total size

#: Held while user code is importable (the import machinery is process-wide).
_LOCK = threading.RLock()


def _split(spec: str, where="controller.factory"):
    target, sep, name = spec.rpartition(":")
    if not sep or not target or not name.isidentifier():
        raise ValueError(f"{where} must be 'package.module:function' or "
                         f"'path/to/file.py:function', got '{spec}'")
    return target, name


def _pruned(name: str) -> bool:
    return name.startswith(".") or name == "__pycache__" or not name.isidentifier()


def _source_files(root: Path, where: str):
    """``(relative path, path)`` of every ``.py`` file under ``root`` an import from it
    can reach, sorted; folders that no import can name (hidden, ``__pycache__``, not
    identifiers) and virtual environments are skipped."""
    found, entries, size = [], 0, 0
    for folder, dirs, files in os.walk(root):
        entries += len(dirs) + len(files)
        if entries > MAX_SOURCE_ENTRIES:
            raise ValueError(f"{where}: the folder {clip(root, 200)} holds more than "
                             f"{MAX_SOURCE_ENTRIES} files; put the controller's files in a "
                             f"folder of their own")
        dirs[:] = sorted(d for d in dirs if not _pruned(d)
                         and not os.path.exists(os.path.join(folder, d, "pyvenv.cfg")))
        for name in files:
            path = Path(folder, name)
            if name.endswith(".py") and path.is_file():
                found.append((path.relative_to(root).as_posix(), path))
                size += path.stat().st_size
        if len(found) > MAX_SOURCE_FILES or size > MAX_SOURCE_BYTES:
            raise ValueError(f"{where}: the folder {clip(root, 200)} holds more than "
                             f"{MAX_SOURCE_FILES} .py files or {MAX_SOURCE_BYTES >> 20} MiB of "
                             f"them; put the controller's files in a folder of their own")
    return sorted(found)


def files_digest(files) -> str:
    """SHA-256 of ``files``, ``[(relative path, bytes)]`` in order: their paths and
    contents (what a folder of code is, whether read here or sent to a worker)."""
    digest = hashlib.sha256()
    for relative, content in files:
        digest.update(f"{relative}\0{hashlib.sha256(content).hexdigest()}\0".encode())
    return digest.hexdigest()


def _read(path: Path, where: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise ValueError(f"{where}: cannot read {clip(path, 200)} ({e.strerror})") from None


def source_digest(root, where="controller.factory") -> str:
    """SHA-256 of every ``.py`` file under ``root`` (relative paths and contents)."""
    return files_digest((relative, _read(path, where))
                        for relative, path in _source_files(Path(root), where))


class _SourceLoader(importlib.machinery.SourceFileLoader):
    """Compiles a user's file from its source every time: a cached ``.pyc`` is trusted
    by the file's size and whole-second time, so an edit that keeps both would run the
    old code."""

    def get_code(self, fullname):
        path = self.get_filename(fullname)
        return self.source_to_code(self.get_data(path), path)


def _only_namespace(name: str) -> bool:
    """Whether nothing but a namespace package named ``name`` is on ``sys.path`` (a
    module or regular package there comes first, as next to a script)."""
    found = importlib.machinery.PathFinder.find_spec(name)
    return found is None or found.loader is None


class _FolderFinder(importlib.abc.MetaPathFinder):
    """Finds modules and packages in one folder, the way Python finds them next to a
    script it runs; records what it found."""

    def __init__(self, folder: Path):
        self.folder, self.found = folder, set()

    def find_spec(self, fullname, path=None, target=None):
        tail = fullname.rpartition(".")[2]
        bases = [self.folder] if path is None else [
            Path(p) for p in path if isinstance(p, str) and Path(p).is_relative_to(self.folder)]
        for base in bases:
            package, module = base / tail / "__init__.py", base / f"{tail}.py"
            if package.is_file():
                spec = importlib.util.spec_from_file_location(
                    fullname, package, loader=_SourceLoader(fullname, str(package)),
                    submodule_search_locations=[str(package.parent)])
            elif module.is_file():
                spec = importlib.util.spec_from_file_location(
                    fullname, module, loader=_SourceLoader(fullname, str(module)))
            elif (base / tail).is_dir() and (path is not None or _only_namespace(fullname)):
                spec = importlib.machinery.ModuleSpec(fullname, None, is_package=True)
                spec.submodule_search_locations = [str(base / tail)]     # a namespace package
            else:
                continue
            self.found.add(fullname)
            return spec
        return None


#: Per thread: the `_UserCode` whose code runs now (`_UserCode.importable`), innermost last.
_RUNNING = threading.local()


def _record_reads(event: str, args):
    """An audit hook (`sys.addaudithook`): a file opened for reading by Python (``open``,
    ``os.open``: numpy, torch, pickle and PIL read so) inside the folder of the user's
    code that runs now, its ``.py`` files and ``__pycache__`` aside, is added to that
    code's `_UserCode.read`. Never raises; returns at once when no user code runs."""
    if event != "open":
        return
    running = getattr(_RUNNING, "codes", None)
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
        for code in running:
            if path.startswith(code.prefix):
                code.read.add(path)
    except Exception:       # noqa: BLE001  (a hook must not break the open it watches)
        pass


_HOOK = []          # [True] once `_record_reads` is installed (hooks cannot be removed)


class _UserCode:
    """A factory file's folder, the digest of its code, and the modules imported from
    it, kept out of ``sys.modules`` (two controllers may each have a ``helpers.py``; an
    edited one is imported afresh) except while the factory is imported or called;
    ``read``: the data files in its folder its code opened meanwhile (`_record_reads`)."""

    def __init__(self, folder: Path, digest: str):
        self.folder, self.digest, self.modules = folder, digest, {}
        self.prefix = os.path.join(os.path.realpath(folder), "")
        self.read = set()

    @contextlib.contextmanager
    def importable(self):
        with _LOCK:
            if not _HOOK:
                sys.addaudithook(_record_reads)
                _HOOK.append(True)
            running = _RUNNING.__dict__.setdefault("codes", [])
            finder = _FolderFinder(self.folder)
            shown = {n: m for n, m in self.modules.items() if n not in sys.modules}
            sys.modules.update(shown)
            meta = sys.meta_path
            meta.insert(meta.index(importlib.machinery.PathFinder)
                        if importlib.machinery.PathFinder in meta else len(meta), finder)
            running.append(self)
            try:
                yield
            finally:
                running.remove(self)
                meta.remove(finder)
                for name in finder.found | set(shown):
                    if name in sys.modules:
                        self.modules[name] = sys.modules.pop(name)


_USER_CODE = {}     # module name of a loaded factory file -> its _UserCode

def importable(module):
    """A context in which the folder of the factory file ``module`` was loaded from is
    importable (a no-op for any other module)."""
    user = _USER_CODE.get(getattr(module, "__name__", None))
    return user.importable() if user else contextlib.nullcontext()


_WARNED = set()     # the files `warn_unkeyed_reads` has warned of (real paths)


def _data_file(path: str, folder: str) -> bool:
    """Whether ``path``, read from the controller's ``folder``, is one of its data files:
    a file that still exists, outside hidden folders, ``__pycache__``, virtual
    environments and installed packages' metadata."""
    parts = Path(os.path.relpath(path, folder)).parts[:-1]
    below = Path(folder)
    for part in parts:
        below = below / part
        if (part.startswith(".") or part in ("__pycache__", "site-packages")
                or part.endswith((".dist-info", ".egg-info"))
                or (below / "pyvenv.cfg").exists()):
            return False
    return os.path.isfile(path)


def warn_unkeyed_reads(spec: str, module, keyed=()):
    """A warning, once per process for each file, naming a data file in the folder of
    the factory file ``module`` that its code opened (at import or when called) and
    that no key covers (``keyed``: the paths whose content is keyed, the
    controller's checkpoint): an edit to it would be answered from the caches."""
    user = _USER_CODE.get(getattr(module, "__name__", None))
    if user is None or multiprocessing.parent_process() is not None:
        return                  # a worker process: the driver that started it says it
    keyed = {os.path.realpath(p) for p in keyed if p}
    with _LOCK:
        new = sorted(p for p in user.read - keyed - _WARNED if _data_file(p, user.prefix))
        _WARNED.update(new)
    for path in new:
        warnings.warn(f"controller.factory '{clip(spec, 200)}' read "
                      f"{clip(os.path.relpath(path, user.prefix), 200)} from its folder: not "
                      f"its code, so no key covers it, and a sweep or run after an edit to it "
                      f"is answered from the caches; name the controller's data file in "
                      f"controller.checkpoint, whose content is keyed", UserWarning, stacklevel=3)


def call_failure(spec: str, error: BaseException, module=None,
                 where="controller.factory") -> ValueError:
    """One line for a user's factory that raised when called: the factory, the error and
    where in the file of ``module`` (the factory's, when it has a file) it arose."""
    file = getattr(module, "__file__", None)
    return _failure(spec, error, Path(file).parent if file else None, where,
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
    one, the innermost that is neither Python's nor installed (`_installed`), when it is
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
        if _installed(path):
            continue
        return None if _ours(path) else (str(path), line, function)
    return None


def _failure(spec: str, error: BaseException, folder=None, where="controller.factory",
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


def _load_file(spec: str, target: str, where="controller.factory", named=None):
    if not is_file(target):
        raise ValueError(f"{where}: file not found: {clip(target, 200)}")
    path = Path(target).resolve()
    digest = source_digest(path.parent, where)
    check_keyed(f"code:{named or target}", digest,
                f"{where} '{clip(spec, 200)}': the code in {clip(path.parent, 200)}")
    name = (f"reachwatch_user_{path.stem if path.stem.isidentifier() else 'factory'}_"
            f"{hashlib.sha256(str(path).encode()).hexdigest()[:8]}_{digest[:16]}")
    with _LOCK:
        if name not in sys.modules:
            user = _UserCode(path.parent, digest)
            module_spec = importlib.util.spec_from_file_location(
                name, path, loader=_SourceLoader(name, str(path)))
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[name] = module
            try:
                with user.importable():
                    module_spec.loader.exec_module(module)
            except (Exception, SystemExit) as e:    # sys.exit() at import: exited silently
                del sys.modules[name]
                raise _failure(spec, e, path.parent, where) from e
            except BaseException:
                del sys.modules[name]
                raise
            _USER_CODE[name] = user
        return sys.modules[name]


def _installed(location) -> bool:
    """Whether ``location`` (a module's file or folder) is part of Python or of an
    installed distribution rather than a user's source tree."""
    path = Path(location).resolve()
    if {"site-packages", "dist-packages"} & set(path.parts):
        return True
    paths = sysconfig.get_paths()
    return any(path.is_relative_to(Path(paths[k]).resolve())
               for k in ("stdlib", "platstdlib") if k in paths)


def _package_root(target: str):
    """The folder of the top-level package the imported module ``target`` belongs to (a
    top-level module: its file) when it is a user's source tree, not reachwatch (its own
    code is versioned by `reachwatch.reach.fingerprint.FORMAT`) nor installed; else None."""
    top = target.partition(".")[0]
    file = getattr(sys.modules.get(target), "__file__", None)
    if top == "reachwatch" or not file or not os.path.isfile(file) or _installed(file):
        return None
    node = Path(file).resolve()
    node = node.parent if node.name == "__init__.py" else node
    for _ in range(target.count(".")):
        node = node.parent
    return node if (node.stem if node.is_file() else node.name) == top else None


_IMPORTED = {}      # a user's top-level package -> the digest of its tree when first used


def _package_digest(spec: str, target: str, where="controller.factory"):
    """The digest of the user's package (or module's folder) ``target`` belongs to, or
    None for reachwatch and installed ones; an error if it changed since this process
    imported it (the code in memory is not the code on disk)."""
    root = _package_root(target)
    if root is None:
        return None
    digest = source_digest(root.parent if root.is_file() else root, where)
    if _IMPORTED.setdefault(root, digest) != digest:
        raise ValueError(f"{where} '{clip(spec, 200)}': files of {clip(root, 200)} "
                         f"changed since this process imported them; start a new process")
    return digest


def _module(spec: str, target: str, where="controller.factory"):
    if target.endswith(".py"):        # its folder's copy, when it came with the task
        return _load_file(spec, local_copy(target), where, named=target)
    try:
        module = importlib.import_module(target)
    except ImportError as e:
        raise ValueError(f"{where}: cannot import '{target}' ({clip(e, 300)}); "
                         f"install the package or name a file as 'path/to/file.py:function'"
                         ) from None
    except (Exception, SystemExit) as e:
        raise _failure(spec, e, where=where) from e
    _package_digest(spec, target, where)
    return module


def resolve(spec: str, where="controller.factory"):
    """``(module, function)`` a non-empty factory string names; errors name the run
    file's field ``where``."""
    target, name = _split(spec, where)
    module = _module(spec, target, where)
    function = getattr(module, name, None)
    if not callable(function):
        raise ValueError(f"{where}: '{target}' has no function '{name}'")
    if not (inspect.isfunction(function) or inspect.isclass(function)
            or inspect.ismethod(function)):
        raise ValueError(f"{where}: '{spec}' is a {type(function).__name__}, not a "
                         f"Python function or class" + (
                             " that takes the ControllerConfig and returns a Drake System"
                             if where == "controller.factory" else ""))
    return module, function


@functools.lru_cache(maxsize=None)
def _versions():
    return importlib.metadata.packages_distributions()


def _version(top: str) -> str:
    names = _versions().get(top, [])
    try:
        return ",".join(f"{n}=={importlib.metadata.version(n)}" for n in sorted(set(names)))
    except importlib.metadata.PackageNotFoundError:
        return ""


def factory_code_hash(spec: str, where="controller.factory") -> str:
    """SHA-256 of the code the factory ``spec`` names can run (so a sweep of an edited
    controller is never answered from a stale cache): every ``.py`` file in a factory
    file's folder and below it; for ``package.module``, every ``.py`` file of a user's
    package (or of a top-level module's folder), or an installed package's version and
    the factory's own file. '' for TaxiNet's, whose content is its checkpoint and gains."""
    if not spec:
        return ""
    target, _ = _split(spec, where)
    module, function = resolve(spec, where)
    if target.endswith(".py"):                                     # the code loaded
        content = {"folder": remember_keyed(f"code:{target}",
                                            _USER_CODE[module.__name__].digest)}
    else:
        digest = _package_digest(spec, target, where)
        if digest is not None:
            content = {"package": digest}
        else:
            try:
                source = Path(inspect.getsourcefile(function)).read_bytes()
            except (OSError, TypeError):
                source = inspect.getsource(function).encode()
            top = target.partition(".")[0]
            content = {"module": top, "version": _version(top),
                       "source": hashlib.sha256(source).hexdigest()}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()
