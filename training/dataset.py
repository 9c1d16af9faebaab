"""Labelled image datasets: uniform states of the grid box, their wing-camera images,
the controller's estimates (when it declares an ``estimate`` output) and an
ensemble's, V(x), and a label per state from the source `LabelSpec` names
(`training.labels`): the BRT
(``V <= 0``), the real closed loop run from the state, a hybrid of both, or the
real loop's runs from uniform states and the states they pass through.

On disk, one folder per (environment, camera, BRT, sampling, labels, image size,
controllers): ``manifest.json`` plus ``.npy`` arrays (``images.npy`` is a uint8
memmap ``(N, H, W, 3)``; ``states.npy`` [px m, py m, theta rad]; ``values.npy`` m;
``labels.npy`` uint8, 1 = anomalous; ``sources.npy`` uint8, where each label came from
(`SOURCE_BRT`, `SOURCE_ROLLOUT`, `SOURCE_PATH`); with read-along states ``runs.npy``
int64, the real run each sample lies on (`NO_RUN` for one drawn on its own: samples
of one run are near-copies, and `train_detector`'s validation split keeps them
together); ``estimates.npy`` ``(N, k)``, the controller's
``estimate`` output (TaxiNet: [px_hat m, theta_hat deg]; k = 0 when it has none);
``ensemble.npy`` ``(N, K, 2)``). The real-loop runs that labelled it are cached
beside the datasets, in ``ROOT/rollouts/`` (`runs_cache`), keyed by content: a dataset
whose label settings change renders again only the runs that differ.
Filled chunk by chunk; the manifest records finished chunks and is replaced
atomically, so an interrupted build resumes. It also records the hash of every array
(the labels' when begun, the rest when finished): a folder whose arrays changed since
is refused, or built again (`build_dataset`'s ``rebuild``), never reused."""

import dataclasses as dc
import functools
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from reachwatch.diagrams import file_hash, make_controller
from reachwatch.reach.application import ApplicationRef
from reachwatch.reach.chunk_files import split
from reachwatch.reach.chunks import run_chunks
from reachwatch.reach.executors import InlineExecutor
from reachwatch.reach.fingerprint import fingerprint, modules_source_digest
from reachwatch.systems import DetectorConfig
from reachwatch.systems.bounds import bounded, bounded_as, check_bounds, seed_field

from .dataset_files import (FILLED, LABELLED, ImageStore, array_hashes, changed_arrays, clear,
                            finished, open_array, read_manifest, reserved_memmap, save_array,
                            write_manifest)
from .dataset_images import ImageSource, ImageTools, estimator, render_chunk

from .labels import (FALLBACK_FIELDS, NO_RUN, SOURCE_BRT, SOURCE_PATH, SOURCE_ROLLOUT,
                     TRAJECTORY_FIELDS, LabelInputs, LabelSpec, label_samples, read_along)

#: 4: the path starts have a stream of their own (`PATHS_STREAM`).
FORMAT = "reachwatch.dataset/4"
#: The random streams of a dataset's uniform states and of its path starts, after its
#: seed: ``[seed, 0, 3]`` and ``[seed, 0, 2]``. A random family draws its environment
#: ``i`` from ``[seed, i]`` and the monitor study the starts of environment ``i`` from
#: ``[seed, i, 1]``, so with equal seeds these streams are none of theirs. Until format
#: 4 they were ``seed`` (numpy's ``[seed, 0]``: environment 0's) and ``[seed, 1]``
#: (environment 1's).
STATES_STREAM, PATHS_STREAM = (0, 3), (0, 2)
#: The modules whose code draws a dataset's states, labels them and stores its images
#: (the loop's own code is in its controller's fingerprint): part of a dataset folder's
#: key (`dataset_folder`) and of the run's dataset stage key, so that an edit to them
#: builds the datasets again.
DATASET_CODE = ("reachwatch.training.dataset", "reachwatch.training.dataset_files",
                "reachwatch.training.dataset_images", "reachwatch.training.labels")
_log = logging.getLogger("reachwatch")


