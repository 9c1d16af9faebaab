"""The run (`Run`) and the learning stages of ``reachwatch run``: train -> evaluate
(sweep and solve are in `brt_stages`, the dataset in `dataset_stages`). Each reads the records of the stages before it and returns JSON-able
outputs (paths relative to the run directory); `Run.stage` skips a stage whose key
(a digest of its inputs) matches its record. The heavy work inside a stage is
itself chunked and cached by content, so a killed stage resumes where it stopped."""

import copy
import dataclasses as dc
import datetime
import hashlib
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import file_hash, load_detector
from reachwatch.reach import Grid, InlineExecutor, ValueFunction
from reachwatch.reach.application import load_application
from reachwatch.reach.fingerprint import modules_source_digest
from reachwatch.systems.checks import device_kind, short
from reachwatch.systems.files import atomic_write_bytes, cache_location
from reachwatch.training.baselines import estimate_error_of
from reachwatch.training.dataset import load_dataset
from reachwatch.training.labels import SOURCE_BRT, SOURCE_PATH, label_source, labels_name
from reachwatch.training.detector_train import (THRESHOLD_CHOICE, held_out_operating_threshold,
                                                operating_threshold, train_detector)
from reachwatch.training.evaluation import (NOT_FAILED, READ_ALONG, UNIFORM_STARTS, Detector,
                                            csv_table, evaluate_environment, markdown_table,
                                            worst_mistakes)
from reachwatch.training.figures import (plot_error_vs_margin, plot_examples, plot_overlay,
                                         plot_roc)
from reachwatch.training.metrics import best_threshold

from .spec import RunSpec, digest, dump_run_spec


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
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return                                  # not a run file we can read: rewritten
    other = recorded.get("name") if isinstance(recorded, dict) else None
    if isinstance(other, str) and other != name:
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
            raise ValueError(f"cannot create the run directory {self.root}: {e.strerror}") from None
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
                for f in ([path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())):
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


def controller_name(scenario) -> str:
    """The controller under test as tables name it: TaxiNet, or the user's factory
    (its function's name)."""
    factory = scenario.controller.factory
    return factory.rpartition(":")[2] if factory else "TaxiNet"


def estimate_error(run: Run):
    """The prediction-error baseline of ``run``'s controller (`baselines.EstimateError`),
    or None when its application does not say what the controller estimates."""
    return estimate_error_of(run.application, controller_name(run.spec.scenario))


def detector_weights(config) -> dict:
    """What a detector's trained weights depend on, which names its checkpoint file: its
    training settings, not how its threshold is chosen (that changes neither the weights
    nor the file), and the kind of device that trains it ("" resolved: CUDA when
    present; another kind trains other weights)."""
    weights = {k: v for k, v in dc.asdict(config).items() if k not in THRESHOLD_CHOICE}
    weights["device"] = device_kind(config.device)
    return weights


def stage_train(run: Run) -> dict:
    """The detector on BRT labels, and the same detector on prediction-error labels
    (baseline a), each with its operating threshold."""
    spec, config = run.spec, run.spec.detector
    data = run.datasets(spec.training_environments())
    progress = run.bar()
    weights = detector_weights(config)
    folders = run.outputs["dataset"]["folders"]
    tag = digest(weights, {e.name: folders[e.name] for e in spec.training_environments()})
    brt_path = run.path(f"detectors/detector_brt_{tag}.pt")
    seconds = None
    if not brt_path.exists():
        seconds = train_detector(data, config, brt_path, progress=progress)["train_seconds"]
    model, _, meta = load_detector(brt_path)
    out = {"detector": run.rel(brt_path), "validation": meta.get("validation", {}),
           "train_seconds": seconds}

    held_out = []       # in the outputs, so that the record holds their hashes too

    def checkpoint_for_prefix(prefix, *labelling):
        def checkpoint_for(left_out):
            kept = {e.name: folders[e.name] for e in spec.training_environments()
                    if e.name not in left_out}
            key = digest(weights, kept, *labelling)
            held_out.append(run.rel(run.path(f"detectors/{prefix}_heldout_{key}.pt")))
            return run.path(held_out[-1])
        return checkpoint_for

    if config.threshold_folds:
        chosen = held_out_operating_threshold(data, config, checkpoint_for_prefix("detector_brt"),
                                              progress=progress)
        out["threshold"] = chosen.threshold
        out["held_out_threshold"] = dc.asdict(chosen)
        out["held_out_checkpoints"] = held_out
    else:
        out["threshold"] = float(operating_threshold(model, data, config))
    error = estimate_error(run)
    if error is None or not all(error.applies(d.states, d.estimates) for d in data):
        return out          # a controller whose estimate the application does not know
    errors = np.concatenate([error(d.states, d.estimates) for d in data])
    error_threshold, _ = best_threshold(np.concatenate([d.labels for d in data]), errors)
    labels = [error.labels(d, error_threshold) for d in data]
    # named by its labels too: another scale, error threshold or labelling code labels
    # other states
    labelling = [list(error.scale), float(error_threshold),
                 modules_source_digest("reachwatch.training.baselines")]
    labelling_key = digest(*labelling)[:8]
    error_path = run.path(f"detectors/detector_prediction_error_{tag}_{labelling_key}.pt")
    if not error_path.exists():
        train_detector(data, config, error_path, progress=progress, labels=labels)
    out.update({"prediction_error_detector": run.rel(error_path),
                "prediction_error_threshold": float(error_threshold)})
    if config.threshold_folds:          # the baseline's threshold is chosen the same way
        chosen = held_out_operating_threshold(
            data, config, checkpoint_for_prefix("detector_prediction_error", *labelling),
            labels=labels, progress=progress)
        out["prediction_error_detector_threshold"] = chosen.threshold
        out["prediction_error_held_out_threshold"] = dc.asdict(chosen)
    else:
        model, _, _ = load_detector(error_path)
        out["prediction_error_detector_threshold"] = operating_threshold(model, data, config,
                                                                         labels)
    return out


