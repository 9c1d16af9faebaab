"""A user's controller code: loading a factory named as ``path/to/file.py:function``
or ``package.module:function``, with the file's folder importable while it loads and
while the factory runs (in any process, nothing left in ``sys.path`` or
``sys.modules``), compiled from source; and its fingerprint (`factory_code_hash`),
which covers every ``.py`` file of that folder, or of a user's package, so an edit
anywhere in the controller's code changes the key of its sweeps."""

import ast
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
import os
import sys
import threading
from pathlib import Path

from reachwatch.systems.checks import clip, is_file
from reachwatch.systems.files import check_keyed, local_copy, remember_keyed

from .data_reads import FolderReads, warn_unkeyed
from .user_errors import factory_failure, is_installed


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


def _holds_code(folder: str) -> bool:
    """Whether ``folder`` holds a ``.py`` file of its own (a package, or a namespace
    package an import reaches through a link), not only data."""
    try:
        return any(name.endswith(".py") for name in os.listdir(folder))
    except OSError:
        return False


def _source_files(root: Path, where: str):
    """``(relative path, path)`` of every ``.py`` file under ``root`` an import from it
    can reach, sorted, through linked packages too (a link to a folder holding a ``.py``
    file; a link to a folder of data alone is not walked);
    folders that no import can name (hidden, ``__pycache__``, not identifiers) and
    virtual environments are skipped."""
    found, entries, size, walked = [], 0, 0, set()
    # a linked package is followed (an import reaches through it), each folder once
    for folder, dirs, files in os.walk(root, followlinks=True):
        real = os.path.realpath(folder)
        if real in walked:
            dirs[:] = []
            continue
        walked.add(real)
        entries += len(dirs) + len(files)
        if entries > MAX_SOURCE_ENTRIES:
            raise ValueError(f"{where}: the folder {clip(root, 200)} holds more than "
                             f"{MAX_SOURCE_ENTRIES} files; put the controller's files in a "
                             f"folder of their own")
        dirs[:] = sorted(d for d in dirs if not _pruned(d)
                         and not os.path.exists(os.path.join(folder, d, "pyvenv.cfg"))
                         and (not os.path.islink(os.path.join(folder, d))
                              or _holds_code(os.path.join(folder, d))))
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