@dc.dataclass
class DatasetSpec:
    """How many states, which seed, how they are labelled, and the stored image size
    (the detector's input)."""
    samples: int = bounded(2000, 10, 10_000_000, whole=True)
    seed: int = seed_field()
    height: int = bounded_as(96, DetectorConfig, "height", note="= detector.detector.height")
    width: int = bounded_as(160, DetectorConfig, "width", note="= detector.detector.width")
    chunk_size: int = bounded(256, 1, 100_000, whole=True)
    labels: LabelSpec = dc.field(default_factory=LabelSpec)

    def key(self) -> dict:
        """What keys a dataset of this spec: every field, the labels' by `LabelSpec.key`."""
        return {**dc.asdict(self), "labels": self.labels.key()}

    def validate(self, where="dataset"):
        check_bounds(self, f"{where}.")
        self.labels.validate(f"{where}.labels")
        return self


def _value_hash(value_function) -> str:
    return hashlib.sha256(np.ascontiguousarray(value_function.values, np.float32)
                          .tobytes()).hexdigest()[:16]


#: The camera placement (every field but the image size) and lighting that datasets were
#: rendered with when their key held the camera's size alone: `camera_view` keys only
#: what differs from it, so those datasets keep their folders.
KEYED_VIEW = {"fov_x_deg": 80.0, "right": 2.17, "up": 0.42, "forward": 0.0,
              "reference_height": 1.5, "yaw_out_deg": 5.0, "pitch_down_deg": 5.0,
              "near": 0.5, "far": 3000.0, "shadows": False}


def camera_view(scenario) -> dict:
    """What a dataset's images depend on in ``scenario``'s camera besides its size (its
    placement, field of view, clipping) and its shadows, where they differ from
    `KEYED_VIEW`."""
    view = {**dc.asdict(scenario.camera), "shadows": bool(scenario.shadows)}
    return {name: value for name, value in view.items()
            if name not in ("height", "width")
            and (name not in KEYED_VIEW or KEYED_VIEW[name] != value)}


def dataset_folder(root, scenario, value_function, spec: DatasetSpec, ensemble=(),
                   box=None, *, application) -> Path:
    """The content-addressed folder of a dataset under ``root`` (``application``: the
    closed loop, a `reachwatch.reach.application.Application`)."""
    scenario = application.resolved(scenario)
    spec_parts = spec.key()
    if not spec.labels.reads_along:
        for name in TRAJECTORY_FIELDS:
            spec_parts["labels"].pop(name)
    if not spec.labels.falls_back_to_trajectory:
        for name in FALLBACK_FIELDS:
            spec_parts["labels"].pop(name)
    parts = {"format": FORMAT, "code": modules_source_digest(*DATASET_CODE),
             "env": dc.asdict(scenario.environment),
             "brt": _value_hash(value_function), "spec": spec_parts,
             "camera": [scenario.camera.height, scenario.camera.width],
             "controller": fingerprint(scenario.controller),
             "ensemble": [file_hash(p) for p in ensemble]}
    if camera_view(scenario):      # a camera placed otherwise renders other images
        parts["view"] = camera_view(scenario)
    if box is not None:
        parts["box"] = np.asarray(box, float).tolist()
    parts["application"] = application.key()
    if spec.labels.reads_along:
        parts["runs"] = 1       # runs.npy, which datasets of read-along states before it lacked
    if spec.labels.source != "brt" or spec.labels.paths:
        # real-loop labels run for the BRT's horizon over its grid: a longer horizon whose
        # converged values are the same bits labels otherwise (BRT labels read the values)
        parts["real_loop"] = {"horizon": float(value_function.horizon),
                              "grid": value_function.grid.key()}
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    return Path(root) / f"{scenario.environment.name}_{spec.samples}_{digest}"


def label_frames(label_info) -> int:
    """The frames the real loop rendered to label a dataset, from its manifest's
    ``labels`` record: the rollouts' (a hybrid's include its audit), the audit's where
    the hybrid fell back to trajectory labels, and the read-along paths'."""
    return (int(label_info.get("rollout_frames", 0)) + int(label_info.get("audit_frames", 0)) +
            int((label_info.get("paths") or {}).get("frames", 0)))


def label_summary(manifest) -> str:
    """One line on how a dataset (its ``manifest``) was labelled: the source, what the
    hybrid's audit decided and on how many runs, and what the labels cost in frames."""
    info, samples = manifest["labels"], manifest["samples"]
    audit = info.get("audit")
    text = info["source"]
    if audit:
        verdict = "trusted" if audit["map_trusted"] else "distrusted"
        text += f": map {verdict} after {audit['samples']} audit runs"
        text += (f", band {audit['band']:.2f} m" if audit["map_trusted"] else
                 f" ({audit['false_safe']} false-safe)")
    if info.get("labelled_by"):
        text += f", {info['labelled_by']} labels"
    frames = label_frames(info)
    return (f"{text}; {samples} labels, {frames} frames ({frames / samples:.1f} per label)"
            if samples else text)


