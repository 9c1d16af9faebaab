"""Labelled image datasets: uniform states of the grid box, their wing-camera images,
the controller's estimates (when it declares an ``estimate`` output) and an
ensemble's, V(x), and a label per state from the source `LabelSpec` names: the BRT
(``V <= 0``), the real closed loop run from the state, a hybrid of both, or the
real loop's runs from uniform states and the states they pass through.

On disk, one folder per (environment, BRT, sampling, labels, image size,
controllers): ``manifest.json`` plus ``.npy`` arrays (``images.npy`` is a uint8
memmap ``(N, H, W, 3)``; ``states.npy`` [px m, py m, theta rad]; ``values.npy`` m;
``labels.npy`` uint8, 1 = anomalous; ``sources.npy`` uint8, where each label came from
(`SOURCE_BRT`, `SOURCE_ROLLOUT`, `SOURCE_PATH`); ``estimates.npy`` ``(N, k)``, the controller's
``estimate`` output (TaxiNet: [px_hat m, theta_hat deg]; k = 0 when it has none);
``ensemble.npy`` ``(N, K, 2)``), and ``rollouts/``, the cached real-loop runs.
Filled chunk by chunk; the manifest records finished chunks and is replaced
atomically, so an interrupted build resumes."""

import dataclasses as dc
import hashlib
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from reachwatch.diagrams import ControllerProbe, StateRenderer, file_hash, load_taxinet, make_controller
from reachwatch.diagrams.controller import has_estimate
from reachwatch.reach.fingerprint import fingerprint
from reachwatch.taxi import resolved
from reachwatch.taxi.fidelity import real_outcomes, real_paths
from reachwatch.systems import TaxiNet, resize_for_detector
from reachwatch.systems.files import atomic_write_bytes

FORMAT = "reachwatch.dataset/3"
LABEL_SOURCES = ("brt", "rollout", "hybrid", "trajectory")
#: Values of ``sources.npy``: the label is the BRT's verdict, the real loop's outcome
#: from the sampled state, or the outcome read along a real run that passed through it.
SOURCE_BRT, SOURCE_ROLLOUT, SOURCE_PATH = 0, 1, 2
#: `LabelSpec` fields read only by the ``trajectory`` source or with ``paths`` (left out
#: of other datasets' keys, so adding them did not move existing datasets).
TRAJECTORY_FIELDS = ("extend", "stride", "paths")


def _whole(where, value, least):
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ValueError(f"{where} must be a whole number >= {least}, got {value!r}")


