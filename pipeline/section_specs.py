"""The sections of a run file (`RunSpec`) that configure one stage each: the ensemble
baseline, the incremental stage, the guard, the real-loop fidelity check, refinement,
the robust BRT and the choice of map, with the bounds of a run file's sizes."""

import dataclasses as dc
from typing import List, Optional

from reachwatch.diagrams.schemas import ApplicationEnvironment, slot_field
from reachwatch.systems import DEFAULT_FALLBACKS, Fallback
from reachwatch.systems.bounds import MAX_INT, bounded, check_bounds, seed_field
from reachwatch.systems.checks import short, warn_once

from .slot_defaults import application_default

#: Bounds of a run file's sizes: nodes per grid axis, horizon (s), real-loop starts.
MAX_GRID = 401
MAX_HORIZON = 120.0
MAX_STARTS = 1_000_000


@dc.dataclass
class EnsembleSpec:
    """The ensemble-variance baseline: TaxiNets differing only in their seed."""
    seeds: List[int] = bounded(default_factory=lambda: [1, 2, 3, 4, 5], low=0, high=MAX_INT,
                               whole=True, each=True, items=(0, 32),
                               note="none, or 2 or more different seeds")
    samples: int = bounded(4000, 1, 1_000_000, whole=True)
    epochs: int = bounded(400, 1, 100_000, whole=True)


@dc.dataclass
class IncrementalConfig:
    """What to mine, how much nominal data to replay, how long to fine-tune, and the
    held-out ``environment`` whose BRT is recomputed with the fine-tuned controller (the
    incremental stage: the application's ``fine_tune``; the taxi's fine-tunes TaxiNet,
    `reachwatch.taxi.incremental`)."""
    enabled: bool = True
    environment: ApplicationEnvironment = slot_field(
        "incremental", application_default(ApplicationEnvironment, "incremental"))
    #: At most this many mined states (spread over datasets); at least one where the
    #: stage runs: it fine-tunes on them.
    anomalies: int = bounded(2000, 0, 1_000_000, whole=True)
    #: Nominal-condition (KMWH 9 h clear) frames replayed.
    replay: int = bounded(2000, 0, 1_000_000, whole=True)
    epochs: int = bounded(60, 1, 100_000, whole=True)
    batch_size: int = bounded(256, 1, 65_536, whole=True)
    learning_rate: float = bounded(3e-4, 0.0, 10.0, low_open=True)
    seed: int = seed_field()

    def validate(self):
        self.environment.validate()
        check_bounds(self, "incremental.")
        if self.enabled and self.anomalies < 1:
            raise ValueError("incremental.anomalies must be at least 1 while the stage "
                             "runs (it fine-tunes on the states it mines), got 0; or set "
                             "incremental: {enabled: false}")
        return self


@dc.dataclass
class GuardSpec:
    """The guarded loop on held-out environments: for each fallback, failure sets and
    liveness from the swept tables over the grid, a trade-off curve over detector
    thresholds, and the same figures from seeded random starts in the real Drake loops.

    Keys:

    ``environments``: the environments guarded; empty: the first test one.

    ``strategies``: the fallbacks, each a speed strategy, optionally ``+`` a steering
    while flagged (e.g. ``slow_down+dead_reckoning``).

    ``candidates``: table-chosen starts tried in the real loops for the showcase run.

    ``online_seconds``: simulated seconds per round of the online rate.

    ``meshcat_html``: the showcase run with a Meshcat replay beside its figure, where
    the application writes one (the taxi does, the generic
    `Application.simulate_guarded` does not).

    ``check_starts``: seeded random on-runway starts run in the real loops, each one
    real run alone and one per fallback; 0: no real-loop check.

    ``check_seed``: the seed of those starts.

    ``tradeoff_points``: detector thresholds on the trade-off curve.

    ``mission_limit``: the failure sets are also judged by distance: failures before
    covering the distance the controller alone covers within the horizon, the runs
    going on for up to this many horizons (a slower aircraft otherwise fails later,
    past the horizon, on the same path).

    ``noise_starts``: real runs of the controller alone on which the detector's
    variation between grid nodes is fitted, so that the real-loop check also shows the
    tables with it (`reach.score_noise`); 0: not fitted.

    ``noise_seed``: the seed of those runs.

    ``flag_budget``: null: the detector's threshold from training. Else the threshold
    per guard environment, set without labels to the one at which the first of
    ``strategies`` flags this share of its control ticks in the tables (with the score
    noise when ``noise_starts`` fits it; `Application.flag_budget_threshold`).

    ``flag_budget_starts``: the application's starts those tables are rolled out from.

    ``flag_budget_seed``: the seed of those starts."""
    environments: List[ApplicationEnvironment] = slot_field("", list)
    strategies: List[str] = dc.field(default_factory=lambda: list(DEFAULT_FALLBACKS))
    candidates: int = bounded(5, 0, MAX_STARTS, whole=True)
    online_seconds: float = bounded(2.0, 0.0, 3600.0, low_open=True, unit="s")
    meshcat_html: bool = True
    check_starts: int = bounded(200, 0, MAX_STARTS, whole=True)
    check_seed: int = seed_field(2000)
    tradeoff_points: int = bounded(9, 0, MAX_STARTS, whole=True)
    mission_limit: float = bounded(3.0, 1.0, 100.0, unit="horizons")
    noise_starts: int = bounded(20, 0, MAX_STARTS, whole=True)
    noise_seed: int = seed_field(4000)
    flag_budget: Optional[float] = bounded(None, 0.0, 1.0, low_open=True, high_open=True)
    flag_budget_starts: int = bounded(600, 1, MAX_STARTS, whole=True)
    flag_budget_seed: int = seed_field(7000)

    def validate(self, trained_names=frozenset()):
        """Raise ValueError naming the first bad field; ``strategies`` rewritten to one
        name per fallback; a guard environment among ``trained_names`` (the run's
        training environments) warned of. Returns self."""
        check_bounds(self, "guard.")
        # one name per fallback ('slow_down', 'slow_down+controller', 'slow_down+taxinet'
        # are one), so that one fallback has one key, one report row and one set of runs
        named, strategies = list(self.strategies), []
        for i, name in enumerate(named):
            try:
                strategies.append(Fallback.parse(name).name)
            except ValueError as e:
                raise ValueError(f"guard.strategies[{i}]: {e}") from None
        self.strategies = strategies
        if len(set(self.strategies)) != len(self.strategies):
            raise ValueError(f"guard.strategies: each fallback once, got {named}")
        if self.flag_budget is not None and not self.strategies:
            raise ValueError("guard.flag_budget: the budget is set on the first of "
                             "guard.strategies, and there are none")
        for i, env in enumerate(self.environments):
            if env.name in trained_names:
                warn_once(f"guard.environments[{i}]: {short(env.name)} is a training "
                          f"environment: the detector has seen its images, so the guard's "
                          f"figures there are better than on a held-out one")
            try:
                env.validate()
            except ValueError as e:
                raise ValueError(f"guard.environments[{i}]: {e}") from None
        return self


