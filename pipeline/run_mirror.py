"""A run directory at an fsspec URL (``s3://bucket/study`` with s3fs, ``gs://...``,
``file:///...``, ``memory://...``). The run works in a local copy, its working
directory: `RunMirror.pull` fetches what the URL holds before the first stage (so a
run resumes on any machine), and `RunMirror.push` puts every file added or changed
since the last push after each stage, the stage records (``stages/*.json``) and
``run.yaml`` last, so a record at the URL never names a file that is not there yet.
A stage killed half-way keeps its finished chunks in the working directory (a re-run
on the same machine resumes them); elsewhere it starts that stage again."""

import hashlib
import json
import os
from pathlib import Path

from reachwatch.systems.files import (atomic_write_bytes, cache_join, cache_root, get_location,
                                      is_url, list_location, put_location)

#: The working directory's own record of what it put to its URL (the URL, and
#: ``{relative: [size, mtime_ns, inode]}``).
PUSHED = ".pushed.json"

#: How many files `RunMirror.push` puts between two saves of `PUSHED`.
SAVE_EVERY = 200

#: Files always fetched again by `RunMirror.pull` (small; they say what is valid).
RECORDS = ("run.yaml", "stages/")


def default_work_dir(url: str) -> Path:
    """``<cache>/runs/<digest of the URL>``: one working directory per run URL."""
    return cache_root() / "runs" / hashlib.sha256(url.encode()).hexdigest()[:16]


def _is_record(relative: str) -> bool:
    return relative == RECORDS[0] or relative.startswith(RECORDS[1])


class RunMirror:
    """The run directory at ``url`` and its working directory ``local`` (default
    `default_work_dir`)."""

    def __init__(self, url: str, local=None):
        if not is_url(url):
            raise ValueError(f"not an fsspec URL: {url!r}")
        self.url = url.rstrip("/")
        self.local = Path(local) if local else default_work_dir(self.url)
        try:
            self.local.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"cannot create the working directory {self.local} of "
                             f"{self.url}: {e.strerror}") from None

    def _pushed(self) -> dict:
        """What this working directory last put to (or fetched from) this URL; nothing
        for another URL (a working directory reused for a second run is put whole)."""
        try:
            saved = json.loads((self.local / PUSHED).read_text())
        except (OSError, ValueError):
            return {}
        return saved.get("files", {}) if saved.get("url") == self.url else {}

    def _signature(self, relative: str):
        stat = (self.local / relative).stat()      # an atomic rewrite is a new inode
        return [stat.st_size, stat.st_mtime_ns, stat.st_ino]

    def pull(self) -> int:
        """Fetch each file at the URL the working directory lacks or holds at another
        size, and every record, but never over a file changed here and not put yet (it
        is newer) nor a hidden one (a temporary file a killed put left); returns how
        many were fetched. A file fetched counts as put."""
        try:
            remote = list_location(self.url)
        except OSError as e:
            raise ValueError(f"--out {self.url}: cannot list it ({type(e).__name__}: "
                             f"{e})") from None
        pushed, fetched = self._pushed(), 0
        for relative, size in sorted(remote.items()):
            target = self.local / relative
            if os.path.basename(relative).startswith("."):
                continue                          # a temporary file a killed put left
            if target.is_file() and pushed.get(relative) != self._signature(relative):
                continue                          # work here not put yet: it is newer
            if not (_is_record(relative) or not target.is_file()
                    or target.stat().st_size != size):
                continue
            get_location(cache_join(self.url, relative), target)
            pushed[relative] = self._signature(relative)
            fetched += 1
        self._save(pushed)
        return fetched

    def push(self) -> int:
        """Put every file of the working directory added or changed since it was last
        pushed (or pulled), the records last; returns how many were put."""
        pushed = self._pushed()
        changed = []
        for path in sorted(self.local.rglob("*")):
            relative = path.relative_to(self.local).as_posix()
            if (not path.is_file() or relative == PUSHED or path.name.startswith(".")
                    or pushed.get(relative) == self._signature(relative)):
                continue
            changed.append(relative)
        changed.sort(key=_is_record)            # records after what they name
        try:
            for i, relative in enumerate(changed):
                signature = self._signature(relative)
                put_location(self.local / relative, cache_join(self.url, relative))
                pushed[relative] = signature
                if i % SAVE_EVERY == SAVE_EVERY - 1:    # a kill re-puts at most these
                    self._save(pushed)
        finally:
            self._save(pushed)
        return len(changed)

    def _save(self, pushed: dict):
        atomic_write_bytes(self.local / PUSHED, json.dumps(
            {"url": self.url, "files": pushed}, sort_keys=True).encode())
