"""`RunSpec`: everything ``reachwatch run`` does, as one YAML file (loaded with
`pydrake.common.yaml`; an unknown or mistyped field is reported by its full path,
e.g. ``run.detector.epoch: unknown field``)."""

import dataclasses as dc
import functools
import re
from typing import Dict, List, Optional

from reachwatch.diagrams import Scenario, load_scenario
from reachwatch.diagrams.scenario import dump_scenario
from reachwatch.diagrams.schemas import (ApplicationEnvironment, ApplicationRandomEnvironments,
                                         slot_field, typed_schema)
from reachwatch.reach import ACCURACIES
from reachwatch.reach.application import load_application
from reachwatch.systems import Fallback
from reachwatch.systems.bounds import bounded, check_bounds
from reachwatch.systems.checks import check_label, short, warn_once
from reachwatch.training.dataset import DatasetSpec
from reachwatch.training.labels import LabelSpec
from reachwatch.training.detector_train import DetectorTrainConfig

from .monitor_spec import (MONITOR_KINDS, MonitorStudySpec, MonitorVariant,  # noqa: F401
                           default_variants, study_lead)
from .section_specs import (MAX_GRID, MAX_HORIZON, MAX_STARTS, EnsembleSpec,  # noqa: F401
                            FidelitySpec, GuardSpec, IncrementalConfig, MapSelectionSpec,
                            RefineSpec, RobustSpec)
from .slot_defaults import DEFAULT_APPLICATION, SlotDefaults, application_default