@dc.dataclass
class LabelSpec:
    """Where a dataset's labels come from (``source``):

    - ``brt``: ``V(x) <= 0`` of the solved BRT. Free, and as right as the map.
    - ``rollout``: the real closed loop (rendering every tick) run from every sampled
      on-runway state for the BRT's horizon, stopping at failure: exact for a
      deterministic loop, about one render per tick.
    - ``hybrid``: the BRT where the map is trusted, rollouts where it is not. The first
      ``audit`` on-runway samples are rolled out. If the BRT called any of them safe and
      the loop failed, the map is not trusted in this environment: every sample it
      calls safe (``V > 0``) is rolled out, and its unsafe verdicts within ``band`` m.
      Otherwise the audit's wrong unsafe verdicts say how far from the boundary the
      map's errors reach: the band is ``band`` m, or ``band_factor`` times the largest
      ``|V|`` of a wrong verdict if wider, and the on-runway samples within it on either
      side (``|V| < band``) are rolled out; a band wider than ``max_band`` m distrusts
      the map too. Unsafe verdicts further in are kept either way. (A false-safe
      verdict in the audit distrusts the map whatever its distance: on KMWH 21 h clear
      the audit's one lay 0.5 m from the boundary, the fresh starts' out to 3.9 m.)

    - ``trajectory``: ``rollout``, with each run lasting ``extend`` s past the horizon;
      every ``stride``-th state it passes through within its first ``extend`` s (and
      inside the dataset's box) is a sample too, labelled by the same run: whether the
      loop fails within the horizon from there. Exact like ``rollout`` for a loop whose
      state is all it remembers (the taxi's), at a fraction of the frames per label;
      the added samples are the states the loop visits, not uniform ones (their
      ``sources`` entry is `SOURCE_PATH`).

    ``paths`` (any source; 0 = none): beside the samples, the real loop from this many
    further uniform on-runway states (drawn after them) runs ``horizon + extend`` s, and
    the states each run passes through are added as ``trajectory`` adds them, the start
    included (`SOURCE_PATH`). With ``brt`` labels this puts true labels on the states the
    loop visits beside the map's labels on uniform ones.

    ``max_rollouts`` (0 = no cap) bounds the rollouts per environment: a dataset that
    would need more keeps only its first samples, as many as the cap allows (they are
    still uniform), and its manifest says how many it kept."""
    source: str = "brt"
    audit: int = 50
    band: float = 2.0
    band_factor: float = 2.0
    max_band: float = 6.0
    max_rollouts: int = 0
    extend: float = 8.0
    stride: int = 8
    paths: int = 0

    def validate(self, where="dataset.labels"):
        if self.source not in LABEL_SOURCES:
            raise ValueError(f"{where}.source must be one of {LABEL_SOURCES}, got '{self.source}'")
        _whole(f"{where}.audit", self.audit, 0)
        _whole(f"{where}.max_rollouts", self.max_rollouts, 0)
        _whole(f"{where}.stride", self.stride, 1)
        _whole(f"{where}.paths", self.paths, 0)
        for name in ("band", "band_factor", "max_band", "extend"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not np.isfinite(value) or value < 0:
                raise ValueError(f"{where}.{name} must be a finite number >= 0, got {value!r}")
        if self.max_band < self.band:
            raise ValueError(f"{where}.max_band ({self.max_band} m) must be at least band "
                             f"({self.band} m)")
        return self


@dc.dataclass
class DatasetSpec:
    """How many states, which seed, how they are labelled, and the stored image size
    (the detector's input)."""
    samples: int = 2000
    seed: int = 0
    height: int = 96
    width: int = 160
    chunk_size: int = 256
    labels: LabelSpec = dc.field(default_factory=LabelSpec)

    def validate(self, where="dataset"):
        for name, least in (("samples", 10), ("height", 16), ("width", 16), ("chunk_size", 1)):
            _whole(f"{where}.{name}", getattr(self, name), least)
        self.labels.validate(f"{where}.labels")
        return self


def _value_hash(value_function) -> str:
    return hashlib.sha256(np.ascontiguousarray(value_function.values, np.float32)
                          .tobytes()).hexdigest()[:16]


def dataset_folder(root, scenario, value_function, spec: DatasetSpec, ensemble=(),
                   box=None) -> Path:
    """The content-addressed folder of a dataset under ``root``."""
    scenario = resolved(scenario)
    spec_parts = dc.asdict(spec)
    if spec.labels.source != "trajectory" and not spec.labels.paths:
        for name in TRAJECTORY_FIELDS:
            spec_parts["labels"].pop(name)
    parts = {"format": FORMAT, "env": dc.asdict(scenario.environment),
             "brt": _value_hash(value_function), "spec": spec_parts,
             "camera": [scenario.camera.height, scenario.camera.width],
             "controller": fingerprint(scenario.controller),
             "ensemble": [file_hash(p) for p in ensemble]}
    if box is not None:
        parts["box"] = np.asarray(box, float).tolist()
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    return Path(root) / f"{scenario.environment.name}_{spec.samples}_{digest}"


def _open_array(folder: Path, name: str, rows_shape: tuple, mmap_mode=None) -> np.ndarray:
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


def _read_manifest(folder: Path) -> dict:
    try:
        return json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{folder} is not a readable reachwatch dataset ({type(e).__name__}: "
                         f"{e}); delete it to rebuild the dataset") from None


def _write_manifest(folder, manifest):
    atomic_write_bytes(folder / "manifest.json", json.dumps(manifest, indent=1).encode())


def _estimator(controller):
    """A function ``(N, H, W, 3) images -> (N, k)`` estimates of ``controller`` (one batch
    when it offers ``estimate(images)``, as TaxiNet's does; else image by image through
    its ``estimate`` port), and k."""
    if not has_estimate(controller):
        return (lambda images: np.zeros((len(images), 0))), 0
    size = controller.GetOutputPort("estimate").size()
    if callable(getattr(controller, "estimate", None)):
        return controller.estimate, size
    probe = ControllerProbe(controller)
    return (lambda images: np.stack([probe.outputs(image)[1] for image in images])), size


def audited_band(values, failed, *, band: float, band_factor: float, max_band: float):
    """``(band m, map trusted, largest error m)`` from an audit: the real outcomes
    ``failed`` of states with BRT values ``values``. The largest error is the largest
    ``|V|`` of a wrong verdict (0 when none); the band is ``band``, widened to
    ``band_factor`` times that error. The map is trusted when the audit found no
    false-safe verdict and the band is at most ``max_band``: a false-safe verdict in a
    small audit says little about how far out the others lie (on KMWH 21 h clear the
    audit's one sat at V = 0.5 m and 200 fresh starts had them out to 3.9 m)."""
    values, failed = np.asarray(values, float), np.asarray(failed, bool)
    wrong = (values <= 0) != failed
    largest = float(np.abs(values[wrong]).max()) if wrong.any() else 0.0
    widened = max(float(band), band_factor * largest)
    false_safe = bool(np.any(failed & (values > 0)))
    return widened, widened <= max_band and not false_safe, largest


def hybrid_rolls_out(values, band: float, map_trusted: bool) -> np.ndarray:
    """Where the ``hybrid`` source labels by the real loop: the states within ``band``
    of the BRT's boundary on either side (``|V| < band``), and every state the BRT calls
    safe (``V > 0``) when the map is not trusted. Callers leave out states already off
    the runway (failures by definition)."""
    values = np.asarray(values, float)
    return (np.abs(values) < band) | ((values > 0) & (not map_trusted))


def assign_labels(values, on_runway, labels: LabelSpec, run_loop):
    """Labels and their sources for states with BRT values ``values`` under
    ``labels.source``; ``on_runway`` marks the states where the loop has not failed
    yet (the audit's candidates) and ``run_loop(index) -> (failed, frames)`` runs the
    real loop from the states at ``index`` (called at most twice: the audit, then the
    rest). Returns ``(n kept, labels, sources, info)``."""
    values, on_runway = np.asarray(values, float), np.asarray(on_runway, bool)
    n = len(values)
    brt = (values <= 0).astype(np.uint8)
    info = {"source": labels.source}
    if labels.source == "brt":
        return n, brt, np.full(n, SOURCE_BRT, np.uint8), info
    failed, frames = {}, 0

    def run(index):
        nonlocal frames
        index = np.array([i for i in index if i not in failed], int)
        if len(index):
            outcome, used = run_loop(index)
            failed.update(zip(index.tolist(), np.asarray(outcome, bool).tolist()))
            frames += int(used)

    if labels.source == "rollout":
        roll = np.arange(n)
    else:
        audit = np.flatnonzero(on_runway)[:labels.audit]
        run(audit)
        audit_failed = np.array([failed[i] for i in audit.tolist()], bool)
        false_safe = int(np.sum(audit_failed & (values[audit] > 0)))
        band, trusted, largest = audited_band(values[audit], audit_failed, band=labels.band,
                                              band_factor=labels.band_factor,
                                              max_band=labels.max_band)
        band = band if trusted else labels.band
        info["audit"] = {"samples": int(len(audit)), "real_failures": int(audit_failed.sum()),
                         "false_safe": false_safe, "largest_error_m": largest,
                         "map_trusted": trusted, "band": band}
        uncertain = hybrid_rolls_out(values, band, trusted) & on_runway
        roll = np.union1d(audit, np.flatnonzero(uncertain)).astype(int)
    if labels.max_rollouts and len(roll) > labels.max_rollouts:
        n = int(roll[labels.max_rollouts])     # the first sample whose rollout is over the cap
        roll = roll[:labels.max_rollouts]
    run(roll)
    out, sources = brt[:n].copy(), np.full(n, SOURCE_BRT, np.uint8)
    for i in roll.tolist():
        out[i], sources[i] = failed[i], SOURCE_ROLLOUT
    info.update(samples_kept=n, rollouts=int(len(roll)), rollout_frames=frames,
                rollout_disagrees_with_brt=int(np.sum(out[roll] != brt[roll])))
    return n, out, sources, info


def trajectory_samples(starts, labels: LabelSpec, run_paths, inside):
    """The ``trajectory`` source's samples: ``starts`` ``(N, n)`` (the first
    ``labels.max_rollouts`` when capped), then the states their runs pass through whose
    label the run settles and that ``inside(states) -> bool array`` keeps. ``run_paths
    (starts) -> dict`` runs the real loop (``failed``, ``path_state`` ``(N, m, n)``,
    ``path_label`` ``(N, m)`` with -1 for unknown, ``ticks``; row 0 is the start).
    Returns ``(states, labels, sources, info)``."""
    starts = np.asarray(starts, float)
    if labels.max_rollouts and len(starts) > labels.max_rollouts:
        starts = starts[:labels.max_rollouts]
    out = run_paths(starts)
    along, settled, left_out = read_along(out, inside, first=1)
    states = np.concatenate([starts, along])
    values = np.concatenate([np.asarray(out["failed"], bool), settled]).astype(np.uint8)
    sources = np.concatenate([np.full(len(starts), SOURCE_ROLLOUT, np.uint8),
                              np.full(len(along), SOURCE_PATH, np.uint8)])
    frames = int(np.sum(out["ticks"]))
    info = {"source": "trajectory", "samples_kept": int(len(starts)),
            "path_samples": int(len(along)), "path_samples_left_out": left_out,
            "rollouts": int(len(starts)), "rollout_frames": frames,
            "frames_per_label": round(frames / len(states), 2)}
    return states, values, sources, info


def read_along(out, inside, *, first: int = 0):
    """The states runs passed through (``out``: `taxi_paths`'s ``path_state`` and
    ``path_label``), from path point ``first`` on (1 leaves the starts out), whose label
    the run settled and that ``inside(states)`` keeps. Returns ``(states, anomalous
    (bool), how many settled states inside left out)``."""
    paths = np.asarray(out["path_state"], float)
    along = paths[:, first:].reshape(-1, paths.shape[2])
    settled = np.asarray(out["path_label"])[:, first:].reshape(-1)
    keep = (settled >= 0) & np.all(np.isfinite(along), axis=1)
    keep[keep] = np.asarray(inside(along[keep]), bool)
    return along[keep], settled[keep] == 1, int(np.sum(settled >= 0) - keep.sum())


def path_starts(lo, hi, count: int, seed: int, half_width: float) -> np.ndarray:
    """``count`` uniform states of the box ``lo``..``hi`` with |px| < ``half_width``
    (a run from off the runway passes through nothing), from a stream of ``seed`` apart
    from the samples'."""
    lo, hi = np.array(lo, float), np.array(hi, float)
    lo[0], hi[0] = max(lo[0], -half_width), min(hi[0], half_width)
    rng = np.random.default_rng([int(seed), 1])
    return lo + rng.uniform(size=(count, len(lo))) * (hi - lo)


def _real_loop(scenario, value_function, states, folder: Path, progress):
    """``run_loop`` for `assign_labels`: the real closed loop from ``states[index]``,
    cached under ``folder/rollouts``."""
    def run_loop(index):
        outcome = real_outcomes(scenario, states[index], grid=value_function.grid,
                                duration=value_function.horizon, cache_dir=folder / "rollouts",
                                progress=progress)
        return outcome.failed, int(np.sum(outcome["ticks"]))
    return run_loop


def _real_paths(scenario, value_function, labels: LabelSpec, folder: Path, progress):
    """``run_paths`` for `trajectory_samples`: `real_paths` cached under
    ``folder/rollouts``."""
    def run_paths(starts):
        return real_paths(scenario, starts, grid=value_function.grid,
                          horizon=value_function.horizon, extend=labels.extend,
                          stride=labels.stride, cache_dir=folder / "rollouts",
                          progress=progress).fields
    return run_paths


def build_dataset(root, scenario, value_function, spec: DatasetSpec = DatasetSpec(), *,
                  ensemble=(), progress=True, box=None) -> Path:
    """Render, estimate and label ``spec.samples`` uniform states of ``box`` (``(lo,
    hi)``, inside the value function's grid; default: the whole grid) in
    ``scenario``'s environment, and with ``trajectory`` labels the states their runs
    pass through (`trajectory_samples`); returns the dataset folder (reused or resumed when it
    already exists)."""
    scenario = resolved(scenario)
    grid = value_function.grid
    if box is not None:
        lo, hi = (np.asarray(b, float) for b in box)
        if lo.shape != grid.lo.shape or hi.shape != grid.lo.shape or np.any(lo >= hi) \
                or not (grid.contains(lo[None]) & grid.contains(hi[None])).all():
            raise ValueError(f"the dataset box {lo.tolist()} .. {hi.tolist()} must be a "
                             f"non-empty box inside the BRT's grid {grid}")
    else:
        lo, hi = grid.lo, grid.hi
    folder = dataset_folder(root, scenario, value_function, spec, ensemble, box)
    folder.mkdir(parents=True, exist_ok=True)
    manifest_path = folder / "manifest.json"
    estimator = None            # the controller is built only when there is work for it
    if manifest_path.exists():
        manifest = _read_manifest(folder)
        k, n = manifest["estimate_size"], manifest["samples"]
        arrays = {name: _open_array(folder, name, shape, "r+") for name, shape in (
            ("images", (n, spec.height, spec.width, 3)), ("estimates", (n, k)),
            ("ensemble", (n, len(ensemble), 2)))}
    else:
        rng = np.random.default_rng(spec.seed)
        states = lo + rng.uniform(size=(spec.samples, grid.ndim)) * (hi - lo)
        if spec.labels.source == "trajectory":
            states, labels, sources, label_info = trajectory_samples(
                states, spec.labels, _real_paths(scenario, value_function, spec.labels,
                                                 folder, progress),
                lambda x: np.all((x >= lo) & (x <= hi), axis=1))
            values, n = value_function.at(states), len(states)
        else:
            values = value_function.at(states)
            n, labels, sources, label_info = assign_labels(
                values, np.abs(states[:, 0]) < scenario.environment.half_width, spec.labels,
                _real_loop(scenario, value_function, states, folder, progress))
            states, values = states[:n], values[:n]
        if spec.labels.paths:
            inside = lambda x: np.all((x >= lo) & (x <= hi), axis=1)   # noqa: E731
            out = _real_paths(scenario, value_function, spec.labels, folder, progress)(
                path_starts(lo, hi, spec.labels.paths, spec.seed,
                            scenario.environment.half_width))
            along, anomalous, left_out = read_along(out, inside)
            states = np.concatenate([states, along])
            values = np.concatenate([values, value_function.at(along)])
            labels = np.concatenate([labels, anomalous.astype(np.uint8)])
            sources = np.concatenate([sources, np.full(len(along), SOURCE_PATH, np.uint8)])
            frames = int(np.sum(out["ticks"]))
            label_info["paths"] = {"runs": int(spec.labels.paths), "samples": int(len(along)),
                                   "left_out": left_out, "frames": frames,
                                   "frames_per_label": round(frames / max(1, len(along)), 2)}
            n = len(states)
        estimator = _estimator(make_controller(scenario.controller))
        k = estimator[1]
        np.save(folder / "states.npy", states)
        np.save(folder / "values.npy", values)
        np.save(folder / "labels.npy", labels)
        np.save(folder / "sources.npy", sources)
        open_mm = np.lib.format.open_memmap
        arrays = {"images": open_mm(folder / "images.npy", "w+", np.uint8,
                                    (n, spec.height, spec.width, 3)),
                  "estimates": open_mm(folder / "estimates.npy", "w+", np.float64, (n, k)),
                  "ensemble": open_mm(folder / "ensemble.npy", "w+", np.float64,
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
                    "ensemble": [str(p) for p in ensemble], "chunks_done": []}
        _write_manifest(folder, manifest)
    states = np.load(folder / "states.npy")
    chunks = [(s, min(s + spec.chunk_size, n)) for s in range(0, n, spec.chunk_size)]
    todo = [c for c in chunks if c[0] not in manifest["chunks_done"]]
    if todo:
        estimate, _ = estimator or _estimator(make_controller(scenario.controller))
        renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)
        ensemble_nets = [TaxiNet(model=m, preprocess_config=p) for m, p, _ in
                         (load_taxinet(c) for c in ensemble)]
        bar = tqdm(total=n, initial=n - sum(e - s for s, e in todo), unit="image",
                   desc=f"dataset {scenario.environment.name}", disable=not progress)
        for s, e in todo:
            full = np.stack([renderer.render(x) for x in states[s:e]])
            arrays["estimates"][s:e] = estimate(full)
            for j, net in enumerate(ensemble_nets):
                arrays["ensemble"][s:e, j] = net.estimate(full)
            arrays["images"][s:e] = resize_for_detector(full, spec)    # as the detector system does
            for a in arrays.values():
                a.flush()
            manifest["chunks_done"].append(s)
            _write_manifest(folder, manifest)
            bar.update(e - s)
        bar.close()
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


def load_dataset(folder) -> LabelledData:
    """Open a finished dataset; raises ValueError if it is incomplete or foreign."""
    folder = Path(folder)
    manifest = _read_manifest(folder)
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{folder}: unknown dataset format {manifest.get('format')}")
    spec = DatasetSpec(**manifest["spec"])
    if len(manifest["chunks_done"]) < -(-manifest["samples"] // spec.chunk_size):
        raise ValueError(f"{folder} is incomplete ({len(manifest['chunks_done'])} chunks); "
                         f"run build_dataset again to resume it")
    n = manifest["samples"]
    load = lambda name, shape, mode=None: _open_array(folder, name, shape, mode)  # noqa: E731
    return LabelledData(folder, manifest,
                        load("images", (n, spec.height, spec.width, 3), "r"),
                        load("states", (n,)), load("values", (n,)), load("labels", (n,)),
                        load("estimates", (n, manifest["estimate_size"])), load("ensemble", (n,)),
                        load("sources", (n,)))
