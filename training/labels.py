"""Where a dataset's labels come from (`LabelSpec`): the BRT's verdict, the real loop's
outcome from each sampled state, a hybrid that rolls out only where an audit distrusts
the map, or the outcomes read along longer real runs. Pure functions of BRT values and
of what a ``run_loop`` / ``run_paths`` callable reports; nothing here renders or knows
the plant (`training.dataset` supplies the taxi's real loop).

The sources are `LabelSource` entries of the registry `LABEL_SOURCE_REGISTRY` (the four
above, registered at the end of this module): the dataset builder labels through
`label_samples`, and run files, ``--labels``, the fidelity check and the report read
the registered names, rules and words, so a new source is a module that registers one."""

import dataclasses as dc
from typing import Callable, NamedTuple, Optional

import numpy as np

from reachwatch.systems.bounds import bounded, check_bounds
from reachwatch.systems.checks import short
from reachwatch.systems.registry import Registry

#: The registered label sources (`LabelSource`), by name.
LABEL_SOURCE_REGISTRY = Registry("label source")
#: Their names (a live view: it prints and compares like the tuple of them, ``('brt',
#: 'rollout', 'hybrid', 'trajectory')`` until another is registered).
LABEL_SOURCES = LABEL_SOURCE_REGISTRY.names
#: Values of ``sources.npy``: the label is the BRT's verdict, the real loop's outcome
#: from the sampled state, or the outcome read along a real run that passed through it.
SOURCE_BRT, SOURCE_ROLLOUT, SOURCE_PATH = 0, 1, 2
#: ``runs.npy``'s entry for a sample that lies on no run shared with other samples.
NO_RUN = -1
#: `LabelSpec` fields read only by the ``trajectory`` source or with ``paths`` (left out
#: of other datasets' keys, so adding them did not move existing datasets).
TRAJECTORY_FIELDS = ("extend", "stride", "paths")
#: `LabelSpec` fields read only by a ``hybrid`` source that falls back to trajectory
#: labels (left out of other datasets' keys for the same reason).
FALLBACK_FIELDS = ("distrusted", "distrusted_starts")
#: What a ``hybrid`` source does in an environment whose audit distrusts the map.
DISTRUSTED_CHOICES = ("rollout", "trajectory")


#: The most real-loop runs a label count may ask for (audit, paths, starts).
MAX_RUNS = 1_000_000