@dc.dataclass
class RunSpec:
    """A whole study: the environments, the swept and solved grids, the labels and the
    detector, and each stage's section.

    Keys:

    ``name``: the run's name (reports and logs).

    ``application``: the closed loop studied (`reachwatch.reach.application`), named
    like a controller factory (``package.module:name`` or ``path/to/file.py:name``: an
    ``Application`` subclass or a function of no arguments returning one); left out or
    empty: the taxi (``reachwatch.taxi.application:TaxiApplication``).

    ``scenario``: camera, controller and fallback settings (its environment and start
    are ignored).

    ``train``: the training environments, of the application's own type
    (`Application.environment_type`; the taxi's `Environment`: a runway, hour and sky).

    ``test``: the held-out environments, of the same type.

    ``train_random``: a family of random environments (the application's; the taxi's
    `RandomEnvironments`) added to ``train``.

    ``test_random``: a family added to ``test``; it needs a seed of its own.

    ``grid``: the swept and solved grid, one size per axis of the application's box
    (the taxi's: ``[n_px, n_py, n_theta]`` over the paper's box).

    ``horizon``: the BRT's horizon, s.

    ``accuracy``: the BRT solver (`reach.ACCURACIES`): ``semi_lagrangian``, or a
    level-set scheme ``low``, ``high``, ``very_high``.

    ``periods_per_step``: control periods per step of the ``semi_lagrangian`` solver;
    each step interpolates V once, so fewer, longer steps blur it less (the default
    against 4: [ground truth](../results/ground-truth.md)).

    ``solved_theta_deg``: widens the box the tables are swept and the BRT solved over
    to abs(theta) <= this (the loop turns far past the paper's 28 deg at night);
    labelled states and check starts stay in the paper's box.

    ``solved_py_max``: widens that box to py <= this, m (a loop started near py = 250 m
    goes on past it within the horizon).

    ``slice_py``: the along-runway position, m, of the figures' slices through the grid.
    These three are the taxi's; an application that does not read one (its
    ``reads_keys``) refuses a run file that sets it.

    ``dataset``: the detector's data set per environment (`DatasetSpec`).

    ``held_out_labels``: where the held-out environments' labels come from; null:
    ``dataset.labels``, as the training environments'. The detector trains on
    ``dataset.labels`` either way; a true-label source here (e.g. ``hybrid``) scores a
    detector trained on cheap BRT labels against the real loop, and Table 2 then also
    scores it against the BRT's verdicts on the same states.

    ``detector``: the single-image detector's training (`DetectorTrainConfig`).

    ``ensemble``: the ensemble-variance baseline (`EnsembleSpec`).

    ``guard``: the guarded loop on held-out environments (`GuardSpec`).

    ``fidelity``: the check of every environment against the real loop (`FidelitySpec`).

    ``refine``: adaptive refinement of the swept tables (`RefineSpec`).

    ``robust``: the robust BRT (`RobustSpec`).

    ``map_selection``: each environment's BRT map chosen by real-loop runs
    (`MapSelectionSpec`).

    ``incremental``: the incremental stage (`IncrementalConfig`).

    ``monitor``: the monitor study over the image history (`MonitorStudySpec`; the
    guard stage guards with ``detector:``'s single-image detector)."""
    name: str = "run"
    application: str = DEFAULT_APPLICATION
    scenario: Scenario = dc.field(default_factory=Scenario)
    train: List[ApplicationEnvironment] = slot_field("", list)
    test: List[ApplicationEnvironment] = slot_field("", list)
    train_random: ApplicationRandomEnvironments = slot_field(
        "train", application_default(ApplicationRandomEnvironments, "train"))
    test_random: ApplicationRandomEnvironments = slot_field(
        "test", application_default(ApplicationRandomEnvironments, "test"))
    grid: List[int] = bounded(default_factory=lambda: [21, 11, 21], low=3, high=MAX_GRID,
                              whole=True, each=True, note="one size per state axis")
    horizon: float = bounded(8.0, 0.0, MAX_HORIZON, low_open=True, unit="s")
    accuracy: str = "semi_lagrangian"
    periods_per_step: int = bounded(40, 1, 10_000, whole=True)
    solved_theta_deg: float = bounded(28.0, 28.0, 180.0, unit="deg")
    solved_py_max: float = bounded(250.0, 250.0, 10_000.0, unit="m")
    slice_py: float = bounded(175.0, 0.0, unit="m", note="<= solved_py_max")
    dataset: DatasetSpec = dc.field(default_factory=DatasetSpec)
    held_out_labels: Optional[LabelSpec] = None
    detector: DetectorTrainConfig = dc.field(default_factory=DetectorTrainConfig)
    ensemble: EnsembleSpec = dc.field(default_factory=EnsembleSpec)
    guard: GuardSpec = dc.field(default_factory=GuardSpec)
    fidelity: FidelitySpec = dc.field(default_factory=FidelitySpec)
    refine: RefineSpec = dc.field(default_factory=RefineSpec)
    robust: RobustSpec = dc.field(default_factory=RobustSpec)
    map_selection: MapSelectionSpec = dc.field(default_factory=MapSelectionSpec)
    incremental: IncrementalConfig = dc.field(default_factory=IncrementalConfig)
    monitor: MonitorStudySpec = dc.field(default_factory=MonitorStudySpec)

    def validate(self):
        """Raise ValueError naming the first bad field; return self."""
        try:
            self.scenario.validate()
        except ValueError as e:     # its fields' paths from the run file's top (a run
            e.args = (scenario_path(e),)    # file has a monitor: too); its type kept
            raise
        unread = self.scenario.single_run_settings()
        if unread:
            warn_once(f"scenario.{', scenario.'.join(unread)}: a single run's (reachwatch "
                      f"simulate); a run's stages set their own starts, durations and seeds "
                      f"and do not read {'it' if len(unread) == 1 else 'them'}")
        check_label("name", self.name)
        check_bounds(self)
        self.application = self.application or DEFAULT_APPLICATION
        application = load_application(self.application)    # a bad name fails before any work
        self.train_random.validate("train_random")
        self.test_random.validate("test_random")
        if not self.train and not self.train_random.count:
            raise ValueError("train: list at least one training environment (or ask for "
                             "train_random: {count: N})")
        if not self.test and not self.test_random.count:
            raise ValueError("test: list at least one held-out environment (or ask for "
                             "test_random: {count: N})")
        for where in ("train", "test"):
            for i, env in enumerate(getattr(self, where)):
                try:
                    env.validate()
                except ValueError as e:
                    raise ValueError(f"{where}[{i}]: {e}") from None
        self._check_same_names(application)
        names = [e.name for e in self.training_environments() + self.held_out_environments()]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            seeds = [getattr(f, "seed", None) for f in (self.train_random, self.test_random)]
            drawn = {e.name for e in self.train_random.environments()} & {
                e.name for e in self.test_random.environments()}
            if drawn and seeds[0] is not None and seeds[0] == seeds[1]:
                raise ValueError(f"test_random.seed is train_random.seed ({seeds[0]}): one "
                                 f"seed draws the same environments, so the held-out ones "
                                 f"would be trained on; give test_random a seed of its own")
            raise ValueError(f"train/test: an environment is listed twice: {short(twice)}")
        # one under another name (a family drawn again under another prefix)
        trained = self._trained_contents(application)
        for env in self.held_out_environments():
            if application.environment_content(env) in trained:
                raise ValueError(
                    f"test: {short(env.name)} is also a training environment "
                    f"({short(trained[application.environment_content(env)])}): a family "
                    f"drawn from the same seed is the same family whatever its prefix; hold "
                    f"out another, or give test_random another seed")
        axes = application.axes
        if len(self.grid) != len(axes):             # each size: check_bounds above
            raise ValueError(f"grid must be {len(axes)} sizes [{', '.join('n_' + a for a in axes)}], "
                             f"each >= 3 and <= {MAX_GRID}, got {short(self.grid)}")
        if self.accuracy not in ACCURACIES:
            raise ValueError(f"accuracy must be one of {sorted(ACCURACIES)}, got "
                             f"'{self.accuracy}'")
        self.refine.validate()
        self.robust.validate()
        self.map_selection.validate()
        if self.map_selection.starts and self.map_selection.seed == self.fidelity.seed:
            raise ValueError(f"map_selection.seed {self.map_selection.seed} equals "
                             f"fidelity.seed: the check would judge the map on the runs that "
                             f"chose it; give the selection another seed")
        for key in ("solved_theta_deg", "solved_py_max", "slice_py"):
            if key not in application.reads_keys and getattr(self, key) != getattr(RunSpec, key):
                raise ValueError(f"{key}: the application '{application.name}' does not read "
                                 f"it (its reads_keys); leave it out")
        if not self.slice_py <= self.solved_py_max:
            raise ValueError(f"slice_py must be a number of metres in [0, solved_py_max "
                             f"{self.solved_py_max:g}], got {self.slice_py!r}")
        self.dataset.validate()
        self.monitor.validate()
        if self.held_out_labels is not None:
            self.held_out_labels.validate("held_out_labels")
        self.detector.validate()
        n_train = len(self.train) + self.train_random.count
        if self.detector.threshold_folds > n_train:
            raise ValueError(f"detector.threshold_folds {self.detector.threshold_folds}: there "
                             f"are only {n_train} training environments to leave out")
        check_bounds(self.ensemble, "ensemble.")
        if len(set(self.ensemble.seeds)) != len(self.ensemble.seeds):
            raise ValueError(f"ensemble.seeds must list different seeds, got "
                             f"{short(self.ensemble.seeds)}")
        self.guard.validate({e.name for e in self.training_environments()})
        check_bounds(self.fidelity, "fidelity.")
        period = self.scenario.controller.period
        for where, seconds in (("horizon", self.horizon),
                               ("guard.online_seconds", self.guard.online_seconds)):
            if seconds < period:
                raise ValueError(f"{where} ({seconds:g} s) must be at least one control period "
                                 f"(scenario.controller.period {period:g} s): within a shorter "
                                 f"one the controller never acts")
        more = self.fidelity.more_starts
        if more and more <= self.fidelity.starts:
            raise ValueError(f"fidelity.more_starts must be 0 (never extend the check) or a "
                             f"whole number above fidelity.starts ({self.fidelity.starts}), "
                             f"got {more!r}")
        if [self.dataset.height, self.dataset.width] != [self.detector.detector.height,
                                                         self.detector.detector.width]:
            raise ValueError(f"dataset image size {[self.dataset.height, self.dataset.width]} "
                             f"must equal the detector input size "
                             f"{[self.detector.detector.height, self.detector.detector.width]}")
        if self.ensemble.seeds and not application.has_ensemble():
            if self.ensemble.seeds != EnsembleSpec().seeds:
                raise ValueError(f"ensemble.seeds: the application '{application.name}' has no "
                                 f"ensemble baseline (it defines no ensemble_config); set "
                                 f"ensemble.seeds: []")
            self.ensemble.seeds = []     # the default: none where the application has none
        if len(self.ensemble.seeds) == 1:
            raise ValueError("ensemble.seeds: an ensemble needs >= 2 seeds (or [] for none)")
        if self.guard_environments() and not self.default_strategies():
            # the default is fitted to the application and controller when a run
            # starts (`pipeline.run.fit_guard`)
            application.check_guard(self.scenario, self.guard.strategies)
        self.incremental.validate()
        if self.incremental.enabled:
            application.check_incremental(self.scenario)
            name = self.incremental.environment.name
            if name in {e.name for e in self.training_environments()}:
                raise ValueError(f"incremental.environment {short(name)} is a training "
                                 f"environment; the fine-tuned controller is judged on a "
                                 f"held-out one: name another")
        if self.monitor.enabled:       # its lead and flag rules can warn within its runs
            study_lead(self.monitor, application, application.resolved(self.scenario))
        targets = self.monitor.state_targets
        if self.monitor.enabled and targets and max(targets) >= len(application.axes):
            raise ValueError(f"monitor.state_targets: {max(targets)} is no axis of the state, "
                             f"which has {len(application.axes)} "
                             f"({', '.join(application.axes)})")
        if self.monitor.enabled and self.monitor.compare_detector:
            seen = sorted({e.name for role, envs in self.monitor.environments().items()
                           if role != "train" for e in envs
                           if application.environment_content(e) in trained})
            if seen:
                raise ValueError(f"monitor: the study would judge the detector on "
                                 f"environments it trained on ({short(seen)}); give "
                                 f"monitor.family another seed, or train on others")
        return self

    def _trained_contents(self, application) -> dict:
        """``{content: name}`` of the training environments
        (`Application.environment_content`: an environment by what the loop sees, its
        name aside)."""
        return {application.environment_content(e): e.name
                for e in self.training_environments()}

    def _check_same_names(self, application):
        """Raise a ValueError naming both places when two environments of the run share
        a name but differ (`Application.same_environment`: their files and stage records
        would be mixed up)."""
        places = [(f"train[{i}]", e) for i, e in enumerate(self.train)]
        places += [(f"test[{i}]", e) for i, e in enumerate(self.test)]
        places += [(f"train_random ({e.name})", e) for e in self.train_random.environments()]
        places += [(f"test_random ({e.name})", e) for e in self.test_random.environments()]
        places += [(f"guard.environments[{i}]", e) for i, e in enumerate(self.guard.environments)]
        if self.incremental.enabled:
            places.append(("incremental.environment", self.incremental.environment))
        first = {}
        for where, env in places:
            try:
                env.validate()
            except ValueError as e:
                raise ValueError(f"{where}: {e}") from None
            if env.name not in first:
                first[env.name] = (where, env)
            elif not application.same_environment(first[env.name][1], env):
                raise ValueError(f"{first[env.name][0]} and {where} are both named "
                                 f"'{env.name}' but differ; give one of them another name")

    def training_environments(self) -> List[ApplicationEnvironment]:
        """``train``, then the ``train_random`` family."""
        return list(self.train) + self.train_random.environments()

    def held_out_environments(self) -> List[ApplicationEnvironment]:
        """``test``, then the ``test_random`` family (never trained on)."""
        return list(self.test) + self.test_random.environments()

    def held_out_groups(self) -> Dict[str, List[str]]:
        """Names of the held-out environments by where they come from: ``"listed"``
        (``test``) and ``"random, seed S"`` (``test_random``); empty groups left out."""
        groups = {"listed": [e.name for e in self.test],
                  f"random, seed {self.test_random.seed}":
                      [e.name for e in self.test_random.environments()]}
        return {name: names for name, names in groups.items() if names}

    def dataset_spec_for(self, env) -> DatasetSpec:
        """The `DatasetSpec` of ``env``'s dataset: ``dataset``, with ``held_out_labels``
        for a held-out environment when it is set."""
        if self.held_out_labels is None or env.name not in {
                e.name for e in self.held_out_environments()}:
            return self.dataset
        return dc.replace(self.dataset, labels=self.held_out_labels)

    def default_strategies(self) -> bool:
        """Whether ``guard.strategies`` are the default (`systems.DEFAULT_FALLBACKS`), not
        a list the run file names: those a run fits to its application and controller."""
        from reachwatch.systems import DEFAULT_FALLBACKS
        return self.guard.strategies == [Fallback.parse(name).name for name in DEFAULT_FALLBACKS]

    def guard_environments(self) -> List[ApplicationEnvironment]:
        return self.guard.environments or self.held_out_environments()[:1]

    def all_environments(self) -> List[ApplicationEnvironment]:
        """Every environment whose BRT a run needs: train, test, guard and incremental,
        each once, in that order."""
        envs, seen = [], set()
        extra = self.guard_environments() + (
            [self.incremental.environment] if self.incremental.enabled else [])
        for env in self.training_environments() + self.held_out_environments() + extra:
            if env.name not in seen:
                seen.add(env.name)
                envs.append(env)
        return envs

    @classmethod
    def schema_for(cls, raw) -> type:
        """The schema a run file's data ``raw`` is loaded with: this one with the
        environments of the application it names (`run_file_schema`)."""
        name = raw.get("application") if isinstance(raw, dict) else None
        return run_file_schema(load_application(name if isinstance(name, str) and name
                                                else DEFAULT_APPLICATION))


