"""A run directory at an fsspec URL (``s3://bucket/study`` with s3fs, ``gs://...``,
``file:///...``, ``memory://...``). The run works in a local copy, its working
directory: `RunMirror.pull` fetches what the URL holds before the first stage (so a
run resumes on any machine), and `RunMirror.push` puts every file added or changed
since the last push after each stage, the stage records (``stages/*.json``) and
``run.yaml`` last, so a record at the URL never names a file that is not there yet.
While a stage runs, `RunMirror.pushing_every` puts the chunks it has finished so far
at a fixed interval: a stage killed half-way (its machine lost, say) resumes on
another machine from the chunks put by then, as it does on the same machine from
those in the working directory. Chunk files alone, because each is written whole (a
hidden temporary file renamed; hidden files are never put) and checked by its
checksum when read back; other files of a stage may describe each other (a dataset's
manifest and its arrays, filled in place) and are put together when it ends."""

import contextlib
import hashlib
import json
import os
import threading
from pathlib import Path
from typing import Callable

from reachwatch.reach.chunk_files import is_chunk_file
from reachwatch.systems.files import (atomic_write_bytes, cache_join, cache_root, get_location,
                                      is_url, list_location, put_location, url_filesystem)

#: The working directory's own record of what it put to its URL (the URL,
#: ``{relative: [size, mtime_ns, inode]}`` of the files here, and ``{relative: version}``
#: of them at the URL: `systems.files.list_location`'s versions).
PUSHED = ".pushed.json"

#: The version recorded for a file put when the URL could not be listed after it
#: (`systems.files.list_location`'s versions are "" or ``field=value`` pairs: never this).
UNKNOWN_VERSION = "?"

#: How many files `RunMirror.push` puts, or `RunMirror.pull` fetches, between two saves
#: of `PUSHED`.
SAVE_EVERY = 200

#: Files always fetched again by `RunMirror.pull` (small; they say what is valid).
RECORDS = ("run.yaml", "stages/")


def default_work_dir(url: str) -> Path:
    """``<cache>/runs/<digest of the URL>``: one working directory per run URL."""
    return cache_root() / "runs" / hashlib.sha256(url.encode()).hexdigest()[:16]


def _is_record(relative: str) -> bool:
    return relative == RECORDS[0] or relative.startswith(RECORDS[1])


def _bytes_bar(total: int, what: str, shown: bool):
    """A tqdm bar of ``total`` bytes (``what``: its text), hidden unless ``shown``."""
    from tqdm import tqdm
    return tqdm(total=total, unit="B", unit_scale=True, unit_divisor=1024, desc=what,
                disable=not shown, leave=False)


