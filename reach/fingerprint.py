"""Content fingerprints of sweep factories: what a cached table was computed from.

A factory (usually ``functools.partial(make_diagram, config)``) is reduced to plain
JSON: the function's name and the source text of the module that defines it; an object
with a ``__fingerprint__()`` method by what that returns; dataclasses field by field;
numpy arrays, torch modules and tensors by a hash of their bytes; and any string or
path that names an existing file by a hash of the file's *contents* (a moved
checkpoint keeps its fingerprint, a retrained one does not). What cannot be reduced
this way raises `Unfingerprintable`, so a sweep never silently reuses a table made by
another controller. Every fingerprint also carries the versions, the render stack and
the source of the packages loops are built from (`LOOP_CODE`)."""

import dataclasses as dc
import functools
import hashlib
import importlib
import inspect
import json
import math
import os
import sys
import time

from pathlib import Path

import numpy as np

from reachwatch.systems.files import file_hash, local_copy, remember_keyed

#: Bump when what a sweep computes changes for the same inputs.
FORMAT = 1


#: The distributions whose versions change what a process computes or renders:
#: reachwatch, drake (its renderer, VTK, comes with it), torch and torchvision (the
#: paper's detector is torchvision's EfficientNet), numpy and scipy. Their versions are
#: in every fingerprint, with `module_versions`', and a Dask worker must have the
#: driver's (`reachwatch.pipeline.executors.check_worker_versions`).
DISTRIBUTIONS = ("reachwatch", "drake", "torch", "torchvision", "numpy", "scipy")


def module_versions() -> dict:
    """Versions read off imported modules, where more than one distribution provides
    the module: ``opencv``, the ``cv2`` that resizes the images datasets store and
    monitors read (opencv-python-headless, opencv-python, a conda build...)."""
    try:
        import cv2
        return {"opencv": str(cv2.__version__)}
    except ImportError:
        return {"opencv": None}


def distribution_versions() -> dict:
    """``{name: version or None}`` of `DISTRIBUTIONS` in this process, and
    `module_versions`."""
    from importlib.metadata import PackageNotFoundError, version
    out = {}
    for name in DISTRIBUTIONS:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return {**out, **module_versions()}


#: What every fingerprint carries besides `FORMAT` (`distribution_versions`) and the
#: render stack (`reachwatch.diagrams.render_stack`).
STACK = distribution_versions()


def _stack() -> dict:
    """`STACK`, this process's render stack (its probe image is rendered once, at the
    first fingerprint: results rendered by another GL driver are another key) and the
    source of `LOOP_CODE` (an edit there is another key, whatever the version says)."""
    from reachwatch.diagrams.render_stack import render_stack
    return {**STACK, "render": render_stack(), "code": loop_code_digest()}


#: reachwatch's packages, lowest layer first.
LIBRARY = tuple(f"reachwatch.{name}" for name in
                ("systems", "diagrams", "reach", "taxi", "training", "pipeline"))

#: The packages every loop is built and run from: its systems, its diagrams, the
#: real-loop runners and the built-in application (the taxi). Their source is in every
#: fingerprint: a factory's own module is not enough when the switch, a monitor or the
#: plant it wires in changes.
LOOP_CODE = LIBRARY[:4]


def loop_code_digest() -> str:
    """`modules_source_digest` of `LOOP_CODE`, read once per process; every call checks
    again that none of its imported files changed since the process started
    (`check_source_unchanged`)."""
    check_source_unchanged(*LOOP_CODE)
    return _loop_code_digest()


@functools.cache
def _loop_code_digest() -> str:
    return modules_source_digest(*LOOP_CODE)


def library_code_digest() -> str:
    """`modules_source_digest` of all of `LIBRARY`, read once per process (every call
    checks again, `check_source_unchanged`): the source a worker must share with the
    driver, whose keys carry parts of it (`LOOP_CODE` in every fingerprint, a dataset's
    own modules in its folder's key)."""
    check_source_unchanged(*LIBRARY)
    return _library_code_digest()


@functools.cache
def _library_code_digest() -> str:
    return modules_source_digest(*LIBRARY)


def modules_source_digest(*names) -> str:
    """SHA-256 of the source of the modules ``names`` (dotted names; a package stands
    for every ``.py`` file under its folder, `diagrams.user_code.source_digest`): a key
    that carries it changes whenever that code does (`LIBRARY`: all of reachwatch)."""
    from reachwatch.diagrams.user_code import files_digest, source_digest
    check_source_unchanged(*names)
    parts = []
    for name in names:
        module = importlib.import_module(name)
        if hasattr(module, "__path__"):
            parts += [(f"{name}/{i}", source_digest(folder, where=name).encode())
                      for i, folder in enumerate(module.__path__)]
        else:
            parts.append((name, Path(module.__file__).read_bytes()))
    return files_digest(parts)


class SourceChanged(ValueError):
    """A module this process imported whose file changed on disk since the process
    started: a key made from the file would not describe the code that runs."""


