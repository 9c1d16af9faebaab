"""`MonitorStudySpec`: the run file's ``monitor:`` section, the study that trains and
judges monitors over the image history (the guard stage guards with ``detector:``'s
single-image detector)."""

import dataclasses as dc
import math
from typing import List, Optional

import numpy as np

from reachwatch.diagrams import MonitorConfig
from reachwatch.reach.application import NoRandomEnvironments
from reachwatch.diagrams.scenario import MAX_FLAG_WINDOW
from reachwatch.diagrams.schemas import (ApplicationEnvironment, ApplicationRandomEnvironments,
                                         slot_field)
from reachwatch.systems import MAX_MEMBERS, TEMPORAL_MODELS, HistoryMonitorConfig
from reachwatch.systems.history_model import check_input_norm, check_pool
from reachwatch.systems.bounds import bounded, bounded_as, check_bounds, seed_field
from reachwatch.systems.checks import check_label, short, warn_once
from reachwatch.systems.flag_filter import check_k_of_n
from reachwatch.training.history_train import (LR_SCHEDULES, HistoryTrainConfig,
                                               check_state_targets)

from .slot_defaults import application_default


MONITOR_KINDS = ("detector", "history")
#: The study's row of the single-image detector judged beside its variants
#: (``compare_detector``); no variant may take the name.
DETECTOR_ROW = "single-image detector"

#: ``monitor.keep``'s value that chooses the kept monitor on the calibration
#: environments; no variant may take the name.
CHOOSE = "choose"

#: The study's row of the oracle monitor in the guarded real loop; no variant may take
#: the name.
ORACLE = "oracle (privileged)"


@dc.dataclass
class MonitorVariant:
    """One monitor to train over the image history.

    Keys:

    ``name``: its name in the report (and its checkpoint's file name).

    ``frames``: how many frames it reads at each tick, the current one included.

    ``stride``: control ticks between the frames it reads.

    ``temporal``: how it combines them (`reachwatch.systems.TEMPORAL_MODELS`): ``stack``
    (the frames' features side by side) or ``gru`` (a recurrent network over them).

    ``signals``: it also reads the loop's online signals (the controller's estimate,
    where it has one, and its steering; without an estimate, the steering alone)."""
    name: str = "single frame"
    frames: int = bounded_as(1, HistoryMonitorConfig, "frames")
    stride: int = bounded_as(1, HistoryMonitorConfig, "stride")
    temporal: str = "stack"
    signals: bool = False


def warn_unused_study_keys(spec, where: str) -> None:
    """A one-line warning (once per process and set of keys) when ``spec``, a study that
    is off (``kind`` not ``history``), sets keys of the study other than ``family``: they
    do nothing, which a run file that meant to run the study would not see. A warning,
    not an error: ``kind: detector`` is also how a run file switches a study it keeps
    off, and then the line says what is off."""
    defaults = type(spec)()
    given = tuple(f.name for f in dc.fields(spec) if f.name not in ("kind", "family")
                  and getattr(spec, f.name) != getattr(defaults, f.name))
    if given:
        warn_once(f"{where}.kind is {short(spec.kind)}, so the monitor study does not run "
                  f"and {short(list(given))} set in {where} do nothing (set {where}.kind: "
                  f"history to run it)")


def default_variants() -> List[MonitorVariant]:
    return [MonitorVariant("single frame"),
            MonitorVariant("stacked 8 (1.4 s)", frames=8, stride=4),
            MonitorVariant("GRU 16 (0.75 s)", frames=16, temporal="gru"),
            MonitorVariant("stacked 8 (1.4 s) + signals", frames=8, stride=4, signals=True),
            MonitorVariant("GRU 16 (0.75 s) + signals", frames=16, temporal="gru", signals=True)]