class RunMirror:
    """The run directory at ``url`` and its working directory ``local`` (default
    `default_work_dir`)."""

    def __init__(self, url: str, local=None):
        if not is_url(url):
            raise ValueError(f"not an fsspec URL: {url!r}")
        self.url = url.rstrip("/")
        url_filesystem(self.url)               # an unknown protocol: one line, nothing made
        self.local = Path(local) if local else default_work_dir(self.url)
        try:
            self.local.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"cannot create the working directory {self.local} of "
                             f"{self.url}: {e.strerror}") from None
        self._pushing = threading.Lock()       # the interval's push and the stage's, one at a time

    def _pushed(self) -> dict:
        """What this working directory last put to (or fetched from) this URL; nothing
        for another URL (a working directory reused for a second run is put whole)."""
        return self._saved("files")

    def _versions(self) -> dict:
        """The URL's versions of the files this working directory last put or fetched."""
        return self._saved("remote")

    def _saved(self, part: str) -> dict:
        try:
            saved = json.loads((self.local / PUSHED).read_text())
        except (OSError, ValueError):
            return {}
        return saved.get(part, {}) if saved.get("url") == self.url else {}

    def _signature(self, relative: str):
        stat = (self.local / relative).stat()      # an atomic rewrite is a new inode
        return [stat.st_size, stat.st_mtime_ns, stat.st_ino]

    def pull(self, progress: bool = False) -> int:
        """Fetch each file at the URL the working directory lacks, holds at another size,
        or last put or fetched at another version there (written again since, by a run
        elsewhere: an array filled in place keeps its size), and every record, but never
        over a file changed here and not put yet (it is newer) nor a hidden one (a
        temporary file a killed put left); returns how many were fetched. A file fetched
        counts as put. ``progress``: a bar of the bytes fetched."""
        try:
            remote = list_location(self.url, versions=True)
        except OSError as e:
            raise ValueError(f"--out {self.url}: cannot list it ({type(e).__name__}: "
                             f"{e})") from None
        pushed, versions, fetched = self._pushed(), self._versions(), 0
        wanted = []
        for relative, (size, version) in sorted(remote.items()):
            target = self.local / relative
            if os.path.basename(relative).startswith("."):
                continue                          # a temporary file a killed put left
            if target.is_file() and pushed.get(relative) != self._signature(relative):
                continue                          # work here not put yet: it is newer
            known = versions.get(relative)        # None: put or fetched before versions
            if not (_is_record(relative) or not target.is_file()
                    or target.stat().st_size != size
                    or (known is not None and known != version)):
                versions[relative] = version
                continue
            wanted.append((relative, size, version))
        try:
            with _bytes_bar(sum(w[1] or 0 for w in wanted), f"fetched from {self.url}",
                            progress) as bar:
                for relative, size, version in wanted:
                    target = self.local / relative
                    get_location(cache_join(self.url, relative), target)
                    pushed[relative], versions[relative] = self._signature(relative), version
                    fetched += 1
                    bar.update(size or 0)
                    if fetched % SAVE_EVERY == 0:     # a pull killed later keeps them
                        self._save(pushed, versions)
        finally:            # interrupted too: what was fetched counts as put, not as work here
            self._save(pushed, versions)
        return fetched

    def push(self, only: Callable[[str], bool] = None, stop: threading.Event = None,
             progress: bool = False) -> int:
        """Put every file of the working directory added or changed since it was last
        pushed (or pulled), the records last, or those alone whose name ``only(name)``
        accepts; returns how many were put. One push at a time; a file removed between
        the listing and its put is left to the next push, as is every file left when
        ``stop`` is set. ``progress``: a bar of the bytes put."""
        with self._pushing:
            pushed, versions = self._pushed(), self._versions()
            changed = []
            for path in sorted(self.local.rglob("*")):
                relative = path.relative_to(self.local).as_posix()
                if (relative == PUSHED or path.name.startswith(".")
                        or (only is not None and not only(path.name))):
                    continue
                try:
                    if not path.is_file() or pushed.get(relative) == self._signature(relative):
                        continue
                except FileNotFoundError:             # removed since the listing
                    continue
                changed.append(relative)
            changed.sort(key=_is_record)            # records after what they name
            put, done, listed_from = 0, [], 0     # how many put, which; the first not listed
            bar = _bytes_bar(sum(signature[0] for signature in (
                self._signature_or_none(r) for r in changed) if signature),
                f"put to {self.url}", progress)
            try:
                for relative in changed:
                    if stop is not None and stop.is_set():
                        break
                    try:
                        signature = self._signature(relative)
                        put_location(self.local / relative, cache_join(self.url, relative))
                    except FileNotFoundError:
                        if (self.local / relative).exists():
                            raise                     # the URL's side: not ours to skip
                        continue                      # removed since the listing
                    bar.update(signature[0])
                    pushed[relative] = signature
                    put += 1
                    done.append(relative)
                    if put % SAVE_EVERY == 0:         # a kill re-puts at most these
                        self._save(pushed, self._put_versions(versions, done[listed_from:]))
                        listed_from = len(done)
            finally:
                bar.close()
                if put:
                    self._save(pushed, self._put_versions(versions, done[listed_from:]))
            return put

    def _signature_or_none(self, relative: str):
        try:
            return self._signature(relative)
        except FileNotFoundError:                 # removed since the listing
            return None

    def _put_versions(self, versions: dict, relatives) -> dict:
        """``versions`` with the URL's versions of the files ``relatives`` just put (one
        listing of the URL). A file it cannot list gets the version `UNKNOWN_VERSION`,
        which no version at the URL equals: the next `pull` fetches it again rather than
        trust it."""
        try:
            listed = list_location(self.url, versions=True)
        except OSError:
            listed = {}
        for relative in relatives:
            versions[relative] = (listed[relative][1] if relative in listed
                                  else UNKNOWN_VERSION)
        return versions

    @contextlib.contextmanager
    def pushing_every(self, seconds: float, log=None, warn=None):
        """While the block runs, `push` the chunk files (`is_chunk_file`) every
        ``seconds`` (0: never) from a daemon thread, so that the chunks a long stage has
        finished reach the URL before the stage ends; ``log(message)`` says how many. A
        push that fails is ``warn``-ed (once until the error changes) and tried again
        ``seconds`` later. When the block ends, a push under way stops after the file it
        is putting (the stage's own push puts the rest)."""
        if not 0 <= seconds <= threading.TIMEOUT_MAX:
            raise ValueError(f"a push interval must be 0 to {threading.TIMEOUT_MAX:g} "
                             f"seconds, got {seconds:g}")
        if not seconds:
            yield
            return
        stop = threading.Event()

        def keep_pushing():
            said = None
            while not stop.wait(seconds):
                try:
                    count = self.push(only=is_chunk_file, stop=stop)
                    said = None
                    if count and log is not None:
                        log(f"{count} chunk files put to {self.url} (every {seconds:g} s)")
                except Exception as e:   # the stage goes on; its own push reports again
                    error = f"{type(e).__name__}: {e}"
                    if warn is not None and error != said:
                        warn(f"could not put the finished chunks to {self.url} ({error}); "
                             f"trying again every {seconds:g} s")
                    said = error

        thread = threading.Thread(target=keep_pushing, name="run-mirror-push", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()

    def _save(self, pushed: dict, versions: dict):
        atomic_write_bytes(self.local / PUSHED, json.dumps(
            {"url": self.url, "files": pushed, "remote": versions}, sort_keys=True).encode())