def _process_start_ns() -> int:
    """When this process started, in `time.time_ns` terms: its start after boot, read off
    ``/proc`` in the kernel's clock ticks (10 ms), against the time since boot now; the
    end of that tick, so that a file written just before the process started is not
    taken for one written after (the interpreter imports nothing of reachwatch in its
    first tick). Where there is no ``/proc``, when this module was imported."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        since_boot = (int(fields[19]) + 1) * 10**9 // os.sysconf("SC_CLK_TCK")
        return time.time_ns() - (time.clock_gettime_ns(time.CLOCK_BOOTTIME) - since_boot)
    except (OSError, ValueError, IndexError, AttributeError):
        return time.time_ns()


#: `_process_start_ns`, once.
PROCESS_START_NS = _process_start_ns()


#: Source files dated in the future, ``{path: (mtime_ns, size)}`` when first seen.
_FUTURE_DATED = {}


def check_source_unchanged(*names):
    """Raise `SourceChanged`, in one line, when a module of ``names`` (dotted names; a
    package stands for its submodules) that this process has imported has a file
    modified after the process started: the process runs the code it imported, and a
    digest of the file as it is now (`modules_source_digest`) would key its results with
    other code. A module not imported yet is not checked: it will run what is on disk."""
    prefixes = tuple(f"{name}." for name in names)
    for module_name, module in list(sys.modules.items()):
        if module_name not in names and not module_name.startswith(prefixes):
            continue
        path = getattr(module, "__file__", None)
        if not path:
            continue
        try:
            stat = os.stat(path)
        except OSError:
            continue
        modified = stat.st_mtime_ns
        if modified > PROCESS_START_NS:
            seen = _FUTURE_DATED.get(path)
            if seen is None and modified > time.time_ns():
                # dated in the future (a checkout from a machine whose clock runs ahead):
                # its time says nothing; it is taken as imported the first time it is
                # seen (and so after the clock passes its date), and any later change of
                # its time or size is a change
                seen = _FUTURE_DATED.setdefault(path, (modified, stat.st_size))
            if seen == (modified, stat.st_size):
                continue
            raise SourceChanged(
                f"{module_name} ({path}) changed on disk after this process started: its "
                f"results would be keyed with code it does not run; start it again (a "
                f"killed run resumes from its caches)")


class Unfingerprintable(ValueError):
    """A factory argument whose content cannot be summarised."""


def _bytes_digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _callable(fn):
    """A function or class by its name and the source of the whole module that defines
    it: the helpers it calls from that module change its key too (a loop's body moved
    into a helper beside it is still covered). Where the module's file cannot be read,
    the function's own source; a builtin has none."""
    module = inspect.getmodule(fn)
    try:
        source = inspect.getsource(module) if module is not None else inspect.getsource(fn)
    except (OSError, TypeError):
        try:
            source = inspect.getsource(fn)
        except (OSError, TypeError):
            source = ""
    return {"callable": f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}",
            "source": _bytes_digest(source.encode())}


def canonical(value, where="factory"):
    """``value`` as JSON-able data that changes whenever its content does."""
    if value is None or isinstance(value, (bool, int)):
        return value
    own = getattr(type(value), "__fingerprint__", None)
    if own is not None and not isinstance(value, type):    # an object that says what it depends on
        return {"object": type(value).__qualname__, "content": canonical(value.__fingerprint__(), where)}
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, (str, os.PathLike)):
        text = os.fspath(value)
        if text and len(text) < 4096 and "\n" not in text and os.path.isfile(local_copy(text)):
            return {"file": remember_keyed(text, file_hash(text, 64))}
        return text
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return canonical(value.item(), where)
    if isinstance(value, np.ndarray):
        array = np.ascontiguousarray(value)
        return {"array": [str(array.dtype), list(array.shape), _bytes_digest(array.tobytes())]}
    if dc.is_dataclass(value) and not isinstance(value, type):
        return {"dataclass": type(value).__qualname__,
                "fields": {f.name: canonical(getattr(value, f.name), f"{where}.{f.name}")
                           for f in dc.fields(value)}}
    if isinstance(value, functools.partial):
        return {"partial": canonical(value.func, where),
                "args": [canonical(a, f"{where}[{i}]") for i, a in enumerate(value.args)],
                "kwargs": {k: canonical(v, f"{where}.{k}") for k, v in sorted(value.keywords.items())}}
    if isinstance(value, (list, tuple)):
        return [canonical(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        return {str(k): canonical(v, f"{where}[{k!r}]") for k, v in sorted(value.items(), key=str)}
    try:
        import torch
        if isinstance(value, torch.Tensor):
            return canonical(value.detach().cpu().numpy(), where)
        if isinstance(value, torch.nn.Module):
            return {"module": type(value).__qualname__,
                    "state": {k: canonical(v, f"{where}.{k}") for k, v in value.state_dict().items()}}
    except ImportError:          # pragma: no cover - torch is a dependency
        pass
    if inspect.isfunction(value) or inspect.isclass(value) or inspect.isbuiltin(value):
        if getattr(value, "__closure__", None):
            raise Unfingerprintable(f"{where}: {value.__qualname__} is a closure; pass its "
                                    f"values with functools.partial instead")
        return _callable(value)
    raise Unfingerprintable(f"{where}: cannot summarise a {type(value).__qualname__}; make "
                            f"the factory a functools.partial of a module-level function over "
                            f"dataclasses, numbers, strings, arrays or file paths")


def fingerprint(*parts) -> str:
    """SHA-256 (hex) of ``parts`` reduced by `canonical`, with the format number and the
    software stack (`STACK` and the render stack, `_stack`)."""
    text = json.dumps([FORMAT, _stack()] + [canonical(p) for p in parts], sort_keys=True)
    return _bytes_digest(text.encode())