@dc.dataclass
class MonitorStudySpec:
    """Which monitor guards the loop, and the study that trains and judges monitors over
    the image history. With ``kind: history`` the study draws ``train``, ``calibrate``
    and ``held_out`` environments, in that order, from the application's random
    ``family``; records real runs in each; trains every variant on the first; fixes
    each variant's threshold and flag rule on the second by conformal risk control
    (`reachwatch.training.conformal`); keeps the variant named by ``keep``, fixed
    before any of them is seen (or, with ``keep: choose``, the one with the fewest
    needless flags there); and judges it on the third and on ``also_held_out``, offline and, with
    ``guarded_runs``, in the guarded real loop beside the single-frame variant and the
    oracle monitor. What the defaults were chosen on, and the measurements: [why the
    study's defaults](../results/monitor.md#why-the-studys-defaults) in the docs.

    Keys:

    ``kind``: ``detector`` (this study is off) or ``history`` (this study, which
    writes its monitors' checkpoints to ``OUT/monitor/``). Either way the ``guard:``
    stage guards with the single-image detector of ``detector:``.

    ``family``: the application's random family the environments are drawn from (the
    taxi's: a ``seed``, hours, skies and runways); its ``count`` is ``train +
    calibrate + held_out``: leave it out. Left out whole, it is the application's
    default family (the taxi's: seed 11, the family the study's defaults were chosen
    on, so its figures are optimistic: give another ``seed`` for a verdict of your
    own).

    ``train``: environments the monitors train on.

    ``calibrate``: environments the thresholds are fixed on; at least 1 / alpha - 1.

    ``held_out``: environments of the family the kept monitor is judged on, within the
    threshold's guarantee.

    ``also_held_out``: named environments outside the family (e.g. the paper's nights),
    judged with the same threshold but outside its guarantee. Their starts are seeded by
    their place after the family's ``train + calibrate + held_out`` environments
    (`monitor_runs.starts_seed`): two studies judge them on the same starts only where
    those three counts add up to the same.

    ``runs``: real runs recorded per training environment (and per calibration and
    judged one, unless set apart below), from the application's seeded starts
    in its grid's box (the taxi's: the paper's box; each environment's starts have a
    random stream of their own).

    ``held_out_runs``: runs recorded per judged environment (held out, of the family
    or outside it); 0: ``runs``. More failing runs to count misses over, without
    training on more (the taxi's starts are drawn in order: its first ``runs`` are
    the same starts).

    ``calibration_runs``: runs recorded per calibration environment; 0: as many as a
    judged one (``held_out_runs``, or ``runs``). The conformal bound speaks of
    environments measured so: an environment's loss is the share of its failing runs
    missed, 0 when none fails, and with fewer runs fewer environments have a failing
    one, so calibration environments with fewer runs than the judged ones bound a
    smaller quantity than the one judged (measured: docs/results/monitor-protocol.md).

    ``duration``: seconds per recorded run. A run that survives it is watched
    ``within`` s longer (the loop alone, not recorded: on from the recording's last
    state when the controller keeps no state of its own, else again from the start),
    so its labels are known and a flag of a run that fails just after is not counted
    needless.

    ``within``: the risk is that of failing within this many seconds. Set it for your
    fallback: the default suits braking's 1.67 s from 5 m/s at 3 m/s^2.

    ``brake_deceleration``: the fallback's braking, m/s^2; a warning counts when it
    comes at least the application's stopping time before the failure
    (`Application.stopping_time`; by default speed / deceleration s).

    ``alpha``: the threshold bounds the expected miss rate of a new environment of the
    family at alpha, an environment where no run fails counting as missing none (so
    where runs fail the bound is alpha over the share of environments with failures;
    the report gives it).

    ``given_failures``: fix the threshold on the calibration environments with a
    warnable failing run alone, so that alpha bounds the expected miss rate of a new
    environment where some run fails; it needs at least 1 / alpha - 1 such
    environments, else the study stops with an error naming how many it had.

    ``height``: the monitors' frame height, px (the camera's frame is resized to it).

    ``width``: the monitors' frame width, px.

    ``pool``: the grid of cells [rows, columns] the encoder's last feature map is
    averaged over (`reachwatch.systems.HistoryMonitorConfig`); [1, 1] averages it
    whole, losing where in the frame a pattern lies.

    ``epochs``: the per-frame encoder's training epochs.

    ``head_epochs``: the temporal head's training epochs, on the encoder's features.

    ``augment``: the per-frame encoder trains on colour-jittered frames (channel gains,
    brightness and contrast drawn per frame).

    ``input_norm``: how the encoder normalises a frame (`reachwatch.systems.INPUT_NORMS`):
    ``per_frame`` standardises each frame on its own, so its brightness, contrast and
    colour cast do not reach the encoder; ``fixed``: the detector's constant shift and
    scale only.

    ``seed``: the monitors' training seed (initial weights, batch order, jitter); train
    with a few to see how far one training's figures are from the next's.

    ``ensemble``: each variant is that many trainings (seeds ``K * seed`` to ``K * seed
    + K - 1``: studies with other seeds share no member), their raw risks averaged at
    every tick before one calibration and threshold; online one `HistoryMonitor` runs
    the members' encoders as one grouped network (measured: a second member added
    0.6-0.7 ms a tick to the first's 1.5-1.6 ms, docs/results/monitor/2026-12-06.md).

    ``lr_schedule``: ``constant``, or ``cosine`` (each training stage's learning rate
    decays to zero over its steps).

    ``state_targets``: components of the recorded state the per-frame encoder also
    learns to estimate from the frame, a squared error weighted ``state_weight`` beside
    the failure loss (`reachwatch.training.history_train.HistoryTrainConfig`); null:
    the application's ``estimated_state`` (the taxi's ``[0, 2]``, the cross-track error
    and heading TaxiNet estimates); ``[]``: none. Privileged, like the labels: read in
    training only.

    ``state_weight``: the weight of the ``state_targets`` error in the encoder's loss.

    ``weight_average``: the share of each training stage's last epochs whose weights are
    averaged into the trained monitor (stochastic weight averaging,
    `reachwatch.training.history_train.HistoryTrainConfig`); 0: off. One network
    online, whatever the share.

    ``guarded_runs``: starts per judged environment (of the family, and outside it)
    also run in the guarded real loop with the kept variant, the single-frame one and
    the oracle; 0: none.

    ``compare_detector``: judge the run's single-image detector (``detector:``, trained
    on its own labels) beside the variants on the same runs (its score at every tick,
    from runs of the loop alone from the same starts: one more render of every judged
    run), its threshold and flag rule fixed on the calibration environments the same
    way, and guard the loop with it beside them. A run file whose family shares an
    environment with the detector's training ones is refused (give ``family`` another
    ``seed``).

    ``variants``: the monitors to train (`MonitorVariant`), each judged in the report.

    ``keep``: the monitor kept (its checkpoint is written to ``OUT/monitor/`` and,
    with ``guarded_runs``, guards the loop; the bound is stated for it): null, the first
    of ``variants``; a variant's name, that one; ``choose``, the variant and flag rule with the fewest needless flags on the calibration
    environments at their own thresholds. The conformal bound speaks of a monitor fixed
    before the calibration environments are seen, not of one chosen among several on
    them: the choice favours whichever those environments happened to flatter, and its
    miss rate on new environments is higher (measured: [the kept monitor fixed in
    advance](../results/monitor/2026-12-06.md#the-kept-monitor-fixed-in-advance-2026-12-06)).

    ``flag_rules``: the k-of-n rules, ``[flags_needed, flag_window]`` each (the guard's
    `FlagFilter`: flag when at least k of the last n ticks reached the threshold or were
    NaN). With
    ``keep: choose`` each variant keeps the rule with the fewest needless flags on the
    calibration environments, its threshold fixed there too, and its guarded runs use
    it; otherwise list one rule, which every variant uses."""
    kind: str = "detector"
    family: ApplicationRandomEnvironments = slot_field(
        "monitor", application_default(ApplicationRandomEnvironments, "monitor"))
    train: int = bounded(12, 1, 1000, whole=True)
    calibrate: int = bounded(10, 1, 1000, whole=True, note=">= 1 / alpha - 1")
    held_out: int = bounded(6, 1, 1000, whole=True)
    also_held_out: List[ApplicationEnvironment] = slot_field("", list)
    runs: int = bounded(30, 1, 100_000, whole=True)
    held_out_runs: int = bounded(0, 0, 100_000, whole=True, note="0: runs")
    calibration_runs: int = bounded(0, 0, 100_000, whole=True, note="0: as judged")
    duration: float = bounded(8.0, 0.0, 600.0, low_open=True, unit="s")
    within: float = bounded(4.0, 0.0, 600.0, low_open=True, high_open=True, unit="s",
                            note="< duration")
    brake_deceleration: float = bounded_as(3.0, MonitorConfig, "brake_deceleration")
    alpha: float = bounded(0.1, 0.0, 1.0, low_open=True, high_open=True,
                           note=">= 1 / (calibrate + 1)")
    given_failures: bool = False
    height: int = bounded_as(48, HistoryMonitorConfig, "height")
    width: int = bounded_as(80, HistoryMonitorConfig, "width")
    pool: List[int] = bounded_as(None, HistoryMonitorConfig, "pool",
                                 default_factory=lambda: [3, 5])
    epochs: int = bounded(12, 1, 10_000, whole=True)
    head_epochs: int = bounded(40, 1, 100_000, whole=True)
    augment: bool = True
    input_norm: str = "per_frame"
    seed: int = seed_field()
    ensemble: int = bounded(1, 1, MAX_MEMBERS, whole=True)
    lr_schedule: str = "constant"
    state_targets: Optional[List[int]] = None
    state_weight: float = bounded_as(1.0, HistoryTrainConfig, "state_weight")
    weight_average: float = bounded_as(0.0, HistoryTrainConfig, "weight_average")
    guarded_runs: int = bounded(0, 0, 100_000, whole=True)
    compare_detector: bool = True
    variants: List[MonitorVariant] = dc.field(default_factory=default_variants)
    keep: Optional[str] = None
    flag_rules: List[List[int]] = dc.field(default_factory=lambda: [[1, 1]])

    @property
    def enabled(self) -> bool:
        return self.kind == "history"

    @property
    def judged_runs(self) -> int:
        """Runs recorded per judged (held-out) environment: ``held_out_runs``, or
        ``runs`` when that is 0."""
        return self.held_out_runs or self.runs

    @property
    def calibration_environment_runs(self) -> int:
        """Runs recorded per calibration environment: ``calibration_runs``, or
        `judged_runs` when that is 0."""
        return self.calibration_runs or self.judged_runs

    def validate(self, where="monitor"):
        if self.kind not in MONITOR_KINDS:
            raise ValueError(f"{where}.kind must be one of {MONITOR_KINDS}, got {self.kind!r}")
        check_bounds(self, f"{where}.")
        if not isinstance(self.augment, bool):
            raise ValueError(f"{where}.augment must be true or false, got {short(self.augment)}")
        check_input_norm(f"{where}.", self.input_norm)
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"{where}.lr_schedule must be one of {LR_SCHEDULES}, got "
                             f"{short(self.lr_schedule)}")
        if self.state_targets is not None:
            check_state_targets(f"{where}.state_targets", self.state_targets)
        check_pool(f"{where}.", self.pool, self.height, self.width,
                   len(HistoryMonitorConfig().channels))
        if self.within >= self.duration:
            raise ValueError(f"{where}.within ({self.within:g} s) must be shorter than "
                             f"{where}.duration ({self.duration:g} s): a run that does not "
                             f"fail says nothing of its last {self.within:g} s")
        if self.guarded_runs > self.judged_runs:
            raise ValueError(f"{where}.guarded_runs ({self.guarded_runs}) must be at most the "
                             f"runs recorded per held-out environment ({self.judged_runs}: "
                             f"{where}.held_out_runs, or {where}.runs when that is 0)")
        if (self.calibrate + 1) * self.alpha < 1:
            raise ValueError(f"{where}.calibrate: {self.calibrate} environments cannot bound the "
                             f"miss rate at alpha {self.alpha:g} (the bound is at least "
                             f"1/(calibrate+1)); use at least {math.ceil(1 / self.alpha - 1)}")
        if not self.enabled:
            warn_unused_study_keys(self, where)
        if self.enabled and isinstance(self.family, NoRandomEnvironments):
            raise ValueError(f"{where}: the study trains, calibrates and judges on "
                             f"environments drawn from the application's random family, and "
                             f"this application draws none (give it a "
                             f"random_environments_type to run the study)")
        self.family.validate(f"{where}.family")
        count = self.train + self.calibrate + self.held_out
        if self.family.count not in (0, count):
            raise ValueError(f"{where}.family.count is train + calibrate + held_out here "
                             f"({count}); leave it out, got {self.family.count}")
        for i, env in enumerate(self.also_held_out):
            try:
                env.validate()
            except ValueError as e:
                raise ValueError(f"{where}.also_held_out[{i}]: {e}") from None
        named = [e.name for e in self.also_held_out]
        if len(set(named)) != len(named):      # rows by name: one would count twice
            twice = sorted({n for n in named if named.count(n) > 1})
            raise ValueError(f"{where}.also_held_out lists an environment name twice: "
                             f"{short(twice)}")
        rules = [tuple(r) if isinstance(r, (list, tuple)) else (r,) for r in self.flag_rules]
        try:
            if not rules or len(set(rules)) != len(rules) or any(len(r) != 2 for r in rules):
                raise ValueError("a list of [flags_needed, flag_window] pairs, each once")
            for k, n in rules:
                check_k_of_n(k, n)
                if n > MAX_FLAG_WINDOW:
                    raise ValueError(f"flag_window at most {MAX_FLAG_WINDOW} ticks")
        except ValueError as e:
            raise ValueError(f"{where}.flag_rules: {e}, got {short(self.flag_rules)}") from None
        for i, v in enumerate(self.variants):
            check_label(f"{where}.variants[{i}].name", v.name)
        names = [v.name for v in self.variants]
        if not self.variants or len(set(names)) != len(names):
            raise ValueError(f"{where}.variants must list at least one variant, each name "
                             f"once, got {names[:8]}")
        for reserved, what in ((DETECTOR_ROW, "the name of the detector's row"),
                               (ORACLE, "the name of the oracle monitor's row"),
                               (CHOOSE, f"{where}.keep's word for choosing")):
            if reserved in names:
                raise ValueError(f"{where}.variants: {reserved!r} is {what}; call the "
                                 f"variant otherwise")
        if self.keep is not None and self.keep not in (CHOOSE, *names):
            raise ValueError(f"{where}.keep must be null (the first variant), {CHOOSE!r} or "
                             f"a variant's name, got {short(self.keep)}")
        if self.keep != CHOOSE and len(self.flag_rules) > 1:
            raise ValueError(f"{where}.flag_rules lists {len(self.flag_rules)} rules, and the "
                             f"kept monitor is fixed in advance ({where}.keep): list one rule, "
                             f"or set {where}.keep: {CHOOSE} to choose the variant and rule on "
                             f"the calibration environments")
        for i, v in enumerate(self.variants):
            check_bounds(v, f"{where}.variants[{i}].")
            if not isinstance(v.signals, bool):
                raise ValueError(f"{where}.variants[{i}].signals must be true or false, got "
                                 f"{short(v.signals)}")
            if v.temporal not in TEMPORAL_MODELS:
                raise ValueError(f"{where}.variants: {v.name!r} temporal must be one of "
                                 f"{TEMPORAL_MODELS}, got {v.temporal!r}")
            HistoryMonitorConfig(frames=v.frames, stride=v.stride, temporal=v.temporal).validate()
        return self

    @property
    def kept_in_advance(self) -> Optional[str]:
        """The kept variant's name when it is fixed before calibration (``keep`` null or
        a name); None with ``keep: choose``."""
        return None if self.keep == CHOOSE else self.keep or self.variants[0].name

    def environments(self):
        """``{"train", "calibrate", "held_out", "also_held_out"}``: lists of environments."""
        family = dc.replace(self.family, count=self.train + self.calibrate + self.held_out)
        envs = family.environments()
        return {"train": envs[:self.train],
                "calibrate": envs[self.train:self.train + self.calibrate],
                "held_out": envs[self.train + self.calibrate:],
                "also_held_out": list(self.also_held_out)}


