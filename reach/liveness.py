"""Safety and liveness of a guarded loop side by side.

A runtime monitor is judged by two columns: the failures it avoids and the missions it
still completes. A fallback that stops the vehicle everywhere empties the failure set
and completes nothing, so every failure figure here comes with its liveness figures,
computed from the same starts for the controller alone and for the guarded loop."""

import dataclasses as dc

import numpy as np

from .fidelity import wilson_interval

#: The key of the controller alone (no detector, no fallback) among the outcomes of
#: each fallback.
UNGUARDED = "unguarded"

#: The per-start fields of `MissionOutcomes` (all arrays of one length).
MISSION_FIELDS = ("failed", "stopped", "ever_stopped", "distance", "flagged_ticks", "ticks")
#: Its optional fields, judged by distance instead of time (see `MissionOutcomes`).
SAME_DISTANCE_FIELDS = ("failed_same_distance", "short_of_distance")


@dc.dataclass
class MissionOutcomes:
    """Per start: ``failed`` (left the safe set within the horizon), ``stopped`` (ended
    the horizon at standstill without failing), ``ever_stopped`` (was at standstill at
    some tick before it ended or failed), ``distance`` (m travelled until the end or the
    failure), ``flagged_ticks`` and ``ticks`` (control ticks flagged by the detector,
    and all control ticks, until the end or the failure).

    A fallback that only slows down leaves the path of a loop whose turn rate scales
    with speed (a car, the taxiing aircraft) as it was and only delays the failure,
    past the horizon if it slows enough. So the optional fields judge the mission by
    distance instead of time, the run going on past the horizon until it has covered
    the distance the controller alone covers within it: ``failed_same_distance`` (left
    the safe set before covering it) and ``short_of_distance`` (neither failed nor
    covered it before the run's time limit: parked or crawling). Both or neither."""
    failed: np.ndarray
    stopped: np.ndarray
    ever_stopped: np.ndarray
    distance: np.ndarray
    flagged_ticks: np.ndarray
    ticks: np.ndarray
    failed_same_distance: np.ndarray = None
    short_of_distance: np.ndarray = None

    def __post_init__(self):
        given = [name for name in SAME_DISTANCE_FIELDS if getattr(self, name) is not None]
        if given and len(given) != len(SAME_DISTANCE_FIELDS):
            raise ValueError(f"MissionOutcomes: give both {SAME_DISTANCE_FIELDS} or neither, "
                             f"got only {given}")
        fields = MISSION_FIELDS + tuple(given)
        for name in fields:
            setattr(self, name, np.asarray(getattr(self, name)).reshape(-1))
        n = {len(getattr(self, name)) for name in fields}
        if len(n) != 1 or n == {0}:
            raise ValueError(f"MissionOutcomes: every field needs the same number (> 0) of "
                             f"starts, got {[len(getattr(self, f)) for f in fields]}")
        for name in ("failed", "stopped", "ever_stopped", *given):
            setattr(self, name, getattr(self, name).astype(bool))
        if np.any(self.stopped & self.failed):
            raise ValueError("MissionOutcomes: a start cannot both fail and end stopped")
        if given and np.any(self.failed_same_distance & self.short_of_distance):
            raise ValueError("MissionOutcomes: a start cannot both fail and fall short of "
                             "the distance")

    @property
    def has_same_distance(self) -> bool:
        return self.failed_same_distance is not None

    def __len__(self):
        return len(self.failed)

    @classmethod
    def from_fields(cls, fields: dict) -> "MissionOutcomes":
        missing = [name for name in MISSION_FIELDS if name not in fields]
        if missing:
            raise ValueError(f"MissionOutcomes: missing fields {missing}")
        return cls(**{name: fields[name] for name in MISSION_FIELDS + SAME_DISTANCE_FIELDS
                      if name in fields})

    def as_fields(self) -> dict:
        names = MISSION_FIELDS + (SAME_DISTANCE_FIELDS if self.has_same_distance else ())
        return {name: getattr(self, name) for name in names}


