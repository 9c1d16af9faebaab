"""The run (`Run`) of ``reachwatch run``: its folder, records and the stage engine
(sweep and solve are in `brt_stages`, the dataset in `dataset_stages`, the detector's
train -> evaluate in `detector_stages`). Each stage reads the records of the stages
before it and returns JSON-able outputs (paths relative to the run directory);
`Run.stage` skips a stage whose key (a digest of its inputs) matches its record. The
heavy work inside a stage is itself chunked and cached by content, so a killed stage
resumes where it stopped."""

import copy
import datetime
import hashlib
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import file_hash
from reachwatch.reach import Grid, InlineExecutor, ValueFunction
from reachwatch.reach.application import load_application
from reachwatch.systems.checks import short
from reachwatch.systems.files import atomic_write_bytes, cache_location
from reachwatch.training.dataset import load_dataset

from .keys import digest
from .spec import RunSpec, dump_run_spec


def _plain(value):
    return value.item() if hasattr(value, "item") else str(value)


#: Bump when a record's meaning changes; older records then run their stage again.
RECORD_FORMAT = 2
_log = logging.getLogger("reachwatch")


def record_check(record: dict) -> str:
    """The digest of everything in a stage record but its ``check``: a record whose
    outputs (or key, or files) were edited after its stage wrote it no longer matches
    its check, and is not trusted (its stage runs again)."""
    text = json.dumps({k: v for k, v in record.items() if k != "check"}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _check_same_run(spec_path: Path, name: str):
    """Refuse, in one line, a run directory that holds another run (its recorded run
    file has another ``name``): its stages' files would be overwritten one by one."""
    import yaml
    try:
        recorded = yaml.safe_load(spec_path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        # whose run it is cannot be told, and a run writes it whole (atomically): not
        # rewritten over what may be another run's files
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{spec_path} cannot be read ({reason}), so whose run "
                         f"{spec_path.parent} holds is unknown: give another --out, or "
                         f"delete {spec_path} to reuse the directory") from None
    other = recorded.get("name") if isinstance(recorded, dict) else None
    if not isinstance(other, str):
        # not a run file a run wrote (every one names its run): harmless in an empty
        # directory, but beside stage records whose run they are is unknown
        if any((spec_path.parent / "stages").glob("*.json")):
            raise ValueError(f"{spec_path} names no run, so whose run {spec_path.parent} "
                             f"holds is unknown: give another --out, or delete {spec_path} "
                             f"to reuse the directory")
        return
    if other != name:
        raise ValueError(f"{spec_path.parent} holds the run {short(other)}, not "
                         f"{short(name)}: give another --out, or delete {spec_path} to "
                         f"reuse the directory")


class Run:
    """A run directory: the spec (``run.yaml``), artifacts, and one record per
    finished stage (``stages/NAME.json``: key, seconds, outputs, the size and
    content hash of every file its outputs name, and a check over all of it)."""

    def __init__(self, spec: RunSpec, root, *, executor=None, progress=True, log=_log.info,
                 sweep_cache=None, only=None):
        self.spec, self.root = spec, Path(root)
        # The closed loop studied (the taxi unless the run file names another).
        self.application = load_application(spec.application)
        # A slice: the per-environment stages for these environments alone (None: all).
        self.only = None if only is None else set(only)
        # Sweeps are keyed by content, so runs may share one cache folder; it may be an
        # fsspec URL (kept a string: `cache_location`), read and written here alone.
        self.sweep_cache = cache_location(sweep_cache) if sweep_cache else self.root / "sweeps"
        self.executor = executor or InlineExecutor()
        self.progress, self.log = progress, log
        self.outputs, self.records = {}, {}
        text = dump_run_spec(spec).encode()
        spec_path = self.root / "run.yaml"
        if not (spec_path.is_file() and spec_path.read_bytes() == text):
            if spec_path.is_file():
                _check_same_run(spec_path, spec.name)
                log(f"{spec_path}: the run file differs from the last one run here; "
                    f"the stages whose inputs changed run again")
            self._writable("to record its run file")
            atomic_write_bytes(spec_path, text)

    def _writable(self, why):
        """Raise a ValueError naming the run directory when it cannot be written."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            blocked = isinstance(e, (FileExistsError, NotADirectoryError))
            raise ValueError(f"cannot create the run directory {self.root}: {e.strerror}"
                             + (" (a file stands where a folder is needed)" if blocked
                                else "")) from None
        if not os.access(self.root, os.W_OK | os.X_OK):
            raise ValueError(f"the run directory {self.root} is not writable, and the run "
                             f"needs it {why}")

    def bar(self):
        """A tqdm-style ``progress(iterable, **kw)`` for training loops, or None when quiet."""
        if not self.progress:
            return None
        from tqdm import tqdm
        return lambda it, **kw: tqdm(it, **kw)

    def path(self, relative) -> Path:
        return self.root / relative

    def rel(self, path) -> str:
        return str(Path(path).resolve().relative_to(self.root.resolve()))

    def output_files(self, outputs) -> dict:
        """``{relative path: {"bytes", "hash"}}`` of every file the ``outputs`` name
        (string values that are paths inside the run directory; folders below the top
        level expanded). A bare top-level folder name is the run's own layout, and as a
        value it is a word such as the label source ``"brt"``: expanded, it made a
        record depend on every BRT of the run."""
        found, root = {}, self.root.resolve()

        def visit(value):
            if isinstance(value, dict):
                for v in value.values():
                    visit(v)
            elif isinstance(value, (list, tuple)):
                for v in value:
                    visit(v)
            elif isinstance(value, str) and value and "\n" not in value and len(value) < 1024:
                path = self.root / value
                try:
                    if not path.exists() or not path.resolve().is_relative_to(root):
                        return
                    if path.is_dir() and len(Path(value).parts) < 2:
                        return
                except OSError:
                    return
                # a hidden file in a folder is another writer's temporary one (a killed
                # write leaves it): not an output, as a run's URL copy never puts one
                for f in ([path] if path.is_file() else sorted(
                        p for p in path.rglob("*")
                        if p.is_file() and not p.name.startswith("."))):
                    found[self.rel(f)] = {"bytes": f.stat().st_size, "hash": file_hash(f)}

        visit(outputs)
        return found

    def _read_record(self, record_path):
        """The record, or ``(None, why it cannot be used)``."""
        if not record_path.exists():
            return None, "no record"
        try:
            record = json.loads(record_path.read_text())
        except (OSError, ValueError) as e:
            return None, f"record {record_path} is corrupt ({type(e).__name__})"
        needed = {"key": str, "seconds": (int, float), "outputs": (dict, list),
                  "files": dict, "format": int}
        if not isinstance(record, dict) or any(not isinstance(record.get(k), t)
                                               for k, t in needed.items()):
            return None, f"record {record_path} is corrupt (not a stage record)"
        if record["format"] > RECORD_FORMAT:   # (its check may be a newer one's too)
            raise ValueError(f"{record_path} was written by a newer reachwatch (record format "
                             f"{record['format']}, this one reads {RECORD_FORMAT}): run it "
                             f"with that version, or give another --out (or delete the "
                             f"record to run its stage again here)")
        if record["format"] != RECORD_FORMAT:
            return None, f"record {record_path} has format {record['format']}"
        # A record written before records carried a check has none: it gets one when reused.
        if "check" in record and record["check"] != record_check(record):
            return None, (f"record {record_path} is corrupt (edited after its stage wrote it: "
                          f"its check does not match)")
        return record, None

    def _check_files(self, record):
        """Why the files a record names no longer match it, or None."""
        why = self._stale_files(record, first=True)
        return next(iter(why.values())) if why else None

    def _stale_files(self, record, first=False) -> dict:
        """``{relative path: why}`` of the files ``record`` names that are missing or
        differ from the recorded size and hash (only the first with ``first``)."""
        stale = {}
        for relative, want in record["files"].items():
            path = self.root / relative
            if not path.is_file():
                stale[relative] = f"its output {relative} is missing"
            elif path.stat().st_size != want.get("bytes"):
                stale[relative] = f"its output {relative} changed size"
            elif file_hash(path) != want.get("hash"):
                stale[relative] = f"its output {relative} changed content"
            if stale and first:
                break
        return stale

    def _remove_stale(self, record):
        """Delete the files ``record`` names whose content no longer is what its stage
        wrote: a stage that reuses a file found at its output path (a checkpoint named by
        its config, a content-addressed dataset) then builds it again instead of adopting
        the edited one. A file that another stage of this run recorded as it is now (its
        own output, which this record names too) is kept."""
        for relative, why in self._stale_files(record).items():
            path = self.root / relative
            if not (path.is_file() and path.resolve().is_relative_to(self.root.resolve())):
                continue
            now = file_hash(path)
            if not any(other["files"].get(relative, {}).get("hash") == now
                       for name, other in self.records.items() if name != record.get("stage")):
                self.log(f"removing {relative}: {why.removeprefix(f'its output {relative} ')} "
                         f"since its record")
                path.unlink(missing_ok=True)

    def content_key(self, name) -> str:
        """A digest of stage ``name``'s record: its key and the size and hash of every
        file its outputs name. What a downstream stage's key uses, so that an upstream
        stage that ran again (its own key unchanged) and wrote other bytes runs what
        reads them again. Not its outputs' values, which hold wall times: identical
        runs keep identical keys (the values are covered by the record's check)."""
        record = self.records[name]
        return digest(record["key"], record["files"])

    def recorded(self, name, key):
        """The record of stage ``name`` when it has ``key`` and every file it names is
        as recorded (what `stage` would reuse), else None; runs nothing."""
        record, _ = self._read_record(self.root / "stages" / f"{name}.json")
        if record is None or record["key"] != key or self._check_files(record) is not None:
            return None
        return record

    def stage(self, name, key, fn) -> dict:
        """``fn()``'s outputs, or the recorded ones when the key is unchanged, the record
        matches its check (`record_check`) and every file it names is there with the
        recorded size and hash. Before ``fn`` runs, the files the old record names that
        were changed since are deleted (`_remove_stale`)."""
        record_path = self.root / "stages" / f"{name}.json"
        record, why = self._read_record(record_path)
        if record is not None:
            why = ("its inputs changed" if record["key"] != key else self._check_files(record))
        if why is None:
            self.log(f"[{name}] up to date (key {key}, took {record['seconds']:.0f} s), skipped")
            if "check" not in record and os.access(record_path.parent, os.W_OK | os.X_OK):
                record["check"] = record_check(record)
                atomic_write_bytes(record_path, json.dumps(record, indent=1).encode())
        else:
            self.log(f"[{name}] running: {why} (key {key})")
            self._writable(f"to run stage {name}")
            if record is not None:
                self._remove_stale(record)
            started = time.time()
            outputs = json.loads(json.dumps(fn(), default=_plain))
            record = {"format": RECORD_FORMAT, "stage": name, "key": key,
                      "seconds": round(time.time() - started, 1),
                      "finished": datetime.datetime.now().isoformat(timespec="seconds"),
                      "outputs": outputs, "files": self.output_files(outputs)}
            record["check"] = record_check(record)
            atomic_write_bytes(record_path, json.dumps(record, indent=1).encode())
            self.log(f"[{name}] done in {record['seconds']:.0f} s")
        self.outputs[name], self.records[name] = record["outputs"], record
        return record["outputs"]

    # --- shared helpers ----------------------------------------------------------
    def scenario_for(self, env, checkpoint=None):
        scenario = copy.deepcopy(self.spec.scenario)
        scenario.environment = env
        if checkpoint is not None:
            scenario.controller.checkpoint = str(checkpoint)
        return scenario

    def grid_for(self, env) -> Grid:
        """The application's box (where states are labelled and checked; the taxi's:
        the paper's) at the run's shape."""
        return self.application.grid(self.scenario_for(env), tuple(self.spec.grid))

    def solved_grid_for(self, env) -> Grid:
        """The box swept and solved over: the application's, widened by the run file
        (the taxi's: |theta| up to ``solved_theta_deg`` and py up to ``solved_py_max``)."""
        return self.application.grid(self.scenario_for(env), tuple(self.spec.grid),
                                     theta_deg=float(self.spec.solved_theta_deg),
                                     py_max=float(self.spec.solved_py_max))

    def environments(self):
        """Every environment whose BRT the run needs (train, test, guard, incremental),
        less those a slice leaves out."""
        return self.selected(self.spec.all_environments())

    def selected(self, envs):
        """``envs`` less those a slice (``only``) leaves out."""
        return [e for e in envs if self.only is None or e.name in self.only]

    def value_function(self, name) -> ValueFunction:
        return ValueFunction.load(self.path(self.outputs["solve"][name]["value"]))

    def steering_table(self, env):
        """``(grid, steering)`` the BRT of ``env`` was solved from: the refined table
        the solve stage saved, or the (cached) sweep."""
        saved = self.outputs["solve"][env.name].get("table")
        if saved:
            with np.load(self.path(saved)) as data:
                steering, lo, hi = data["steering"], data["lo"], data["hi"]
            axes = self.application.axes
            return Grid(lo=lo, hi=hi, shape=steering.shape[:len(axes)], names=axes), steering
        scenario, grid = self.scenario_for(env), self.solved_grid_for(env)
        table = self.application.sweep(scenario, grid, cache_dir=self.sweep_cache,
                                       executor=self.executor, progress=False)
        return grid, table[self.application.probe(scenario).control_port]

    def datasets(self, envs):
        return [load_dataset(self.path(self.outputs["dataset"]["folders"][e.name])) for e in envs]