def study_lead(spec: MonitorStudySpec, application, scenario, where="monitor") -> float:
    """How far ahead of a failure a warning must come: the application's
    `stopping_time` under the study's braking, checked against the study's timing
    (`check_study_timing`; a one-line error else)."""
    lead = application.stopping_time(scenario, spec.brake_deceleration)
    if isinstance(lead, bool) or not isinstance(lead, (int, float, np.floating, np.integer)) \
            or not (math.isfinite(lead) and lead > 0):
        raise ValueError(f"the application '{application.name}': stopping_time must be a "
                         f"number of seconds > 0, got {lead!r}")
    check_study_timing(spec, float(lead), scenario.controller.period, where)
    return float(lead)


def check_study_timing(spec: MonitorStudySpec, lead: float, period: float, where="monitor"):
    """A ValueError in one line, before any run is recorded, when no failure within the
    study's runs could be warned of ``lead`` s ahead: the lead is not shorter than a
    run, or a k-of-n rule cannot flag before then (its k-th flag comes k - 1 control
    periods into a run at the earliest)."""
    brake = f"braking at {where}.brake_deceleration {spec.brake_deceleration:g} m/s^2"
    if lead >= spec.duration:
        raise ValueError(f"{where}.duration ({spec.duration:g} s) is not longer than the "
                         f"fallback's lead ({lead:g} s: the application's stopping time "
                         f"{brake}): no failure within a run can be warned of in time; "
                         f"lengthen the runs or brake harder")
    for k, n in (tuple(rule) for rule in spec.flag_rules):
        earliest = (k - 1) * period
        if earliest >= spec.duration - lead:
            raise ValueError(f"{where}.flag_rules: [{k}, {n}] flags {k - 1} control periods "
                             f"({earliest:g} s at scenario.controller.period {period:g} s) "
                             f"into a run at the earliest, and a warning must come {lead:g} s "
                             f"before a failure within {where}.duration ({spec.duration:g} "
                             f"s): no run could be warned of; ask fewer flags")