def runs_cache(folder) -> Path:
    """Where the real-loop runs labelling the dataset in ``folder`` are cached: shared by
    every dataset under the same root (the cache is keyed by scenario and starts), so
    one built again with other label settings reuses the runs it has in common, the
    audit and the trajectory runs, instead of rendering them again."""
    return Path(folder).parent / "rollouts"


def _real_loop(application, scenario, value_function, folder: Path, progress, executor):
    """``run_loop`` for `label_samples`: the application's real closed loop from
    ``states``, cached in `runs_cache`, run on ``executor``."""
    def run_loop(states):
        outcome = application.real_outcomes(scenario, states, grid=value_function.grid,
                                duration=value_function.horizon, cache_dir=runs_cache(folder),
                                executor=executor, progress=progress)
        return outcome.failed, int(np.sum(outcome["ticks"]))
    return run_loop


def _real_paths(application, scenario, value_function, folder: Path, progress, executor,
                labels: LabelSpec):
    """``run_paths`` for `label_samples`: the application's ``real_paths``, cached
    in `runs_cache`, run on ``executor``."""
    def run_paths(starts):
        return application.real_paths(scenario, starts, grid=value_function.grid,
                          horizon=value_function.horizon, extend=labels.extend,
                          stride=labels.stride, cache_dir=runs_cache(folder),
                          executor=executor, progress=progress).fields
    return run_paths