def check_mission_limit(value) -> float:
    """``value`` as a float, or a clear error: a mission limit is a multiple of the
    horizon, at least 1."""
    try:
        limit = float(value)
    except (TypeError, ValueError):
        limit = float("nan")
    if not (np.isfinite(limit) and limit >= 1):
        raise ValueError(f"mission_limit is a multiple of the horizon >= 1, got {value!r}")
    return limit


def _rate(mask):
    count, n = int(np.sum(mask)), int(np.size(mask))
    if n == 0:
        return {"count": 0, "of": 0, "rate": None, "ci95": None}
    return {"count": count, "of": n, "rate": count / n, "ci95": list(wilson_interval(count, n))}


def liveness_figures(alone: MissionOutcomes, guarded: MissionOutcomes) -> dict:
    """The figures of a guarded loop against the controller alone from the same starts.

    - ``failure_set`` / ``alone_failure_set``: share of starts that fail (Wilson 95 %);
      ``failure_cut``: 1 - guarded / alone (None when the controller alone never fails);
    - ``ended_stopped``, ``ever_stopped``: share of all starts;
    - ``needless_stops``: of the starts the controller alone survives, the share the
      guarded loop ends stopped (an intervention that cost the mission for nothing);
    - ``harmed``: of those starts, the share the guarded loop makes fail;
    - ``saved`` / ``saved_moving``: of the starts the controller alone fails, the share
      the guarded loop survives / survives without ending stopped;
    - ``distance_ratio``: mean distance travelled, guarded over alone;
    - ``flagged_ticks``: share of all control ticks the detector flagged;
    - when both carry the same-distance fields: ``same_distance_failure_set`` (share of
      starts that fail before covering the distance the controller alone covers in the
      horizon), ``same_distance_failure_cut`` (1 - guarded / alone, by that measure) and
      ``short_of_distance`` (share that neither fails nor covers it: missions lost);
    - ``failed_at_start``: share of starts outside the safe set already (failed before
      their first tick, as grid nodes off the runway do): no fallback can save them, yet
      they count in every failure set, so ``failure_cut_inside`` (and
      ``same_distance_failure_cut_inside``) give the cut over the other starts, and
      ``saved_inside`` / ``saved_moving_inside`` the saves of those the controller alone
      fails."""
    if len(alone) != len(guarded):
        raise ValueError(f"liveness_figures: {len(alone)} starts alone but {len(guarded)} "
                         f"guarded; both must come from the same starts")
    survives, fails = ~alone.failed, alone.failed
    alone_mean = float(np.mean(alone.distance))
    ticks = int(np.sum(guarded.ticks))
    out = {"starts": len(alone),
           "failure_set": _rate(guarded.failed),
           "alone_failure_set": _rate(alone.failed),
           "failure_cut": _cut(alone.failed, guarded.failed),
           "ended_stopped": _rate(guarded.stopped),
           "ever_stopped": _rate(guarded.ever_stopped),
           "needless_stops": _rate(guarded.stopped[survives]),
           "harmed": _rate(guarded.failed[survives]),
           "saved": _rate(~guarded.failed[fails]),
           "saved_moving": _rate((~guarded.failed & ~guarded.stopped)[fails]),
           "distance_ratio": float(np.mean(guarded.distance)) / alone_mean if alone_mean > 0 else None,
           "flagged_ticks": int(np.sum(guarded.flagged_ticks)) / ticks if ticks else None}
    at_start = alone.failed & guarded.failed & (alone.ticks == 0) & (guarded.ticks == 0)
    savable = fails & ~at_start
    out.update(failed_at_start=_rate(at_start),
               failure_cut_inside=_cut(alone.failed[~at_start], guarded.failed[~at_start]),
               saved_inside=_rate(~guarded.failed[savable]),
               saved_moving_inside=_rate((~guarded.failed & ~guarded.stopped)[savable]))
    if alone.has_same_distance and guarded.has_same_distance:
        out.update(same_distance_failure_set=_rate(guarded.failed_same_distance),
                   alone_same_distance_failure_set=_rate(alone.failed_same_distance),
                   same_distance_failure_cut=_cut(alone.failed_same_distance,
                                                  guarded.failed_same_distance),
                   short_of_distance=_rate(guarded.short_of_distance),
                   same_distance_failure_cut_inside=_cut(alone.failed_same_distance[~at_start],
                                                         guarded.failed_same_distance[~at_start]))
    return out


