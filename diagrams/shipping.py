"""Files a task names, sent with it: a worker on another machine, or started in another
directory, reads the driver's checkpoints and a user's code from the copy that came
with the task, never from a path of the driver's (which it may not have, or may have
with other content: a silent wrong answer).

On the driver, `pack` walks a task's arguments as a fingerprint does (dataclasses,
`functools.partial`, lists, tuples, dicts) and collects every string that names an
existing file (a checkpoint, say) and every ``path/to/file.py:name`` (a user's factory:
every ``.py`` file of that file's folder goes with it, the files its fingerprint
covers). On the worker, `run_shipped` writes each folder once, atomically, into
``<cache>/shipped/<its digest>/`` and runs the task inside
`reachwatch.systems.files.shipped_copies`, so that every place opening a path the task
names (`local_copy`) opens the copy instead. A factory given as
``package.module:function`` is not sent: install the package on every worker."""

import dataclasses as dc
import functools
import hashlib
import os
import re
import shutil
import threading
import time
import uuid
from pathlib import Path

from reachwatch.systems.checks import clip
from reachwatch.systems.files import cache_root, shipped_copies

from .user_code import _source_files, files_digest

#: The most bytes one task may bring (its files are held in memory on both sides).
MAX_SHIPPED_BYTES = 1 << 30

_FACTORY_FILE = re.compile(r"(.+\.py):[A-Za-z_]\w*")


@dc.dataclass(frozen=True)
class ShippedFolder:
    """Files sent together, as they lie relative to their folder: ``files`` is
    ``((relative path, bytes), ...)`` sorted; ``digest`` names their content."""
    digest: str
    files: tuple


@dc.dataclass(frozen=True)
class Shipment:
    """What a task brings: its ``folders``, and ``names``, ``((path as the task names
    it, folder digest, relative path in that folder), ...)``."""
    folders: tuple
    names: tuple

    @property
    def digest(self) -> str:
        return hashlib.sha256(repr((sorted(f.digest for f in self.folders),
                                    self.names)).encode()).hexdigest()


def _folder(files) -> ShippedFolder:
    """The folder of ``files`` (``[(relative, path)]``) read now."""
    read = []
    for relative, path in sorted(files):
        try:
            read.append((relative, Path(path).read_bytes()))
        except OSError as e:
            raise ValueError(f"a task names {clip(path, 200)}, which cannot be read to send "
                             f"it to the workers ({e.strerror})") from None
    return ShippedFolder(files_digest(read), tuple(read))


#: A file changed less than this long before it was read may change again within the
#: same timestamp (a coarse clock): it is read again at the next task (as git does).
RACY_SECONDS = 2.0


def _signature(files) -> tuple:
    """What says the files are unchanged since they were read: each one's path, size,
    inode, modification and change times (the change time moves at every write and
    cannot be set back, as ``cp -p`` or ``touch -d`` set a modification time); None
    when one changed too recently to tell (`RACY_SECONDS`)."""
    out, now = [], time.time_ns()
    for _, path in files:
        stat = os.stat(path)
        if now - max(stat.st_mtime_ns, stat.st_ctime_ns) < RACY_SECONDS * 1e9:
            return None
        out.append((os.fspath(path), stat.st_size, stat.st_ino, stat.st_mtime_ns,
                    stat.st_ctime_ns))
    return tuple(out)


def _named(value, found: dict, depth: int = 0):
    """Add to ``found`` (``{path as named: "file" | "code"}``) the files ``value`` names."""
    if depth > 12 or value is None or isinstance(value, (bool, int, float, bytes)):
        return
    if isinstance(value, (str, os.PathLike)):
        text = os.fspath(value)
        if not isinstance(text, str) or not text or len(text) >= 4096 or "\n" in text:
            return
        code = _FACTORY_FILE.fullmatch(text)
        if code is not None and os.path.isfile(code.group(1)):
            found[code.group(1)] = "code"
        elif os.path.isfile(text):
            found.setdefault(text, "file")
        return
    if dc.is_dataclass(value) and not isinstance(value, type):
        for field in dc.fields(value):
            if field.compare:           # not a cache of live objects (a renderer)
                _named(getattr(value, field.name), found, depth + 1)
    elif isinstance(value, functools.partial):
        _named(value.args, found, depth + 1)
        _named(value.keywords, found, depth + 1)
    elif isinstance(value, (list, tuple, set, frozenset)):
        for item in value:
            _named(item, found, depth + 1)
    elif isinstance(value, dict):
        for item in value.values():
            _named(item, found, depth + 1)