def stage_evaluate(run: Run) -> dict:
    """Table 2 on the held-out environments, error-vs-margin and overlay figures."""
    spec, trained = run.spec, run.outputs["train"]
    detectors = []
    source = labels_name(label_source(spec.dataset.labels.source).table_name,
                         spec.dataset.labels.paths)
    candidates = [(f"detector ({source} labels)", trained["detector"], trained["threshold"])]
    if "prediction_error_detector" in trained:
        candidates.append((f"detector (prediction-error labels, error > "
                           f"{trained['prediction_error_threshold']:.3f})",
                           trained["prediction_error_detector"],
                           trained["prediction_error_detector_threshold"]))
    for name, path, threshold in candidates:
        model, config, _ = load_detector(run.path(path))
        detectors.append(Detector(name, model, config, threshold))
    rows, figures = [], {}
    held_out = spec.held_out_environments()
    # Each row's accuracy at an oracle threshold for the recall the figures are judged at.
    ceiling_recall = spec.detector.judged_recall
    error = estimate_error(run)
    for env, d in zip(held_out, run.datasets(held_out)):
        # States that have not failed yet: for the taxi, the aircraft still on the runway.
        inside = ~run.application.failed(run.scenario_for(env), d.states)
        subsets = {NOT_FAILED: inside}
        if np.any(d.sources == SOURCE_PATH):      # read-along states: each kind alone too
            subsets[UNIFORM_STARTS] = d.sources != SOURCE_PATH
            subsets[READ_ALONG] = d.sources == SOURCE_PATH
        env_rows, scores = evaluate_environment(d, detectors, device=spec.detector.device,
                                                subsets=subsets, target_recall=ceiling_recall,
                                                estimate_error=error)
        rows += env_rows
        if np.any(d.sources != SOURCE_BRT):       # also scored against the BRT's verdicts
            as_brt = dc.replace(d, labels=d.brt_labels,
                                manifest={**d.manifest, "labels": {"source": "brt"}})
            rows += evaluate_environment(as_brt, detectors, device=spec.detector.device,
                                         subsets=subsets, target_recall=ceiling_recall,
                                         estimate_error=error)[0]
        predictions = {r["method"]: scores[r["method"]] >= r["threshold"]
                       for r in env_rows if r["states"] == "all"}
        margin = plot_error_vs_margin({m: (d.values, d.labels, p) for m, p in predictions.items()},
                                      run.path(f"figures/error_vs_margin_{env.name}.png"))
        overlay = plot_overlay(run.application, run.scenario_for(env), run.value_function(env.name),
                               d.states, d.labels, predictions[detectors[0].name],
                               at=spec.slice_py, path=run.path(f"figures/overlay_{env.name}.png"),
                               title=f"{env.name}: {detectors[0].name}")
        thresholds = {r["method"]: r["threshold"] for r in env_rows if r["states"] == "all"}
        roc = plot_roc({m: (d.labels, scores[m], t) for m, t in thresholds.items()},
                       run.path(f"figures/roc_{env.name}.png"),
                       title=f"{env.name}: ROC over all states (dots: operating points)")
        main = detectors[0]
        misses, alarms = worst_mistakes(d.labels, scores[main.name], main.threshold, 4)
        caption = lambda kind, i: (f"{kind}: score {scores[main.name][i]:.3f}, "  # noqa: E731
                                   f"V {d.values[i]:+.2f}\nstate "
                                   f"{np.array2string(d.states[i], precision=2)}")
        examples = plot_examples([d.images[i] for i in np.r_[misses, alarms]],
                                 [caption("missed", i) for i in misses] +
                                 [caption("false alarm", i) for i in alarms],
                                 run.path(f"figures/mistakes_{env.name}.png"),
                                 title=f"{env.name}: {main.name}, its most confident misses "
                                       f"and false alarms")
        figures[env.name] = {"error_vs_margin": run.rel(margin), "overlay": run.rel(overlay),
                             "roc": run.rel(roc), "mistakes": run.rel(examples),
                             "mistake_counts": {"misses": len(misses), "false_alarms": len(alarms)}}
    atomic_write_bytes(run.path("table2.md"), markdown_table(rows).encode())
    atomic_write_bytes(run.path("table2.csv"), csv_table(rows).encode())
    return {"rows": rows, "figures": figures, "table_md": "table2.md", "table_csv": "table2.csv"}
