"""Files: atomic writes (a reader never sees a half-written file), content hashes, and
the copies of files that came with a task (`local_copy`)."""

import contextlib
import contextvars
import errno
import hashlib
import os
import shutil
import tempfile
import threading
from pathlib import Path

from .checks import clip


def cache_root() -> Path:
    """Where reachwatch caches generated assets and sweeps: ``$REACHWATCH_CACHE`` or
    ``~/.cache/reachwatch``."""
    return Path(os.environ.get("REACHWATCH_CACHE", Path.home() / ".cache" / "reachwatch"))


# --- content a driver keyed its work with -------------------------------------------

#: What this process put in cache keys (`remember_keyed`): ``{name: digests}``, a file
#: by the path a task names it with (`file_hash`, 64 digits), a user's code by its file.
_KEYED = {}
_KEYED_LOCK = threading.Lock()
#: What a task brought from its driver (`keyed_by_driver`); None: no check.
_DRIVER_KEYED = contextvars.ContextVar("reachwatch_driver_keyed", default=None)


#: The key of `keyed_digests` that holds the driver's working directory, against which
#: a task resolves the relative paths it names (a worker's own may be another).
DRIVER_CWD = "cwd:"


def _keyed_name(name, cwd=None) -> str:
    """``name`` as keyed: a path made absolute against ``cwd`` (default: this process's
    working directory; ``./m.pt`` and its absolute path are one file), behind its
    ``code:`` prefix when it has one; a URL as it is."""
    text = os.fspath(name)
    prefix = "code:" if text.startswith("code:") else ""
    path = text[len(prefix):]
    if is_url(path) or not path:
        return prefix + path
    if os.path.isabs(path):
        return prefix + os.path.normpath(path)
    return prefix + os.path.normpath(os.path.join(cwd or os.getcwd(), path))


def remember_keyed(name: str, digest: str) -> str:
    """Notes that this process keyed work with ``name`` (a path as tasks name it) holding
    content of ``digest``; returns ``digest``."""
    with _KEYED_LOCK:
        _KEYED.setdefault(_keyed_name(name), set()).add(digest)
    return digest


def keyed_digests() -> dict:
    """``{name: digests}`` this process keyed work with, and its working directory
    (`DRIVER_CWD`): what a task it sends takes."""
    with _KEYED_LOCK:
        keyed = {name: frozenset(digests) for name, digests in _KEYED.items()}
    try:
        here = {DRIVER_CWD: frozenset([os.getcwd()])} if keyed else {}
    except OSError:                   # the working directory is gone: absolute names only
        here = {}
    return {**keyed, **here}


@contextlib.contextmanager
def keyed_by_driver(keyed):
    """Runs the block (a task on a worker) with ``keyed`` as its driver's
    `keyed_digests`: a checkpoint or a user's code it loads under a name the driver
    keyed must hold content the driver keyed (`check_keyed`), not a file edited since,
    which would run under the old content's key. Empty or None: no check."""
    token = _DRIVER_KEYED.set(dict(keyed) if keyed else None)
    try:
        yield
    finally:
        _DRIVER_KEYED.reset(token)


def keyed_check_active() -> bool:
    """Whether this block runs a task that brought its driver's keys (`check_keyed` has
    something to check; else a caller need not compute a digest for it)."""
    return _DRIVER_KEYED.get() is not None


def check_keyed(name, digest: str, what: str) -> None:
    """Raise ValueError, in one line, when a task's driver keyed ``name`` with other
    content than ``digest`` (``what``: the file or code, in words; `keyed_by_driver`).
    A name the driver did not key is not checked."""
    keyed = _DRIVER_KEYED.get()
    if keyed is None:
        return
    cwd = next(iter(keyed.get(DRIVER_CWD, ())), None)     # the driver's, where it sent it
    digests = keyed.get(_keyed_name(name, cwd))
    if digests is not None and digest not in digests:
        raise ValueError(f"{what} changed after this run keyed its results with it; start "
                         f"the run again (it resumes from its caches)")