def build_dataset(root, scenario, value_function, spec: DatasetSpec = DatasetSpec(), *,
                  application, ensemble=(), progress=True, box=None, rebuild=False,
                  executor=None) -> Path:
    """Render, estimate and label ``spec.samples`` uniform states of ``box`` (``(lo,
    hi)``, inside the value function's grid; default: the whole grid) in
    ``scenario``'s environment, and with ``trajectory`` labels the states their runs
    pass through (`trajectory_samples`); returns the dataset folder (reused or resumed when it
    already exists). A folder whose arrays are not the ones its manifest recorded
    (edited, truncated or missing since) is a ValueError naming the file, or with
    ``rebuild`` is built again from the start. ``application``: the closed loop (a
    `reachwatch.reach.application.Application`): its failure rule, start distribution,
    real loop and camera. ``executor``: where the image chunks
    (`dataset_images.render_chunk`) and the real loop's runs go (default: here, one
    after another); this process writes what comes back, so workers need no
    filesystem shared with it."""
    scenario = application.resolved(scenario)
    grid = value_function.grid
    if box is not None:
        lo, hi = (np.asarray(b, float) for b in box)
        if lo.shape != grid.lo.shape or hi.shape != grid.lo.shape or np.any(lo >= hi) \
                or not (grid.contains(lo[None]) & grid.contains(hi[None])).all():
            raise ValueError(f"the dataset box {lo.tolist()} .. {hi.tolist()} must be a "
                             f"non-empty box inside the BRT's grid {grid}")
    else:
        lo, hi = grid.lo, grid.hi
    folder = dataset_folder(root, scenario, value_function, spec, ensemble, box,
                            application=application)
    folder.mkdir(parents=True, exist_ok=True)
    manifest_path = folder / "manifest.json"
    inline = executor is None or isinstance(executor, InlineExecutor)
    tools = manifest = None     # the renderer is built only when there is work for it
    if manifest_path.exists():
        # Reused (or resumed) only when its arrays are the ones its manifest recorded:
        # else refused in one line, or with ``rebuild`` built again.
        try:
            manifest = read_manifest(folder)
            k, n = manifest["estimate_size"], manifest["samples"]
            for name in LABELLED[:4]:
                open_array(folder, name, (n,))
            arrays = {name: open_array(folder, name, shape, "r+") for name, shape in (
                ("images", (n, spec.height, spec.width, 3)), ("estimates", (n, k)),
                ("ensemble", (n, len(ensemble), 2)))}
            # (the filled arrays' hashes are those of the finished dataset)
            why = changed_arrays(folder, manifest,
                                  None if finished(manifest, spec) else LABELLED)
            if why:
                raise ValueError(f"{why}; delete {folder} to rebuild the dataset")
        except ValueError as e:
            if not rebuild:
                raise
            _log.warning(f"dataset {folder.name}: {str(e).split('; delete')[0]}; "
                         f"building it again")
            arrays = None
            clear(folder)
            manifest = None
    if manifest is None:
        rng = np.random.default_rng([spec.seed, *STATES_STREAM])
        states = lo + rng.uniform(size=(spec.samples, grid.ndim)) * (hi - lo)
        inside = lambda x: np.all((x >= lo) & (x <= hi), axis=1)       # noqa: E731
        real = (application, scenario, value_function, folder, progress, executor)
        states, values, labels, sources, label_info, runs = label_samples(LabelInputs(
            states, spec.labels, value_function.at,
            lambda x: ~application.failed(scenario, x), _real_loop(*real),
            _real_paths(*real, spec.labels), inside))
        n = len(states)
        if spec.labels.paths:
            out = _real_paths(*real, spec.labels)(application.starts(
                scenario, (lo, hi), spec.labels.paths, [spec.seed, *PATHS_STREAM]))
            along, anomalous, left_out, along_runs = read_along(out, inside)
            states = np.concatenate([states, along])
            values = np.concatenate([values, value_function.at(along)])
            labels = np.concatenate([labels, anomalous.astype(np.uint8)])
            sources = np.concatenate([sources, np.full(len(along), SOURCE_PATH, np.uint8)])
            runs = np.concatenate([runs, along_runs + (runs.max(initial=NO_RUN) + 1)])
            frames = int(np.sum(out["ticks"]))
            label_info["paths"] = {"runs": int(spec.labels.paths), "samples": int(len(along)),
                                   "left_out": left_out, "frames": frames,
                                   "frames_per_label": round(frames / max(1, len(along)), 2)}
            n = len(states)
        if inline:      # renders here: built once, for the estimate size and the images
            tools = ImageTools.build(application, scenario, ensemble)
        k = tools.estimate_size if tools else estimator(make_controller(scenario.controller))[1]
        save_array(folder / "states.npy", states)
        save_array(folder / "values.npy", values)
        save_array(folder / "labels.npy", labels)
        save_array(folder / "sources.npy", sources)
        if spec.labels.reads_along:
            save_array(folder / "runs.npy", np.asarray(runs, np.int64))
        arrays = {"images": reserved_memmap(folder / "images.npy", np.uint8,
                                            (n, spec.height, spec.width, 3)),
                  "estimates": reserved_memmap(folder / "estimates.npy", np.float64, (n, k)),
                  "ensemble": reserved_memmap(folder / "ensemble.npy", np.float64,
                                              (n, len(ensemble), 2))}
        manifest = {"format": FORMAT, "environment": scenario.environment.name,
                    "environment_spec": dc.asdict(scenario.environment),
                    "grid": grid.key(), "brt_hash": _value_hash(value_function),
                    "brt_fraction_of_samples": float(np.mean(values <= 0)),
                    "samples": n, "labels": label_info,
                    "label_counts": {"brt": int(np.sum(sources == SOURCE_BRT)),
                                     "rollout": int(np.sum(sources == SOURCE_ROLLOUT)),
                                     "path": int(np.sum(sources == SOURCE_PATH))},
                    "image_size": [spec.height, spec.width],
                    "camera_size": [scenario.camera.height, scenario.camera.width],
                    "spec": dc.asdict(spec), "controller": dc.asdict(scenario.controller),
                    "estimate_size": k,
                    # by name and content, as the folder's key has them: not by the
                    # path, which is the run directory's (a moved run is the same run)
                    "ensemble": [{"file": Path(p).name, "hash": file_hash(p)}
                                 for p in ensemble], "chunks_done": [],
                    "hashes": array_hashes(folder, LABELLED)}
        write_manifest(folder, manifest)
    states = np.load(folder / "states.npy")
    chunks = split(n, spec.chunk_size)
    store = ImageStore(folder, manifest, arrays, spec.chunk_size)
    if not all(store.valid(c) for c in chunks):
        if inline and tools is None:
            tools = ImageTools.build(application, scenario, ensemble)
        source = ImageSource(None if inline else ApplicationRef(application._loaded_as()),
                             scenario, tuple(str(p) for p in ensemble), spec.height,
                             spec.width, folder.name, tools)
        run_chunks(render_chunk, chunks, store,
                   args=lambda c: (source, states[c.start:c.stop]), executor=executor,
                   caller="build_dataset",
                   bar=functools.partial(tqdm, total=n, unit="image", disable=not progress,
                                         desc=f"dataset {scenario.environment.name}"))
    elif not set(LABELLED[:4] + FILLED) <= set(manifest.get("hashes", {})):
        # built before datasets recorded their arrays' hashes: recorded now, so that
        # a later edit is found
        manifest["hashes"] = {**array_hashes(folder, LABELLED + FILLED),
                              **manifest.get("hashes", {})}
        write_manifest(folder, manifest)
    return folder