class _UserCode:
    """A factory file's folder, the digest of its code, and the modules imported from
    it, kept out of ``sys.modules`` (two controllers may each have a ``helpers.py``; an
    edited one is imported afresh) except while the factory is imported or called;
    ``reads``: the files of its folder its code opened meanwhile (`data_reads`)."""

    def __init__(self, folder: Path, digest: str):
        self.folder, self.digest, self.modules = folder, digest, {}
        self.reads = FolderReads(folder)
        # the top-level names its folder's files and packages take, next to a script
        self.provides = {p.stem for p in folder.glob("*.py")} | {
            p.parent.name for p in folder.glob("*/__init__.py")}
        _FOLDERS.add(folder)
        self._outside = None

    def outside(self) -> dict:
        """``{name: digest}`` of the top-level modules its folder's code imports (any
        ``import`` statement of its ``.py`` files, those inside functions too) that
        Python finds in a user's source tree outside the folder (through the working
        directory or ``PYTHONPATH``; not installed, not reachwatch), and of those these
        import in turn: a module file by its content, a package (a namespace one too)
        by every ``.py`` file of it. Found without importing
        (`importlib.util.find_spec` of top-level names), once, so that its factory's
        key does not depend on what the process imported first."""
        if self._outside is None:
            found, seen = {}, set(self.provides)
            waiting = _imported_names(p for _, p in _source_files(self.folder,
                                                                   "controller.factory"))
            while waiting - seen:
                name = min(waiting - seen)
                seen.add(name)
                files = self._outside_files(name)
                if files is not None:
                    found[name] = files_digest((r, _read(p, "controller.factory"))
                                               for r, p in files)
                    waiting |= _imported_names(p for _, p in files)   # and what they import
            self._outside = dict(sorted(found.items()))
        return self._outside

    def _outside_files(self, name: str):
        """``[(relative path, path)]`` of the top-level module ``name`` when Python finds
        it in a user's source tree outside the folder (a module file; a package's, or a
        namespace package's, every ``.py`` file), else None (not found, Python's own,
        installed, reachwatch, or in the folder)."""
        if name == "reachwatch" or name in sys.builtin_module_names:
            return None
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            return None
        origin = getattr(spec, "origin", None)
        if origin and os.path.isfile(origin):
            roots = [Path(origin)]
        elif not origin and getattr(spec, "submodule_search_locations", None):
            roots = [Path(p) for p in spec.submodule_search_locations]  # a namespace package
        else:
            return None
        files = []
        for root in roots:
            path = root.resolve()
            if is_installed(str(path)) or path.is_relative_to(self.folder):
                return None
            if path.name == "__init__.py":
                files += [(f"{name}/{r}", p) for r, p in _source_files(path.parent,
                                                                       "controller.factory")]
            elif path.is_dir():
                try:
                    files += [(f"{name}/{r}", p) for r, p in _source_files(path, "")]
                except ValueError:
                    raise ValueError(f"controller.factory: its code imports {name}, a folder "
                                     f"without __init__.py outside the factory's folder "
                                     f"({clip(path, 200)}) with too many files to key; give "
                                     f"the module another name, or the folder an "
                                     f"__init__.py") from None
            else:
                files.append((path.name, path))
        return files

    def _other_folders(self, module) -> bool:
        """Whether ``module`` was loaded from another user folder's code (not from this
        folder, Python's, an installed package or anywhere else)."""
        file = getattr(module, "__file__", None)
        if not file:
            return False
        path = Path(file).resolve()
        return (not path.is_relative_to(self.folder)
                and any(path.is_relative_to(f) for f in _FOLDERS if f != self.folder))

    @contextlib.contextmanager
    def importable(self):
        """Its folder's modules importable, as next to a script: a module of the same
        name that another factory's folder shows meanwhile (an application's
        ``utils.py`` while the controller's own ``utils.py`` is imported) is hidden until
        the block ends, so each folder's code imports its own. (Python's modules and
        installed ones are never hidden.)"""
        with _LOCK:
            finder = _FolderFinder(self.folder)
            hidden = {n: m for n, m in list(sys.modules.items())
                      if n.partition(".")[0] in self.provides and self._other_folders(m)}
            for name in hidden:
                del sys.modules[name]
            shown = {n: m for n, m in self.modules.items() if n not in sys.modules}
            sys.modules.update(shown)
            meta = sys.meta_path         # before the path and any other folder's finder
            meta.insert(next((i for i, f in enumerate(meta) if isinstance(f, _FolderFinder)
                              or f is importlib.machinery.PathFinder), len(meta)), finder)
            try:
                with self.reads.recording():
                    yield
            finally:
                meta.remove(finder)
                for name in finder.found | set(shown):
                    if name in sys.modules:
                        self.modules[name] = sys.modules.pop(name)
                sys.modules.update(hidden)


_USER_CODE = {}     # module name of a loaded factory file -> its _UserCode
_FOLDERS = set()    # the folders of every factory file loaded (or loading)


def importable(module):
    """A context in which the folder of the factory file ``module`` was loaded from is
    importable (a no-op for any other module)."""
    user = _USER_CODE.get(getattr(module, "__name__", None))
    return user.importable() if user else contextlib.nullcontext()


def warn_unkeyed_reads(spec: str, module, keyed=()):
    """`data_reads.warn_unkeyed` of the folder the factory file ``module`` was loaded
    from (a no-op for any other module)."""
    user = _USER_CODE.get(getattr(module, "__name__", None))
    if user is not None:
        warn_unkeyed(spec, user.reads, keyed)


def _imported_names(paths) -> set:
    """The top-level names every ``import`` statement of the ``.py`` files ``paths``
    imports (relative imports aside)."""
    names = set()
    for path in paths:
        try:
            tree = ast.parse(path.read_bytes())
        except (SyntaxError, ValueError, OSError):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names.update(alias.name.partition(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.partition(".")[0])
    return names


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
                raise factory_failure(spec, e, path.parent, where) from e
            except BaseException:
                del sys.modules[name]
                raise
            _USER_CODE[name] = user
        return sys.modules[name]


def _package_root(target: str):
    """The folder of the top-level package the imported module ``target`` belongs to (a
    top-level module: its file) when it is a user's source tree, not reachwatch (its own
    code is versioned by `reachwatch.reach.fingerprint.FORMAT`) nor installed; else None."""
    top = target.partition(".")[0]
    file = getattr(sys.modules.get(target), "__file__", None)
    if top == "reachwatch" or not file or not os.path.isfile(file) or is_installed(file):
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
        raise factory_failure(spec, e, where=where) from e
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
        user = _USER_CODE[module.__name__]
        content = {"folder": remember_keyed(f"code:{target}", user.digest)}
        if user.outside():      # what its code imports from a source tree outside it
            content["outside"] = user.outside()
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