@dc.dataclass
class FidelitySpec:
    """The check of every environment against the real Drake loop: ``starts`` seeded
    uniform on-runway starts each (0 = no check; each costs up to horizon / period
    renders), and the share of real runs leaving the solved box above which BRT
    labels are refused (``max_box_exits``).

    ``more_starts`` (0 = never): where the first ``starts`` runs find the BRT or the
    labels wrong at least once, or where the hybrid labels' audit (runs of its own)
    distrusted the map, the check goes on to this many starts (the same seeded draw,
    so the first ``starts`` are the same runs), putting the renders where the verdicts
    are in doubt: a narrow interval where the map errs (at night), ``starts`` runs
    where it does not. An extension chosen by the first runs leans the environment's
    rates slightly towards error (one chosen by the audit does not); the report says
    which environments were extended, and why."""
    starts: int = bounded(50, 0, MAX_STARTS, whole=True)
    seed: int = seed_field(1000)
    max_box_exits: float = bounded(0.05, 0.0, 1.0)
    more_starts: int = bounded(0, 0, MAX_STARTS, whole=True, note="0 or above starts")

    def key(self) -> dict:
        """What the fidelity stage's key reads: every field, ``more_starts`` only when
        set (adding it moved no existing check), and then the rule that extends (which
        has grown since: a check from before it is run again)."""
        fields = dc.asdict(self)
        if not self.more_starts:
            fields.pop("more_starts")
        else:
            fields["extend_where"] = "a wrong verdict, or a map the audit distrusted"
        return fields


@dc.dataclass
class RefineSpec:
    """Adaptive refinement of every environment's swept table before its BRT is
    solved (`reach.refine`): ``levels`` times (0 = none) halve the grid spacing and
    render the new nodes only in the cells where the BRT's boundary passes within
    ``band`` m or the steering varies by more than ``variation_deg`` across the cell
    (None: the band alone)."""
    levels: int = bounded(0, 0, 5, whole=True)
    band: float = bounded(2.0, 0.0, 1000.0, unit="m")
    variation_deg: Optional[float] = bounded(None, 0.0, low_open=True, unit="deg")

    def validate(self):
        return check_bounds(self, "refine.")


@dc.dataclass
class RobustSpec:
    """A robust BRT for every environment (`reach.robust`): where the swept steering
    ranges over more than ``min_spread_deg`` across the ``neighbourhood`` nodes around a
    node (None = off), the solver lets it take the worst value in that range
    (`solve_brt`'s ``control_bounds``), since its interpolation there says little about
    the controller between the nodes."""
    min_spread_deg: Optional[float] = bounded(None, 0.0, unit="deg")
    neighbourhood: int = bounded(3, 3, 21, whole=True, unit="nodes", note="odd")

    @property
    def enabled(self) -> bool:
        return self.min_spread_deg is not None

    def validate(self):
        check_bounds(self, "robust.")
        if self.neighbourhood % 2 == 0:
            raise ValueError(f"robust.neighbourhood must be an odd whole number of nodes, got "
                             f"{self.neighbourhood!r}")


@dc.dataclass
class MapSelectionSpec:
    """Each environment's BRT map chosen by real-loop runs (`reach.select_map`). With
    ``starts`` > 0, every refinement level (0 to ``refine.levels``) is solved as
    ``robust`` says and again robustly with each spread of ``robust_spreads_deg``; the
    real loop runs from ``starts`` seeded on-runway starts (``seed``, not the fidelity
    check's, so the check judges the kept map on runs the choice never saw); and the
    map with the fewest false-unsafe + ``false_safe_weight`` x false-safe verdicts
    there is kept (ties: fewer false-safe, then fewer renders). 0 starts: off, the last
    level is kept."""
    starts: int = bounded(0, 0, MAX_STARTS, whole=True)
    seed: int = seed_field(2000)
    robust_spreads_deg: List[float] = bounded(default_factory=list, low=0.0, high=360.0,
                                              unit="deg", each=True, items=(0, 16))
    false_safe_weight: float = bounded(2.0, 1.0, 1000.0)

    def validate(self):
        return check_bounds(self, "map_selection.")