def _cut(alone_failed, guarded_failed):
    """1 - guarded / alone failures (None when the controller alone never fails)."""
    return 1.0 - guarded_failed.mean() / alone_failed.mean() if np.any(alone_failed) else None


def percent(entry, digits=1) -> str:
    """``"12.3 % [8.1, 17.6]"`` for a `_rate` entry (``"-"`` when it has no starts)."""
    if entry is None or entry.get("rate") is None:
        return "-"
    lo, hi = entry["ci95"]
    return (f"{100 * entry['rate']:.{digits}f} % [{100 * lo:.{digits}f}, "
            f"{100 * hi:.{digits}f}]")


def same_distance(figures: dict) -> str:
    """The same-distance figures of `liveness_figures` in words (or that there are none)."""
    if "same_distance_failure_set" not in figures:
        return "not judged by distance"
    cut = _share_text(figures["same_distance_failure_cut"])
    if figures.get("failed_at_start", {}).get("count"):
        cut += (f"; {_share_text(figures['same_distance_failure_cut_inside'])} over the starts "
                f"inside the safe set")
    return (f"at the same distance: alone fails {percent(figures['alone_same_distance_failure_set'])}, "
            f"guarded {percent(figures['same_distance_failure_set'])} "
            f"(cut {cut}), short of the distance {percent(figures['short_of_distance'])}")


def _share_text(value):
    return "-" if value is None else f"{100 * value:.0f} %"


def threshold_for_flag_budget(flagged_share, budget: float, *, low: float = 0.0,
                              high: float = 1.0, tolerance: float = 1e-3):
    """The detector threshold at which a guarded loop flags ``budget`` of its control
    ticks, found without labels: ``flagged_share(threshold)`` is the share of ticks the
    loop flags at that threshold (e.g. the ``flagged_ticks`` of `liveness_figures` from
    rollouts), assumed to fall as the threshold rises. Bisects ``[low, high]`` down to
    ``tolerance`` for the lowest threshold whose share is within the budget: returns
    ``(threshold, share, steps)``, ``steps`` the ``(threshold, share)`` pairs tried.

    A budget is what keeps a guard from flagging everything in an environment its
    detector was not trained on, where a threshold chosen on the training environments
    may flag most ticks (and a braking fallback then parks the vehicle on most starts).
    It fixes how often the guard intervenes, not how many interventions are saves: that
    still depends on how well the detector ranks the environment's states."""
    budget = float(budget)
    if not 0.0 < budget < 1.0:
        raise ValueError(f"a flag budget is a share of control ticks in (0, 1), got {budget!r}")
    if not (np.isfinite(low) and np.isfinite(high) and low < high) or not tolerance > 0:
        raise ValueError(f"threshold_for_flag_budget: need finite low < high and tolerance > 0, "
                         f"got low={low!r}, high={high!r}, tolerance={tolerance!r}")
    steps = []

    def share(threshold):
        value = flagged_share(float(threshold))
        steps.append((float(threshold), None if value is None else float(value)))
        return 0.0 if value is None else float(value)     # no ticks: nothing flagged

    if share(low) <= budget:
        if steps[-1][1] is None:
            raise ValueError("the flag budget cannot be met or missed: the loop runs no "
                             "control tick from these starts (every one has failed already)")
        return float(low), steps[-1][1], steps
    top = share(high)
    if top > budget:
        raise ValueError(f"even at threshold {high:g} the loop flags {100 * top:.1f} % of its "
                         f"ticks, over the flag budget of {100 * budget:g} %")
    below, above = float(low), float(high)       # share(below) > budget >= share(above)
    while above - below > tolerance:
        middle = 0.5 * (below + above)
        if share(middle) <= budget:
            above, top = middle, steps[-1][1]
        else:
            below = middle
    return above, top, steps


