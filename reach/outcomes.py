"""What the real closed loop does from given starts: run a rollout function over
the starts chunk by chunk, on any executor, each finished chunk written atomically
under ``cache_dir/key/``, so a killed batch resumes and a repeated one costs
nothing.

A rollout function is any picklable callable ``rollout(states) -> dict`` mapping
``(n, ndim)`` starts to arrays with ``n`` rows: ``failed`` (bool) is required;
``failure_time`` (s), ``left_box`` (bool) and ``ticks`` (frames rendered) are read
when present. An application's is its `Application.real_outcomes` rollout (the
generic one is `reachwatch.reach.loop_runs.loop_rollouts`); anything deterministic
that runs the loop the labels are about will do.

`path_labels` reads labels for every tick of one longer run: for a loop whose state
is all it remembers (its controller has no state of its own), the run from a state it
passes through is the rest of the same run."""

import dataclasses as dc
import functools
import hashlib

import numpy as np
from tqdm import tqdm

from reachwatch.systems.files import cache_join, make_folder
from .chunk_files import FolderStore, split
from .chunks import run_chunks
from .executors import InlineExecutor, WorkerLost
from .fingerprint import fingerprint


@dc.dataclass
class Outcomes:
    """Per-start arrays of a batch of rollouts (``fields["failed"]`` and whatever else
    the rollout function returned); ``computed``: starts run by the call that
    returned it (0 when every chunk was cached)."""
    fields: dict
    key: str
    computed: int = 0

    def __getitem__(self, name):
        return self.fields[name]

    def __len__(self):
        return len(self.fields["failed"])

    @property
    def failed(self) -> np.ndarray:
        return self.fields["failed"].astype(bool)


def outcomes_key(rollout, states) -> str:
    """The cache folder name of a batch: the rollout function's fingerprint and the
    hash of the starts' bytes."""
    states = np.ascontiguousarray(states, np.float64)
    digest = hashlib.sha256(states.tobytes() + str(states.shape).encode()).hexdigest()[:12]
    base = getattr(rollout, "func", rollout)
    return f"{getattr(base, '__name__', 'rollout')}_{len(states)}_{fingerprint(rollout)[:16]}_{digest}"


def _run_chunk(fn, states, required) -> dict:
    """``fn(states)``'s arrays, checked: a worker returns them and the driver writes the
    cache, so no worker needs the driver's filesystem."""
    out = fn(states)
    if not isinstance(out, dict) or any(name not in out for name in required):
        raise ValueError(f"{getattr(getattr(fn, 'func', fn), '__name__', 'the function')} must "
                         f"return a dict with {', '.join(map(repr, required)) or 'arrays'}, got "
                         f"{sorted(out) if isinstance(out, dict) else type(out).__name__}")
    arrays = {k: np.asarray(v) for k, v in out.items()}
    for name, a in arrays.items():
        if a.shape[:1] != (len(states),):
            raise ValueError(f"output '{name}' has {a.shape[:1]} rows for {len(states)} states")
    return arrays


def _fits(required):
    """Whether a stored chunk holds every ``required`` array and only arrays with one
    row per state (else it is run again)."""
    def fits(chunk, arrays) -> bool:
        return (all(n in arrays for n in required) and
                all(len(a) == chunk.rows for a in arrays.values()))
    return fits