def file_hash(path, length: int = 16) -> str:
    """SHA-256 (hex, first ``length`` digits) of a file's bytes, read in blocks: the
    cache key of a checkpoint, and how a stage record recognises its output files."""
    digest = hashlib.sha256()
    with open(local_copy(path), "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:length]


@contextlib.contextmanager
def _replacing(path: Path):
    """A temporary file's name beside ``path``, which replaces ``path`` (with a new
    file's mode, not mkstemp's 0600) when the block ends without an error, its bytes on
    disk first (``fsync``: after a power loss the name holds the whole new file or the
    old one, not an empty one; a file system that cannot sync is let be)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        yield tmp
        _synced(tmp, path)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _synced(tmp, path: Path) -> None:
    """``fsync`` of the file ``tmp`` (about to replace ``path``); an error names
    ``path``, except that a file system without ``fsync`` is let be."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as e:
        if e.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EROFS):
            raise OSError(e.errno, e.strerror, str(path)) from e
    finally:
        os.close(fd)


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file in the same folder + rename; a
    write that fails (a full disk) names ``path``."""
    path = Path(path)
    with _replacing(path) as tmp:
        try:
            with open(tmp, "wb") as f:
                f.write(data)
        except OSError as e:
            if e.filename is None and e.errno is not None:
                raise OSError(e.errno, e.strerror, str(path)) from e
            raise
    return path


# --- cache locations: a local folder or an fsspec URL ----------------------------------
# A cache (sweep chunks, batches of rollouts) is read and written by the driver alone, so
# it may live anywhere fsspec reaches (``memory://``, ``s3://`` with s3fs installed, a
# chained ``simplecache::s3://...``): no worker needs the driver's filesystem. A local
# path (or a ``file://`` URL, made one) takes the plain file calls it always did;
# fsspec is imported only for a URL.

def is_url(location) -> bool:
    """Whether ``location`` is an fsspec URL (``memory://...``, ``s3://...``, a chained
    ``a::b://...``) rather than a local path."""
    return isinstance(location, str) and ("://" in location or "::" in location)


def cache_location(location):
    """A cache folder as reachwatch holds it: a local path, or a ``file://`` URL, as a
    `Path`; any other fsspec URL as its string, unchanged."""
    if isinstance(location, Path):
        return location
    location = os.fspath(location)
    if location.startswith("file://") and "::" not in location:
        from fsspec.implementations.local import LocalFileSystem
        return Path(LocalFileSystem._strip_protocol(location))
    return location if is_url(location) else Path(location)


def cache_join(base, *parts):
    """``base/part/...`` for a cache location: a `Path` for a local one, the URL string
    with ``/``-joined parts for any other (never ``Path(url)``, which breaks ``//``)."""
    base = cache_location(base)
    if isinstance(base, Path):
        return base.joinpath(*parts)
    return "/".join([base.rstrip("/"), *parts])


def url_filesystem(url):
    """``(filesystem, path)`` of a URL; a ValueError in one line when its protocol is
    unknown or needs a package that is not installed (s3fs for ``s3://``)."""
    import fsspec                     # only for a URL: a local cache never imports it
    try:
        return fsspec.core.url_to_fs(url)
    except ImportError as e:
        raise ValueError(f"{clip(url, 200)}: {e} (its fsspec implementation is not "
                         f"installed)") from None
    except ValueError as e:
        raise ValueError(f"{clip(url, 200)}: {e}") from None


def make_folder(location):
    """Create the cache folder ``location`` (and its parents) if missing."""
    location = cache_location(location)
    if isinstance(location, Path):
        location.mkdir(parents=True, exist_ok=True)
    else:                             # a no-op on object stores, which have no folders
        fs, path = url_filesystem(location)
        fs.makedirs(path, exist_ok=True)


def read_location(location) -> bytes:
    """The bytes of the file or object ``location``; FileNotFoundError (an OSError)
    when there is none."""
    location = cache_location(location)
    if isinstance(location, Path):
        return location.read_bytes()
    fs, path = url_filesystem(location)
    return fs.cat_file(path)


#: The fields of an fsspec listing that change when an object is written again, most
#: telling first: object stores' content tags and generations, then modification or
#: creation times (`list_location`'s versions).
VERSION_FIELDS = ("ETag", "etag", "md5Hash", "crc32c", "generation", "version_id",
                  "LastModified", "last_modified", "updated", "mtime", "created")


def _version(info: dict) -> str:
    """What of an fsspec listing's ``info`` changes when the file is written again."""
    return "|".join(f"{key}={info[key]}" for key in VERSION_FIELDS if info.get(key) is not None)


def list_location(location, versions: bool = False) -> dict:
    """``{relative path: size in bytes}`` of every file under the folder ``location``
    (local or an fsspec URL); empty when there is none. With ``versions``, ``{relative
    path: [size, version]}``, the version a string that changes when the file is
    written again (its store's tag or generation, or its modification or creation
    time: `VERSION_FIELDS`), "" where the listing says none."""
    location = cache_location(location)
    if isinstance(location, Path):
        if not location.is_dir():
            return {}
        return {p.relative_to(location).as_posix(): [stat.st_size, f"mtime={stat.st_mtime_ns}"]
                if versions else stat.st_size
                for p in location.rglob("*") if p.is_file() for stat in [p.stat()]}
    fs, root = url_filesystem(location)
    try:
        found = fs.find(root, detail=True)
    except FileNotFoundError:
        return {}
    root = root.rstrip("/")
    return {path[len(root):].lstrip("/"): [int(info.get("size") or 0), _version(info)]
            if versions else int(info.get("size") or 0)
            for path, info in found.items() if info.get("type") == "file"
            and path.startswith(root + "/")}


def put_location(path, location):
    """Copy the local file ``path`` to the file or object ``location`` whole: a reader
    sees the old content or the new (a local target through a rename; an object store
    puts an object whole), streamed, not read into memory."""
    location = cache_location(location)
    if isinstance(location, Path):
        with _replacing(location) as tmp:
            shutil.copyfile(path, tmp)
        return location
    fs, remote = url_filesystem(location)
    fs.put_file(os.fspath(path), remote)
    return location


def get_location(location, path):
    """Copy the file or object ``location`` to the local file ``path``, atomically."""
    source = cache_location(location)
    with _replacing(Path(path)) as tmp:
        if isinstance(source, Path):
            shutil.copyfile(source, tmp)
        else:
            fs, remote = url_filesystem(source)
            fs.get_file(remote, tmp)
    return Path(path)


def write_location(location, data: bytes):
    """Write ``data`` to the file or object ``location`` atomically: a reader sees the
    old content or the new, never part of it."""
    location = cache_location(location)
    if isinstance(location, Path):
        return atomic_write_bytes(location, data)
    # An object store (S3, GCS, Azure) puts an object whole or not at all, so one call
    # writing all the bytes is atomic there; a temporary object and a rename would be
    # a copy and a delete, not atomic. (A filesystem without that guarantee, say SFTP,
    # could leave a partial file; chunks carry a checksum, so one is computed again.)
    fs, path = url_filesystem(location)
    fs.pipe_file(path, data)
    return location


# --- files that came with a task ------------------------------------------------------
# A task sent to a worker on another machine (or started in another directory) carries
# the files its arguments name (`reachwatch.diagrams.shipping`): the worker writes them
# into a folder of its own and runs the task inside `shipped_copies`, and every place
# that opens a file a task names (a checkpoint, a user's code, a fingerprint) asks
# `local_copy` first, so no path of the driver's is ever opened there.

_SHIPPED = contextvars.ContextVar("reachwatch_shipped_copies", default=None)


def local_copy(path):
    """The copy of ``path`` (as a task names it) that came with the running task, as a
    string; ``path`` itself, unchanged, outside such a task or for a path it did not
    bring."""
    copies = _SHIPPED.get()
    if not copies or not isinstance(path, (str, os.PathLike)):
        return path
    return copies.get(os.fspath(path), path)


@contextlib.contextmanager
def shipped_copies(copies: dict):
    """Within: `local_copy` answers each path of ``copies`` (``{as named: local copy}``)
    with its copy, in this thread and context only."""
    token = _SHIPPED.set(dict(copies))
    try:
        yield
    finally:
        _SHIPPED.reset(token)


def strict_json(value, **kwargs) -> str:
    """JSON text of ``value`` that any JSON parser reads: each float that is not finite
    (NaN, an infinity: Python's JSON would write ``NaN``, ``-Infinity``) is written
    ``null``, for a document that holds no null of its own; `nan_for_null` reads it
    back. numpy numbers are written as Python's."""
    import json
    import math

    import numpy as np

    def plain(x):
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        if isinstance(x, (float, np.floating)):
            return float(x) if math.isfinite(x) else None
        if isinstance(x, np.integer):
            return int(x)
        return x

    return json.dumps(plain(value), allow_nan=False, **kwargs)


def nan_for_null(value, lists=None, null=float("nan")):
    """Parsed JSON ``value`` (a `strict_json` document) with each null a NaN; ``lists``:
    ``{key: number}``, the number a null stands for in the list under that key (e.g.
    -inf where the document's NaN and -inf meant different things)."""
    lists = lists or {}
    if isinstance(value, dict):
        return {k: nan_for_null(v, lists, lists.get(k, float("nan")) if isinstance(v, list)
                                else float("nan"))
                for k, v in value.items()}
    if isinstance(value, list):
        return [nan_for_null(v, lists, null) for v in value]
    return null if value is None else value