def labels_name(source: str, paths) -> str:
    """A label set's name in tables and reports: its ``source`` (as the caller spells it),
    with " + read-along" when ``paths`` added states read along real runs, so that such
    labels never share a name with the source's alone."""
    return f"{source} + read-along" if paths else source


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
      With ``distrusted: trajectory``, an environment whose audit distrusts the map is
      labelled as the ``trajectory`` source labels it instead, from the first
      ``distrusted_starts`` samples: where the map is wrong (at night) nearly every
      sample it calls safe would be rolled out, about 130-160 frames each, while a
      run read along labels a state for 12-21. An environment whose map the audit
      trusts keeps the BRT's labels and band rollouts; the manifest records which
      (``labelled_by``). The datasets then differ in kind between environments:
      uniform states where the map is trusted, mostly states the loop visits where it
      is not (Table 2 scores both kinds apart).

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

    ``more_audit`` (``hybrid`` only; 0 = off, else above ``audit``): an audit whose
    first ``audit`` runs found the map right goes on, ``audit`` runs at a time, up to
    ``more_audit`` runs, and stops at the first batch that finds a false-safe verdict
    or widens the band past ``max_band``. No false-safe verdict in n runs bounds the
    map's false-safe rate below ``1 - 0.05 ** (1 / n)`` with 95 % confidence: 5.8 % for
    50 runs, 2.9 % for 100, 1.5 % for 200. (A night map with 4-8 % false-safe starts
    passed an audit of 50 in a run of the study's environments.) Each batch is cached
    on its own, so raising ``more_audit`` reuses the runs already made; a distrusted map
    stops the audit early, so where maps are wrong it costs little more than ``audit``
    runs.

    ``max_rollouts`` (0 = no cap) bounds the rollouts per environment: a dataset that
    would need more keeps only its first samples, as many as the cap allows (they are
    still uniform), and its manifest says how many it kept."""
    source: str = "brt"
    audit: int = bounded(50, 0, MAX_RUNS, whole=True, note=">= 1 for hybrid")
    more_audit: int = bounded(0, 0, MAX_RUNS, whole=True, note="0 or above audit")
    band: float = bounded(2.0, 0.0, 1000.0, unit="m")
    band_factor: float = bounded(2.0, 0.0, 1000.0)
    max_band: float = bounded(6.0, 0.0, 1000.0, unit="m", note=">= band")
    max_rollouts: int = bounded(0, 0, 100 * MAX_RUNS, whole=True)
    extend: float = bounded(8.0, 0.0, 600.0, unit="s")
    stride: int = bounded(8, 1, 10_000, whole=True)
    paths: int = bounded(0, 0, MAX_RUNS, whole=True)
    distrusted: str = "rollout"
    distrusted_starts: int = bounded(100, 1, MAX_RUNS, whole=True)

    @property
    def falls_back_to_trajectory(self) -> bool:
        """Whether an environment whose audit distrusts the map gets trajectory labels."""
        return self.source == "hybrid" and self.distrusted == "trajectory"

    @property
    def reads_along(self) -> bool:
        """Whether the samples may include states read along real runs (``paths``, or a
        source whose `LabelSource.reads_along` says so: ``trajectory`` labels, a hybrid
        that falls back to them): such datasets record each sample's run."""
        return bool(label_source(self.source).reads_along(self)) or self.paths > 0

    def key(self) -> dict:
        """What keys a dataset built with these labels: every field, ``more_audit`` only
        when set (adding it moved no existing dataset)."""
        fields = dc.asdict(self)
        if not self.more_audit:
            fields.pop("more_audit")
        return fields

    def validate(self, where="dataset.labels"):
        if self.source not in LABEL_SOURCE_REGISTRY:
            raise ValueError(f"{where}.source must be one of {LABEL_SOURCES}, got "
                             f"{short(self.source)}")
        check_bounds(self, f"{where}.")
        if self.more_audit and (self.audit < 1 or self.more_audit <= self.audit):
            raise ValueError(f"{where}.more_audit must be 0 (an audit of {where}.audit runs) "
                             f"or a whole number above {where}.audit ({self.audit}, at least "
                             f"1), got {self.more_audit}")
        check = label_source(self.source).check
        if check is not None:
            check(self, where)
        if self.distrusted not in DISTRUSTED_CHOICES:
            raise ValueError(f"{where}.distrusted must be one of {DISTRUSTED_CHOICES} (what "
                             f"the hybrid source does where its audit distrusts the map), "
                             f"got {short(self.distrusted)}")
        if self.max_band < self.band:
            raise ValueError(f"{where}.max_band ({self.max_band} m) must be at least band "
                             f"({self.band} m)")
        return self


class LabelInputs(NamedTuple):
    """What a `LabelSource` labels from: ``states`` ``(N, n)``, the uniform samples in
    order; ``labels`` the `LabelSpec`; ``values_at(states)`` the BRT's values;
    ``not_failed(states)`` where the loop has not failed yet (bool); ``run_loop(states)
    -> (failed, frames)`` the real loop from each state for the BRT's horizon;
    ``run_paths(starts) -> dict`` the real loop's runs read along (`trajectory_samples`);
    ``inside(states)`` whether states lie in the dataset's box (bool). The callables
    that run the loop render; the rest are pure."""
    states: np.ndarray
    labels: LabelSpec
    values_at: Callable
    not_failed: Callable
    run_loop: Callable
    run_paths: Callable
    inside: Callable


class Labelled(NamedTuple):
    """A source's labels: the samples' ``states``, their BRT ``values``, ``labels``
    (uint8, 1 = anomalous), ``sources`` (uint8: `SOURCE_BRT`, `SOURCE_ROLLOUT`,
    `SOURCE_PATH`), ``info`` (the manifest's ``labels`` record, ``source`` included)
    and ``runs`` (the run each sample lies on, `NO_RUN` for none)."""
    states: np.ndarray
    values: np.ndarray
    labels: np.ndarray
    sources: np.ndarray
    info: dict
    runs: np.ndarray


def _never(*_):
    return False


@dc.dataclass(frozen=True, kw_only=True)
class LabelSource:
    """A label source, registered by ``name`` in `LABEL_SOURCE_REGISTRY`:

    - ``label(inputs: LabelInputs) -> Labelled``: the dataset's samples and labels;
    - ``verdicts(record, band, values, real_failed) -> bool array``: what this rule
      gives at fresh states with BRT values ``values`` whose real outcomes are
      ``real_failed`` (``record``: the manifest's ``labels`` record; ``band`` m where
      it recorded none): the fidelity check compares them with the real loop;
    - ``text``: what the labels are, for the report; ``table_name``: how tables name a
      detector trained on them (default ``name``);
    - ``reads_along(spec) -> bool``: whether its samples may include states read along
      runs (their run is recorded, and `TRAJECTORY_FIELDS` keyed);
    - ``by_own_run(record) -> bool``: whether a fresh state's label is its own run's
      outcome (then it agrees with the real loop by construction);
    - ``check(spec, where)``: a further check of the `LabelSpec` for this source (a
      one-line ValueError), or None.

    The name is all that dataset keys and run files hold of a source (with the
    `LabelSpec` fields): give a changed rule a new name."""
    name: str
    label: Callable
    verdicts: Callable
    text: str
    table_name: str = ""
    reads_along: Callable = _never
    by_own_run: Callable = _never
    check: Optional[Callable] = None

    def __post_init__(self):
        if not self.table_name:
            object.__setattr__(self, "table_name", self.name)


def label_source(name) -> LabelSource:
    """The registered `LabelSource` named ``name``, or a one-line ValueError."""
    if name not in LABEL_SOURCE_REGISTRY:
        raise ValueError(f"label source must be one of {LABEL_SOURCES}, got {short(name)}")
    return LABEL_SOURCE_REGISTRY.get(name)


def label_samples(inputs: LabelInputs) -> Labelled:
    """The labels of ``inputs.states`` by their source (``inputs.labels.source``):
    `LabelSource.label` of the registered one."""
    return label_source(inputs.labels.source).label(inputs)


def label_verdicts(record: dict, band: float, values, real_failed) -> np.ndarray:
    """`LabelSource.verdicts` of the source that made ``record`` (a manifest's
    ``labels`` record)."""
    return np.asarray(label_source(record["source"]).verdicts(record, band, values,
                                                              real_failed), bool)


def labels_every_state_by_its_run(record: dict) -> bool:
    """`LabelSource.by_own_run` of the source that made ``record``."""
    return bool(label_source(record.get("source", "brt")).by_own_run(record))


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


def _audit(values, not_failed, labels: LabelSpec, run, failed):
    """The ``hybrid`` source's audit: ``run(index)`` runs the real loop from the first
    ``labels.audit`` on-runway states (and on, a batch of ``labels.audit`` at a time up
    to ``labels.more_audit``, while the map stays trusted) and records each outcome in
    ``failed`` {index: bool}. Returns ``(audit index, their outcomes, record)``, the
    record being what the manifest keeps: samples, real failures, false-safe verdicts,
    the largest error, whether the map is trusted and the band (``labels.band`` when it
    is not); with ``more_audit``, also the batches run."""
    candidates = np.flatnonzero(not_failed)
    size = min(max(labels.audit, labels.more_audit), len(candidates))
    audit, batches, trusted = candidates[:0], 0, True
    while len(audit) < size and trusted:
        batch = candidates[len(audit):min(len(audit) + labels.audit, size)]
        run(batch)                      # one call per batch: each is cached on its own
        audit, batches = candidates[:len(audit) + len(batch)], batches + 1
        trusted = audited_band(values[audit], [failed[i] for i in audit.tolist()],
                               band=labels.band, band_factor=labels.band_factor,
                               max_band=labels.max_band)[1]
    audit_failed = np.array([failed[i] for i in audit.tolist()], bool)
    band, trusted, largest = audited_band(values[audit], audit_failed, band=labels.band,
                                          band_factor=labels.band_factor,
                                          max_band=labels.max_band)
    record = {
        "samples": int(len(audit)), "real_failures": int(audit_failed.sum()),
        "false_safe": int(np.sum(audit_failed & (values[audit] > 0))),
        "largest_error_m": largest, "map_trusted": trusted,
        "band": band if trusted else labels.band}
    if labels.more_audit:
        record["batches"] = batches
    return audit, audit_failed, record


def assign_labels(values, not_failed, labels: LabelSpec, run_loop):
    """Labels and their sources for states with BRT values ``values`` under
    ``labels.source``; ``not_failed`` marks the states where the loop has not failed
    yet (the audit's candidates) and ``run_loop(index) -> (failed, frames)`` runs the
    real loop from the states at ``index`` (called at most twice: the audit, then the
    rest). Returns ``(n kept, labels, sources, info)``.

    A ``hybrid`` source with ``distrusted: trajectory`` stops after an audit that
    distrusts the map and returns ``(0, None, None, info)``, ``info["labelled_by"]``
    being ``"trajectory"``: the caller labels the environment by `trajectory_samples`
    (it renders; this module does not). Only these three sources label this way (the
    registered ones label through `label_samples`)."""
    if labels.source not in ("brt", "rollout", "hybrid"):
        raise ValueError(f"assign_labels labels the brt, rollout and hybrid sources, not "
                         f"{short(labels.source)} (see label_samples)")
    values, not_failed = np.asarray(values, float), np.asarray(not_failed, bool)
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
        audit, audit_failed, info["audit"] = _audit(values, not_failed, labels, run, failed)
        band, trusted = info["audit"]["band"], info["audit"]["map_trusted"]
        if not trusted and labels.falls_back_to_trajectory:
            info.update(labelled_by="trajectory", audit_frames=frames)
            return 0, None, None, info
        uncertain = hybrid_rolls_out(values, band, trusted) & not_failed
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
    Returns ``(states, labels, sources, info, runs)``; ``runs[i]`` is the index of the
    run sample ``i`` lies on (its start's row)."""
    starts = np.asarray(starts, float)
    if labels.max_rollouts and len(starts) > labels.max_rollouts:
        starts = starts[:labels.max_rollouts]
    out = run_paths(starts)
    along, settled, left_out, runs = read_along(out, inside, first=1)
    states = np.concatenate([starts, along])
    values = np.concatenate([np.asarray(out["failed"], bool), settled]).astype(np.uint8)
    sources = np.concatenate([np.full(len(starts), SOURCE_ROLLOUT, np.uint8),
                              np.full(len(along), SOURCE_PATH, np.uint8)])
    frames = int(np.sum(out["ticks"]))
    info = {"source": "trajectory", "samples_kept": int(len(starts)),
            "path_samples": int(len(along)), "path_samples_left_out": left_out,
            "rollouts": int(len(starts)), "rollout_frames": frames,
            "frames_per_label": round(frames / len(states), 2)}
    return states, values, sources, info, np.concatenate([np.arange(len(starts)), runs])


def read_along(out, inside, *, first: int = 0):
    """The states runs passed through (``out``: `reach.loop_runs.loop_paths`'s ``path_state`` and
    ``path_label``), from path point ``first`` on (1 leaves the starts out), whose label
    the run settled and that ``inside(states)`` keeps. Returns ``(states, anomalous
    (bool), how many settled states inside left out, the run of each state (its row in
    ``out``))``."""
    paths = np.asarray(out["path_state"], float)
    along = paths[:, first:].reshape(-1, paths.shape[2])
    runs = np.repeat(np.arange(len(paths)), paths.shape[1] - first)
    settled = np.asarray(out["path_label"])[:, first:].reshape(-1)
    keep = (settled >= 0) & np.all(np.isfinite(along), axis=1)
    keep[keep] = np.asarray(inside(along[keep]), bool)
    return along[keep], settled[keep] == 1, int(np.sum(settled >= 0) - keep.sum()), runs[keep]


def _assigned(inputs: LabelInputs) -> Labelled:
    """``brt``, ``rollout`` and ``hybrid`` labels (`assign_labels`); a hybrid whose
    audit distrusts the map with ``distrusted: trajectory`` labels by
    `trajectory_samples` from the first ``distrusted_starts`` samples instead."""
    states, spec = np.asarray(inputs.states, float), inputs.labels
    values = inputs.values_at(states)
    n, labels, sources, info = assign_labels(
        values, inputs.not_failed(states), spec, lambda index: inputs.run_loop(states[index]))
    if info.get("labelled_by") == "trajectory":          # the audit distrusts the map
        states, labels, sources, read, runs = trajectory_samples(
            states[:spec.distrusted_starts], spec, inputs.run_paths, inputs.inside)
        return Labelled(states, inputs.values_at(states), labels, sources,
                        {**read, **info}, runs)
    return Labelled(states[:n], values[:n], labels, sources, info,
                    np.full(n, NO_RUN, np.int64))


def _trajectory(inputs: LabelInputs) -> Labelled:
    states, labels, sources, info, runs = trajectory_samples(
        inputs.states, inputs.labels, inputs.run_paths, inputs.inside)
    return Labelled(states, inputs.values_at(states), labels, sources, info, runs)


def _check_hybrid(spec: LabelSpec, where: str):
    if spec.audit == 0:
        raise ValueError(f"{where}.audit must be >= 1 for the hybrid source: an audit of "
                         f"no runs would trust every map unchecked (use source: brt for "
                         f"the map's labels alone)")


def _hybrid_verdicts(record, band, values, real_failed):
    if record.get("labelled_by") == "trajectory":        # rolled out everywhere
        return np.asarray(real_failed, bool)
    audit = record["audit"]
    rolled = hybrid_rolls_out(values, audit.get("band", band), audit["map_trusted"])
    return np.where(rolled, real_failed, np.asarray(values) <= 0)


def _real(record, band, values, real_failed):
    return np.asarray(real_failed, bool)             # a fresh uniform state: its own run


def _always(*_):
    return True


LABEL_SOURCE_REGISTRY.register(LabelSource(
    name="brt", label=_assigned, table_name="BRT",
    verdicts=lambda record, band, values, real_failed: np.asarray(values) <= 0,
    text="anomalous iff V(x) <= 0: as right as the BRT map"))
LABEL_SOURCE_REGISTRY.register(LabelSource(
    name="rollout", label=_assigned, table_name="real-loop", verdicts=_real,
    by_own_run=_always, text="the real Drake loop run from every state: exact"))
LABEL_SOURCE_REGISTRY.register(LabelSource(
    name="hybrid", label=_assigned, table_name="hybrid", verdicts=_hybrid_verdicts,
    reads_along=lambda spec: spec.falls_back_to_trajectory,
    by_own_run=lambda record: record.get("labelled_by") == "trajectory",
    check=_check_hybrid,
    text="the real Drake loop within a band of the BRT's boundary as wide as an audit of "
         "the map measures its errors to reach, or wherever the map calls a state safe "
         "when the audit finds a false-safe verdict or errors too far out to trust it; "
         "V(x) <= 0 elsewhere"))
LABEL_SOURCE_REGISTRY.register(LabelSource(
    name="trajectory", label=_trajectory, table_name="real-loop trajectory",
    verdicts=_real, reads_along=_always, by_own_run=_always,
    text="the real Drake loop run from every uniform state for longer than the horizon, "
         "and the states each run passes through labelled by the same run: exact for a "
         "loop whose state is all it remembers; those added states are where the loop "
         "goes, not uniform"))
