"""Files: atomic writes (a reader never sees a half-written file) and content hashes."""

import hashlib
import os
import tempfile
from pathlib import Path


def cache_root() -> Path:
    """Where reachwatch caches generated assets and sweeps: ``$REACHWATCH_CACHE`` or
    ``~/.cache/reachwatch``."""
    return Path(os.environ.get("REACHWATCH_CACHE", Path.home() / ".cache" / "reachwatch"))


def file_hash(path, length: int = 16) -> str:
    """SHA-256 (hex, first ``length`` digits) of a file's bytes, read in blocks: the
    cache key of a checkpoint, and how a stage record recognises its output files."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:length]


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file in the same folder + rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)          # mkstemp's 0600 is not what users expect
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