class Packer:
    """Builds the `Shipment` of a task's arguments; a file or folder unchanged since it
    was last read (same size, time and inode) is not read again."""

    def __init__(self):
        self._read = {}         # path as named -> (signature, folder, relative)
        self._lock = threading.Lock()

    def _entry(self, named: str, kind: str):
        if kind == "code":      # the factory file's folder, as its loader and fingerprint
            path = Path(named).resolve()        # read it: a link's target's folder
            files = _source_files(path.parent, where=f"the code of {clip(named, 200)}")
        else:
            path = Path(named)
            files = [(path.name, path)]
        signature = _signature(files)
        with self._lock:
            kept = self._read.get(named)
        if kept is not None and signature is not None and kept[0] == signature:
            return kept[1], kept[2]
        folder = _folder(files)
        entry = (signature, folder, path.name)
        with self._lock:
            self._read[named] = entry
        return folder, path.name

    def pack(self, *values):
        """The `Shipment` of the files ``values`` name; None when they name none."""
        found = {}
        _named(values, found)
        if not found:
            return None
        folders, names, size = {}, [], 0
        for named in sorted(found):
            folder, relative = self._entry(named, found[named])
            if folder.digest not in folders:
                folders[folder.digest] = folder
                size += sum(len(data) for _, data in folder.files)
            names.append((named, folder.digest, relative))
        if size > MAX_SHIPPED_BYTES:
            raise ValueError(f"a task names {size >> 20} MiB of files to send to the workers "
                             f"(at most {MAX_SHIPPED_BYTES >> 20} MiB): "
                             f"{clip(', '.join(sorted(found)), 300)}")
        return Shipment(tuple(folders[d] for d in sorted(folders)), tuple(names))


def pack(*values):
    """The `Shipment` of the files ``values`` name (see the module); None for none."""
    return Packer().pack(*values)


_UNPACKED = set()               # (root, folder digest) written and checked by this process
_UNPACK_LOCK = threading.Lock()


def _copy_digest(target: Path, folder: ShippedFolder) -> str:
    """The digest of the copy at ``target`` of ``folder``'s files (those alone: a file
    the code wrote beside them is not its content); '' when one is missing."""
    try:
        return files_digest([(relative, (target / relative).read_bytes())
                             for relative, _ in folder.files])
    except OSError:
        return ""


def _write(root: Path, folder: ShippedFolder):
    """Write ``folder`` to ``root/<digest>`` through a temporary folder renamed into
    place; a copy there that differs (edited, torn) is first renamed aside, so no
    reader sees a folder half removed."""
    target = root / folder.digest
    if target.is_dir() and _copy_digest(target, folder) != folder.digest:
        aside = root / f".{folder.digest}.stale.{uuid.uuid4().hex}"
        try:
            os.rename(target, aside)
        except OSError:
            pass                                 # another process moved it first
        shutil.rmtree(aside, ignore_errors=True)
    if target.is_dir():
        return
    staging = root / f".{folder.digest}.{uuid.uuid4().hex}"
    try:
        for relative, data in folder.files:
            path = staging / relative
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        os.rename(staging, target)
    except OSError:
        shutil.rmtree(staging, ignore_errors=True)
        if not target.is_dir():           # not another process's copy: a real error
            raise


def unpack(shipment: Shipment, root=None) -> dict:
    """Write ``shipment``'s folders under ``root`` (default ``<cache>/shipped``), each
    once per content (`_write`); a copy found there is checked against its digest once
    per process. Returns ``{path as named: its copy}``."""
    root = Path(root) if root is not None else cache_root() / "shipped"
    with _UNPACK_LOCK:
        for folder in shipment.folders:
            if (root, folder.digest) in _UNPACKED and (root / folder.digest).is_dir():
                continue
            _write(root, folder)
            if _copy_digest(root / folder.digest, folder) != folder.digest:
                raise OSError(f"the copy of shipped files at {root / folder.digest} does not "
                              f"match what was sent; another process is changing it")
            _UNPACKED.add((root, folder.digest))
    return {named: str(root / digest / relative) for named, digest, relative in shipment.names}


def run_shipped(shipment: Shipment, fn, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` with the files of ``shipment`` in place of the paths the
    arguments name (a worker's side of `pack`)."""
    with shipped_copies(unpack(shipment)):
        return fn(*args, **kwargs)