def default_chunk_size(count: int) -> int:
    """8 states per chunk, fewer for a batch under 32 states so that it still makes 4
    chunks that a pool's workers share (a chunk's cache file holds its own rows, so
    the size of a batch's chunks must not change between runs: it depends only on
    ``count``)."""
    return min(8, max(1, -(-int(count) // 4)))


def map_states(fn, states, *, cache_dir, chunk_size: int = None, executor=None,
               progress: bool = True, label: str = None, max_in_flight: int = None,
               required=(), unit: str = "state"):
    """``fn(states[s:e]) -> dict of arrays with e - s rows`` over ``states`` ``(N, ndim)``
    in chunks of ``chunk_size`` (default `default_chunk_size`), each cached under
    ``cache_dir/outcomes_key(fn, states)``
    and run on ``executor`` (default: here, one after another); ``required`` names the
    arrays every chunk must hold. Each chunk's arrays come back to this process, which
    writes the cache: workers share no filesystem with it. At most ``max_in_flight``
    chunks are in flight (default: twice the executor's worker threads, `in_flight`).
    The progress bar moves per chunk. Returns
    ``(fields, key, computed)``: the arrays of all states in order, the cache folder
    name, and the states this call ran (0 when every chunk was cached). ``cache_dir``
    is a local folder or an fsspec URL (``memory://...``, ``s3://...``)."""
    states = np.asarray(states, float)
    if states.ndim != 2 or len(states) == 0 or not np.all(np.isfinite(states)):
        raise ValueError(f"states must be a non-empty (N, ndim) array of finite numbers, got "
                         f"shape {states.shape}")
    if chunk_size is None:
        chunk_size = default_chunk_size(len(states))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a whole number >= 1, got {chunk_size!r}")
    required = tuple(required)
    key = outcomes_key(fn, states)
    folder = cache_join(cache_dir, key)
    make_folder(folder)
    chunks = split(len(states), chunk_size)
    # the key holds the states, not the chunk size: each file says which rows it holds
    store = FolderStore(folder, _fits(required), keep=True, rows=True)
    ran = run_chunks(_run_chunk, chunks, store,
                     args=lambda c: (fn, states[c.start:c.stop], required), executor=executor,
                     default=InlineExecutor, max_in_flight=max_in_flight, caller="map_states",
                     bar=functools.partial(tqdm, total=len(states), unit=unit,
                                           desc=label or key, disable=not progress))
    computed = sum(c.rows for c in ran)
    fields = None
    for chunk in chunks:
        arrays = store.read(chunk)
        if arrays is None:
            raise WorkerLost(f"chunk {chunk.index} of {key} did not finish (its file is "
                             f"missing or damaged after its worker stored it); a re-run "
                             f"computes it again")
        if fields is None:
            fields = {k: np.empty((len(states),) + a.shape[1:], a.dtype) for k, a in arrays.items()}
        _check_chunk_fields(fields, arrays, chunk, key)
        for k, a in arrays.items():
            if not np.can_cast(a.dtype, fields[k].dtype, "safe"):     # e.g. ints, then floats
                fields[k] = fields[k].astype(np.result_type(fields[k].dtype, a.dtype))
            fields[k][chunk.start:chunk.stop] = a
    return fields, key, computed


def _check_chunk_fields(fields, arrays, chunk, key):
    """Every chunk of one `map_states` holds the same arrays, of the same shape per
    state, as the first: the call's function returned otherwise (one line that says
    how) rather than a field left unfilled or cut to another's shape."""
    if set(arrays) != set(fields):
        raise ValueError(f"chunk {chunk.index} of {key} holds the arrays {sorted(arrays)}, the "
                         f"first chunk {sorted(fields)}: the function must return the same "
                         f"names from every chunk")
    for k, a in arrays.items():
        if a.shape[1:] != fields[k].shape[1:]:
            raise ValueError(f"chunk {chunk.index} of {key}: {k!r} has shape {a.shape[1:]} a "
                             f"state, the first chunk's {fields[k].shape[1:]}: the function "
                             f"must return the same shape from every chunk")


def run_outcomes(rollout, states, *, cache_dir, chunk_size: int = None, executor=None,
                 progress: bool = True, label: str = None, max_in_flight: int = None) -> Outcomes:
    """``rollout`` from every start in ``states`` ``(N, ndim)``; chunks of
    ``chunk_size`` starts (default `default_chunk_size`) are cached under ``cache_dir/outcomes_key(...)`` and run
    on ``executor`` (default: here, one after another). The progress bar moves per
    chunk."""
    fields, key, computed = map_states(
        rollout, states, cache_dir=cache_dir, chunk_size=chunk_size, executor=executor,
        progress=progress, label=f"real loop {label or ''}".rstrip(),
        max_in_flight=max_in_flight, required=("failed",), unit="run")
    return Outcomes(fields=fields, key=key, computed=computed)


def recording_fields(count: int, length: int, height: int, width: int, signals: int,
                     state_dim: int, *, scored: bool = False) -> dict:
    """The fields of ``count`` recorded runs of ``length`` control ticks, empty: ``frames``
    uint8 ``(count, length, height, width, 3)``, ``signals`` ``(count, length, signals)``
    and ``state`` ``(count, length, state_dim)`` (NaN), ``ticks``, ``failed``,
    ``failure_time`` (NaN); ``scored``: ``score`` ``(count, length)`` (NaN) too. Every
    real-loop recorder fills these (`put_recording`), so a monitor reads one layout."""
    return {"frames": np.zeros((count, length, height, width, 3), np.uint8),
            "signals": np.full((count, length, signals), np.nan),
            "state": np.full((count, length, state_dim), np.nan),
            "ticks": np.zeros(count, int), "failed": np.zeros(count, bool),
            "failure_time": np.full(count, np.nan),
            **({"score": np.full((count, length), np.nan)} if scored else {})}


def put_recording(out: dict, i: int, *, frames=None, signals=None, state=None, score=None,
                  failed: bool, failure_time: float):
    """Run ``i`` into `recording_fields` ``out``: its first ``n`` ticks (``n``: the rows
    of ``state``, at most the fields' length; none for a start that had already failed,
    whose failure time is then 0) and its outcome (``failure_time`` kept only if it
    failed)."""
    n = 0 if state is None else min(len(state), out["state"].shape[1])
    if n:
        out["frames"][i, :n] = np.asarray(frames)[:n]
        out["signals"][i, :n] = np.asarray(signals)[:n]
        out["state"][i, :n] = np.asarray(state)[:n]
        if score is not None:
            out["score"][i, :n] = np.asarray(score, float)[:n]
    out["ticks"][i] = n
    out["failed"][i] = bool(failed)
    out["failure_time"][i] = failure_time if failed else np.nan


def time_to_failure(time, failure_time: float, duration: float):
    """How long each state a run passes through (at its ticks ``time``, s from 0) has
    until the run fails: ``(ttf s, observed)``. For a run that failed (at
    ``failure_time`` s; NaN or None for none) the time is ``failure_time - t`` and
    observed; for one that did not, it is right-censored at the end of the run
    (``duration`` s): ``duration - t`` and not observed, meaning "no failure before
    that long", never "safe". A label source for any loop whose runs are logged at
    its control ticks; `fails_within` turns it into labels for a horizon."""
    time = np.asarray(time, float)
    if time.ndim != 1 or not np.all(np.isfinite(time)):
        raise ValueError(f"time must be a 1-d array of finite tick times, got shape {time.shape}")
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a finite number > 0 s, got {duration}")
    failed = failure_time is not None and np.isfinite(failure_time)
    end = float(failure_time) if failed else float(duration)
    return end - time, np.full(len(time), failed, bool)


def fails_within(ttf, observed, within: float) -> np.ndarray:
    """Labels for "the run fails within ``within`` s of this state" from
    `time_to_failure`'s ``(ttf, observed)``: 1 where an observed failure comes within
    ``within`` s, 0 where none comes within it (observed later, or censored only after
    ``within`` s had passed), -1 where the run was censored sooner, so it cannot tell."""
    if not (np.isfinite(within) and within > 0):
        raise ValueError(f"horizon must be a finite number > 0 s, got {within}")
    ttf, observed = np.asarray(ttf, float), np.asarray(observed, bool)
    eps = 1e-9
    labels = np.full(ttf.shape, -1, np.int8)
    labels[observed & (ttf <= within + eps)] = 1
    labels[observed & (ttf > within + eps)] = 0
    labels[~observed & (ttf + eps >= within)] = 0
    return labels


def path_labels(time, failure_time: float, duration: float, horizon: float) -> np.ndarray:
    """Labels of the states a run passes through at its ticks ``time`` (s, from 0):
    1 where the run fails (at ``failure_time`` s; NaN for none) within ``horizon`` s
    of the tick, 0 where it does not and the run lasted (``duration`` s, or until its
    failure) at least ``horizon`` s past the tick, and -1 where the run ended before
    the tick's horizon did, so it cannot tell: `fails_within` of `time_to_failure`.

    These are the outcomes the loop would have from each of those states if started
    there, provided the loop's state is all it remembers and its control ticks fall
    on the run's: the real loop's logged ticks are control ticks, and a loop whose
    controller keeps its own state (a filter, a frame history) breaks the premise."""
    return fails_within(*time_to_failure(time, failure_time, duration), horizon)


def path_points(horizon: float, extend: float, stride: int, period: float) -> np.ndarray:
    """The ticks at which labels are read along a run (`Application.real_paths`): every
    ``stride``-th tick from the start (tick 0) up to ``extend`` s, the stretch whose
    horizon the run of ``horizon + extend`` s covers."""
    return np.arange(int(np.floor(extend / (stride * period) + 1e-9)) + 1) * int(stride)


def path_fields(count: int, points, state_dim: int) -> dict:
    """The fields of `Application.real_paths` for ``count`` starts, empty (see
    `put_path`): ``failed``, ``failure_time`` (NaN), ``left_box``, ``max_abs_theta``
    (NaN), ``ticks``, ``path_state`` ``(count, len(points), state_dim)`` (NaN) and
    ``path_label`` ``(count, len(points))`` (-1). Every real-loop path runner fills
    these, so the labels read one layout."""
    return {"failed": np.zeros(count, bool), "failure_time": np.full(count, np.nan),
            "left_box": np.zeros(count, bool), "max_abs_theta": np.full(count, np.nan),
            "ticks": np.zeros(count, int),
            "path_state": np.full((count, len(points), state_dim), np.nan),
            "path_label": np.full((count, len(points)), -1, np.int8)}


def put_path(out: dict, i: int, start, *, time=None, state=None, failure_time=None,
             duration: float = 0.0, horizon: float = 0.0, points=()) -> np.ndarray:
    """Start ``i`` into `path_fields` ``out``: a run from ``start`` logged at ``time``
    with ``state`` over ``duration`` s, failed at ``failure_time`` (None: not), its
    states at ``points`` labelled by `path_labels` (``failed`` is the start's own label,
    within ``horizon``); no ``time``: a start that had already failed (labelled 1, at
    time 0). Returns the mask of the run's ticks within ``horizon`` (none for a start
    that had failed), over which the caller reads ``left_box`` and ``max_abs_theta``."""
    if time is None:
        out["failed"][i], out["failure_time"][i] = True, 0.0
        out["path_state"][i, 0], out["path_label"][i, 0] = start, 1
        return np.zeros(0, bool)
    labels = path_labels(time, failure_time, duration, horizon)
    kept = np.asarray(points)[np.asarray(points) < len(time)]
    out["failed"][i] = labels[0] == 1
    out["failure_time"][i] = np.nan if failure_time is None else failure_time
    out["ticks"][i] = len(time)
    out["path_state"][i, :len(kept)] = np.asarray(state)[kept]
    out["path_label"][i, :len(kept)] = labels[kept]
    return np.asarray(time) <= horizon + 1e-9


def check_memoryless(controller):
    """Raise ValueError when the loop's ``controller`` (a Drake System) keeps state of
    its own (a filter, a frame history): then the run from a state a longer run passed
    through is not the rest of that run, and labels read along runs would be guesses."""
    states = controller.CreateDefaultContext().num_total_states()
    if states:
        raise ValueError(
            f"trajectory labels need a controller that keeps no state of its own, but "
            f"'{controller.get_name()}' ({type(controller).__name__}) has {states}: a run "
            f"from a state a longer run passed through would not repeat that run. Label "
            f"with dataset.labels.source: rollout instead")