#: A guarded run at standstill this long (s) is parked for good: its image, and so its
#: flag and its speed, no longer change.
PARKED_SECONDS = 1.0


def travelled(time, speed, failure_time=None):
    """Metres travelled over the logged ticks (a tick's speed applies since the previous
    one), plus the stretch from the last tick to ``failure_time`` when given."""
    distance = float(np.sum(speed[1:] * np.diff(time)))
    if failure_time is not None and failure_time > time[-1]:
        distance += float(speed[-1] * (failure_time - time[-1]))
    return distance


#: `mission_row` of a start that had already failed (no run).
FAILED_AT_START = (True, False, False, 0.0, 0, 0, True, False)


def mission_row(time, speed, anomaly, *, failed: bool, failure_time, nominal: float,
                duration: float, goal: float) -> tuple:
    """One run's `MISSION_FIELDS` then `SAME_DISTANCE_FIELDS` (the caller keeps those it
    asked for), from its logged ``time``, ``speed`` (None: ``nominal`` throughout; a
    tick's speed applies since the previous one) and ``anomaly`` flags (None: none),
    whether it ``failed`` and when (``failure_time``, s, may lie between ticks). Ticks
    past ``duration`` (a mission-limited run's) count only for the same-distance
    fields: whether it failed at all, and whether it fell short of ``goal`` m."""
    time = np.asarray(time, float)
    speed = (np.full(len(time), nominal) if speed is None
             else np.asarray(speed, float).reshape(-1))
    k = int(np.sum(time <= duration + 1e-9))                # the ticks within the horizon
    within = bool(failed) and failure_time <= duration + 1e-9
    distance = travelled(time[:k], speed[:k], failure_time if within else None)
    acting = time[:k] < duration - 1e-9
    flags = (np.zeros(k, bool) if anomaly is None
             else np.asarray(anomaly, float).reshape(-1)[:k] >= 0.5)
    whole = travelled(time, speed, failure_time if failed else None)
    return (within, not within and speed[k - 1] <= 0, bool(np.any(speed[1:k] <= 0)),
            distance, int(np.sum(flags & acting)), int(np.sum(acting)), bool(failed),
            not failed and whole < goal * (1 - 1e-9))


def mission_done(goal: float, nominal: float, period: float, horizon: float):
    """A real run's ``stop_when`` (`reachwatch.diagrams.simulate`) for a mission: true
    once the run has covered ``goal`` m, or, past ``horizon`` s, once it has stood
    still for `PARKED_SECONDS` (within the horizon a parked run goes on, so its ticks
    and flagged ticks there are those of a run without a mission limit, as the table
    rollouts count them)."""
    parked_ticks = max(1, int(round(PARKED_SECONDS / period)))
    seen = {"distance": 0.0, "still": 0}

    def done(rows):                      # called once per tick, after its row is read
        speed = float(np.ravel(rows["speed"][-1])[0]) if "speed" in rows else nominal
        if len(rows["state"]) > 1:       # the first row is the start: nothing travelled
            seen["distance"] += speed * period
        seen["still"] = seen["still"] + 1 if speed <= 0 else 0
        past = (len(rows["state"]) - 1) * period >= horizon - 1e-9
        return seen["distance"] >= goal * (1 - 1e-9) or (past and seen["still"] >= parked_ticks)
    return done
