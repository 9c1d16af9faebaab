"""A job's chunks and their files: `Chunk` (rows ``start:stop``), `split`, and
`FolderStore`, the store `reach.chunks.run_chunks` keeps finished chunks in (one
``.npz`` per chunk, written atomically with its `chunk_checksum`, local or at an
fsspec URL)."""

import dataclasses as dc
import hashlib
import io
import re
from pathlib import Path
from typing import Callable

import numpy as np

from reachwatch.systems.files import cache_join, cache_location, read_location, write_location


@dc.dataclass(frozen=True)
class Chunk:
    """Rows ``start:stop`` of a job, its ``index``-th chunk."""
    index: int
    start: int
    stop: int

    @property
    def rows(self) -> int:
        return self.stop - self.start


def split(count: int, size: int) -> list:
    """``count`` rows as `Chunk` s of ``size`` rows (the last one shorter)."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"chunk_size must be a whole number >= 1, got {size!r}")
    return [Chunk(i, s, min(s + int(size), int(count)))
            for i, s in enumerate(range(0, int(count), int(size)))]


#: The entry of a chunk file holding `chunk_checksum` of its other arrays.
CHECKSUM = "checksum"


def chunk_checksum(arrays: dict) -> str:
    """SHA-256 (hex) of a chunk's arrays (all but `CHECKSUM`): names, dtypes, shapes and
    bytes. Stored in the chunk file when written and compared when it is read, so a
    chunk whose numbers changed since (its shape kept) is computed again."""
    digest = hashlib.sha256()
    for name in sorted(k for k in arrays if k != CHECKSUM):
        a = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def checksum_ok(arrays: dict) -> bool:
    """Whether a chunk's arrays match the `CHECKSUM` they were stored with (a chunk
    written before chunks carried one is taken as it is)."""
    return CHECKSUM not in arrays or str(arrays[CHECKSUM]) == chunk_checksum(arrays)


def store_chunk_file(path, arrays: dict):
    """Write a chunk's ``arrays`` (an ``.npz``, atomically: `write_location`) with their
    `chunk_checksum`; ``path`` is local or an fsspec URL."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays, **{CHECKSUM: np.asarray(chunk_checksum(arrays))})
    return write_location(path, buffer.getvalue())


def read_chunk_file(path, names=None) -> dict:
    """The arrays ``names`` (default: all, `CHECKSUM` too) of the chunk file ``path``:
    a local file is loaded as it lies, an fsspec URL's object read whole first. Raises
    what loading raises (missing, truncated, not an ``.npz``, an array it lacks)."""
    path = cache_location(path)
    source = path if isinstance(path, Path) else io.BytesIO(read_location(path))
    with np.load(source, allow_pickle=False) as data:
        return {k: data[k] for k in (data.files if names is None else names)}


def chunk_path(folder, index: int):
    """The file of chunk ``index`` in a `FolderStore`'s ``folder`` (a `Path`, or a URL
    string for a folder given as one)."""
    return cache_join(folder, f"chunk_{index:06d}.npz")


def is_chunk_file(name: str) -> bool:
    """Whether the file ``name`` (a path's last part) is one `chunk_path` names: written
    whole, and checked by its checksum when read."""
    return re.fullmatch(r"chunk_\d{6,}\.npz", name) is not None


#: The entry of a chunk file that holds the rows ``[start, stop)`` it covers (written by a
#: `FolderStore` made with ``rows=True``).
ROWS = "_rows"


class FolderStore:
    """Chunks as files ``folder/chunk_000000.npz``, ... (`store_chunk_file`); ``folder``
    is a local path or an fsspec URL (``memory://...``, ``s3://...``). A stored
    chunk is valid when it loads, matches its checksum, covers the chunk's rows where
    its file says which (`ROWS`), and ``fits(chunk, arrays)`` (default: always);
    ``rows``: write `ROWS` into each chunk file, so that a chunk written with another
    chunk size is run again rather than read into the wrong rows (for a job whose key
    does not hold its chunk size), and take no file that does not say its rows;
    ``keep``: hold the arrays read or stored, for `read`; ``stamp``: ``{name: str}``
    written into each chunk file and required the same in each file read (what the
    folder's name does not key: a chunk another writer stored in the folder for other
    work is run again, not read)."""

    def __init__(self, folder, fits: Callable = None, keep: bool = False, rows: bool = False,
                 stamp: dict = None):
        self.folder, self.fits, self.rows = cache_location(folder), fits, rows
        self.stamp = {name: np.asarray(str(value)) for name, value in (stamp or {}).items()}
        self.kept = {} if keep else None

    def path(self, chunk: Chunk):
        return chunk_path(self.folder, chunk.index)

    def read(self, chunk: Chunk):
        """The chunk's arrays (without `CHECKSUM`), or None when its file is missing,
        truncated, corrupt, fails its checksum or does not fit."""
        if self.kept is not None and chunk.index in self.kept:
            return self.kept[chunk.index]
        try:
            arrays = read_chunk_file(self.path(chunk))
            if not checksum_ok(arrays):
                return None
            arrays.pop(CHECKSUM, None)
            covered = arrays.pop(ROWS, None)
            if covered is None and self.rows:   # which rows it holds, unsaid: run it again
                return None
            if covered is not None and covered.tolist() != [chunk.start, chunk.stop]:
                return None
            for name, value in self.stamp.items():
                if str(arrays.pop(name, None)) != str(value):
                    return None
            if self.fits is not None and not self.fits(chunk, arrays):
                return None
        except Exception:   # missing, truncated, corrupt or lacking an array: run it again
            return None
        if self.kept is not None:
            self.kept[chunk.index] = arrays
        return arrays

    def valid(self, chunk: Chunk) -> bool:
        return self.read(chunk) is not None

    def store(self, chunk: Chunk, arrays: dict):
        written = {**arrays, **self.stamp}
        if self.rows:
            written[ROWS] = np.array([chunk.start, chunk.stop])
        store_chunk_file(self.path(chunk), written)
        if self.kept is not None:
            self.kept[chunk.index] = arrays
