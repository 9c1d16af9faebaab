"""A dataset folder's files: its ``manifest.json`` (replaced atomically) and its ``.npy``
arrays, checked against the hashes the manifest recorded; and `ImageStore`, which
writes each finished chunk of images into them (`reach.chunks` runs the chunks)."""

import errno
import io
import json
import os
from pathlib import Path

import numpy as np

from reachwatch.diagrams import file_hash
from reachwatch.systems.files import atomic_write_bytes


def open_array(folder: Path, name: str, rows_shape: tuple, mmap_mode=None) -> np.ndarray:
    """``folder/name.npy``, checked against the leading ``rows_shape``; a truncated,
    corrupt or misshapen file is a ValueError naming it. (numpy's ``r+`` memmap would
    silently zero-extend a truncated file, so every file is first opened read-only.)"""
    path = folder / f"{name}.npy"
    try:
        array = np.load(path, mmap_mode="r" if mmap_mode else None, allow_pickle=False)
        if mmap_mode not in (None, "r"):
            del array
            array = np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"{path} is unreadable (truncated or corrupt: {e}); delete "
                         f"{folder} to rebuild the dataset") from None
    if array.shape[:len(rows_shape)] != tuple(rows_shape):
        raise ValueError(f"{path} holds shape {array.shape}, the manifest says "
                         f"{tuple(rows_shape)}; delete {folder} to rebuild the dataset")
    return array


#: What every dataset manifest holds, and of which type (the rest is checked where read).
MANIFEST_FIELDS = {"format": str, "samples": int, "estimate_size": int, "chunks_done": list,
                   "spec": dict, "labels": dict}


def read_manifest(folder: Path) -> dict:
    """The dataset manifest of ``folder``; a ValueError in one line when it cannot be
    read or lacks what every manifest holds (`MANIFEST_FIELDS`)."""
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{folder} is not a readable reachwatch dataset ({type(e).__name__}: "
                         f"{e}); delete it to rebuild the dataset") from None
    bad = ([] if not isinstance(manifest, dict) else
           [k for k, t in MANIFEST_FIELDS.items()
            if not isinstance(manifest.get(k), t) or isinstance(manifest.get(k), bool)])
    if not isinstance(manifest, dict) or bad:
        what = "not an object" if not isinstance(manifest, dict) else f"bad or no {', '.join(bad)}"
        raise ValueError(f"{folder} is not a readable reachwatch dataset (its manifest has "
                         f"{what}); delete it to rebuild the dataset")
    return manifest


def save_array(path: Path, array) -> None:
    """``array`` as the ``.npy`` file ``path``, replaced whole (`atomic_write_bytes`: a
    full disk is an error naming the file, and leaves no half-written one)."""
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array))
    atomic_write_bytes(path, buffer.getvalue())


def write_manifest(folder, manifest):
    atomic_write_bytes(folder / "manifest.json", json.dumps(manifest, indent=1).encode())


#: The arrays written once, when a dataset is begun (its labels); the others are filled
#: chunk by chunk (`FILLED`).
LABELLED = ("states", "values", "labels", "sources", "runs")
FILLED = ("images", "estimates", "ensemble")


def array_hashes(folder: Path, names) -> dict:
    """``{name: file_hash}`` of the ``folder/name.npy`` that exist among ``names``."""
    return {name: file_hash(folder / f"{name}.npy") for name in names
            if (folder / f"{name}.npy").is_file()}


def changed_arrays(folder: Path, manifest: dict, names=None) -> str:
    """Why the arrays of ``folder`` (those of ``names``; default all) no longer are the
    ones its manifest recorded (``manifest["hashes"]``), or "" when they are."""
    for name, want in manifest.get("hashes", {}).items():
        if names is not None and name not in names:
            continue
        path = folder / f"{name}.npy"
        if not path.is_file():
            return f"{path} is missing"
        if file_hash(path) != want:
            return f"{path} changed since the dataset was built"
    return ""


def finished(manifest: dict, spec) -> bool:
    """Whether every chunk of ``spec.chunk_size`` rows (a `DatasetSpec`'s) is done."""
    return len(manifest["chunks_done"]) >= -(-manifest["samples"] // spec.chunk_size)


def clear(folder: Path):
    """Remove the dataset in ``folder`` (its manifest first, so that a build stopped
    half way through this begins anew)."""
    (folder / "manifest.json").unlink(missing_ok=True)
    for path in folder.glob("*.npy"):
        path.unlink()


class ImageStore:
    """Where `reach.chunks.run_chunks` puts a dataset's rendered chunks: the chunk's
    rows of the ``arrays`` (the `FILLED` memmaps), flushed, then the chunk in the
    manifest's ``chunks_done`` (a chunk is done once it is recorded there), and when the
    last is done the filled arrays' hashes; the manifest is replaced atomically after
    each chunk, so an interrupted build resumes."""

    def __init__(self, folder: Path, manifest: dict, arrays: dict, chunk_size: int):
        self.folder, self.manifest, self.arrays = folder, manifest, arrays
        self.chunk_size = chunk_size

    def valid(self, chunk) -> bool:
        return chunk.start in self.manifest["chunks_done"]

    def store(self, chunk, out: dict):
        for name, array in self.arrays.items():
            array[chunk.start:chunk.stop] = out[name]
            array.flush()
        manifest = self.manifest
        manifest["chunks_done"] = sorted(manifest["chunks_done"] + [chunk.start])
        if finished(manifest, self):              # the filled arrays are final now
            manifest["hashes"] = {**manifest.get("hashes", {}),
                                  **array_hashes(self.folder, FILLED)}
        write_manifest(self.folder, manifest)


def reserved_memmap(path: Path, dtype, shape) -> np.memmap:
    """A new ``.npy`` array of ``shape`` mapped from ``path`` (``open_memmap``, ``w+``)
    with its bytes reserved on disk at once (``posix_fallocate``): a sparse file's
    pages are allocated only as rows are written, and a full disk then kills the
    process with SIGBUS, which no handler catches. Here it is an `OSError` naming the
    file and its size before any row is rendered (the file removed: what was reserved
    is given back once the caller lets go of the error). Where the file system cannot reserve, glibc writes the
    zeros instead, or (no support at all) the array stays sparse."""
    array = np.lib.format.open_memmap(path, "w+", dtype, shape)
    size = os.path.getsize(path)
    try:
        with open(path, "r+b") as f:
            os.posix_fallocate(f.fileno(), 0, size)
    except OSError as e:
        if e.errno in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            return array
        path.unlink(missing_ok=True)     # (its blocks freed once the mapping is let go)
        raise OSError(e.errno, f"{e.strerror}: cannot reserve {size / 2**20:.1f} MiB for "
                               f"the dataset array", str(path)) from None
    return array