@dc.dataclass
class LabelledData:
    """A dataset folder's arrays (images memory-mapped), or arrays made in memory
    (`from_arrays`, for a plant other than the taxi)."""
    folder: Path
    manifest: dict
    images: np.ndarray
    states: np.ndarray
    values: np.ndarray
    labels: np.ndarray
    estimates: np.ndarray
    ensemble: np.ndarray
    sources: np.ndarray = None      # SOURCE_BRT / SOURCE_ROLLOUT / SOURCE_PATH per label
    #: The real run each sample lies on (`NO_RUN` for a sample drawn on its own); None
    #: when no sample shares a run (datasets without read-along states)
    runs: np.ndarray = None

    @property
    def brt_labels(self) -> np.ndarray:
        """``V <= 0`` at every state, whatever the labels' source."""
        return (self.values <= 0).astype(np.uint8)

    @classmethod
    def from_arrays(cls, *, images, states, values, environment: str, camera_size):
        """Labelled data from any plant: detector-size RGB ``images`` ``(N, h, w, 3)``
        uint8, the ``states`` ``(N, n)`` they were rendered at and their BRT ``values``
        (label 1 iff ``V <= 0``); ``camera_size`` = (height, width) of the camera frames
        the online detector will see."""
        images, states, values = np.asarray(images), np.asarray(states), np.asarray(values)
        n = len(images)
        if images.dtype != np.uint8 or images.ndim != 4 or images.shape[3] != 3:
            raise ValueError(f"images must be uint8 (N, h, w, 3), got {images.dtype} {images.shape}")
        if len(states) != n or values.shape != (n,):
            raise ValueError(f"{n} images need {n} states and {n} values, got "
                             f"{len(states)} and {values.shape}")
        manifest = {"format": FORMAT, "environment": environment,
                    "camera_size": [int(v) for v in camera_size],
                    "image_size": list(images.shape[1:3]), "estimate_size": 0, "samples": n,
                    "labels": {"source": "brt"}}
        return cls(None, manifest, images, states, values, (values <= 0).astype(np.uint8),
                   np.zeros((n, 0)), np.zeros((n, 0, 2)), np.full(n, SOURCE_BRT, np.uint8))


def load_dataset(folder, verify: bool = False) -> LabelledData:
    """Open a finished dataset; raises ValueError if it is incomplete or foreign, or if
    an array differs from the one its manifest recorded (the images checked too with
    ``verify``)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{folder}: unknown dataset format {manifest.get('format')}")
    spec = DatasetSpec(**manifest["spec"])
    if not finished(manifest, spec):
        raise ValueError(f"{folder} is incomplete ({len(manifest['chunks_done'])} chunks); "
                         f"run build_dataset again to resume it")
    n = manifest["samples"]
    load = lambda name, shape, mode=None: open_array(folder, name, shape, mode)  # noqa: E731
    data = LabelledData(folder, manifest,
                        load("images", (n, spec.height, spec.width, 3), "r"),
                        load("states", (n,)), load("values", (n,)), load("labels", (n,)),
                        load("estimates", (n, manifest["estimate_size"])), load("ensemble", (n,)),
                        load("sources", (n,)),
                        load("runs", (n,)) if (folder / "runs.npy").exists() else None)
    # Every array but the images (the bulk) is checked against the manifest at every
    # load; the images too with ``verify`` (build_dataset checks all before reusing).
    why = changed_arrays(folder, manifest, None if verify else LABELLED + FILLED[1:])
    if why:
        raise ValueError(f"{why}; delete {folder} to rebuild the dataset")
    return data