@functools.lru_cache(maxsize=None)
def run_file_schema(application) -> type:
    """`RunSpec` whose environments and random families are ``application``'s
    (`Application.run_file_types`; `reachwatch.diagrams.schemas.typed_schema`)."""
    environment, family = application.run_file_types()
    return typed_schema(RunSpec, ((ApplicationEnvironment, environment),
                                  (ApplicationRandomEnvironments, family)),
                        SlotDefaults(application))


def load_run_spec(filename=None, *, data=None) -> RunSpec:
    """Load and validate a run specification (YAML file or string)."""
    return load_scenario(filename, data=data, schema=RunSpec, root="run")


def dump_run_spec(spec: RunSpec) -> str:
    """YAML text of ``spec`` (round-trips through `load_run_spec`)."""
    return dump_scenario(spec)      # as `RunSpec.schema_for` its application


def scenario_path(error: ValueError) -> str:
    """A scenario's validation message as a run file's: a field path it begins with
    (``monitor.threshold ...``) from the run file's top (``scenario.monitor.threshold
    ...``), anything else after ``scenario: ``."""
    text = str(error)
    first = re.match(r"[A-Za-z_]+", text)
    if first and first.group() in {f.name for f in dc.fields(Scenario)}:
        return f"scenario.{text}"
    return f"scenario: {text}"
