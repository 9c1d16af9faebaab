"""Safety and liveness of a guarded loop side by side.

A runtime monitor is judged by two columns: the failures it avoids and the missions it
still completes. A fallback that stops the vehicle everywhere empties the failure set
and completes nothing, so every failure figure here comes with its liveness figures,
computed from the same starts for the controller alone and for the guarded loop."""

import dataclasses as dc

import numpy as np

from .fidelity import wilson_interval

#: The per-start fields of `MissionOutcomes` (all arrays of one length).
MISSION_FIELDS = ("failed", "stopped", "ever_stopped", "distance", "flagged_ticks", "ticks")


@dc.dataclass
class MissionOutcomes:
    """Per start: ``failed`` (left the safe set within the horizon), ``stopped`` (ended
    the horizon at standstill without failing), ``ever_stopped`` (was at standstill at
    some tick before it ended or failed), ``distance`` (m travelled until the end or the
    failure), ``flagged_ticks`` and ``ticks`` (control ticks flagged by the detector,
    and all control ticks, until the end or the failure)."""
    failed: np.ndarray
    stopped: np.ndarray
    ever_stopped: np.ndarray
    distance: np.ndarray
    flagged_ticks: np.ndarray
    ticks: np.ndarray

    def __post_init__(self):
        for name in MISSION_FIELDS:
            setattr(self, name, np.asarray(getattr(self, name)).reshape(-1))
        n = {len(getattr(self, name)) for name in MISSION_FIELDS}
        if len(n) != 1 or n == {0}:
            raise ValueError(f"MissionOutcomes: every field needs the same number (> 0) of "
                             f"starts, got {[len(getattr(self, f)) for f in MISSION_FIELDS]}")
        for name in ("failed", "stopped", "ever_stopped"):
            setattr(self, name, getattr(self, name).astype(bool))
        if np.any(self.stopped & self.failed):
            raise ValueError("MissionOutcomes: a start cannot both fail and end stopped")

    def __len__(self):
        return len(self.failed)

    @classmethod
    def from_fields(cls, fields: dict) -> "MissionOutcomes":
        missing = [name for name in MISSION_FIELDS if name not in fields]
        if missing:
            raise ValueError(f"MissionOutcomes: missing fields {missing}")
        return cls(**{name: fields[name] for name in MISSION_FIELDS})

    def as_fields(self) -> dict:
        return {name: getattr(self, name) for name in MISSION_FIELDS}


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
    - ``flagged_ticks``: share of all control ticks the detector flagged."""
    if len(alone) != len(guarded):
        raise ValueError(f"liveness_figures: {len(alone)} starts alone but {len(guarded)} "
                         f"guarded; both must come from the same starts")
    survives, fails = ~alone.failed, alone.failed
    alone_mean = float(np.mean(alone.distance))
    ticks = int(np.sum(guarded.ticks))
    out = {"starts": len(alone),
           "failure_set": _rate(guarded.failed),
           "alone_failure_set": _rate(alone.failed),
           "failure_cut": (1.0 - guarded.failed.mean() / alone.failed.mean()
                           if alone.failed.any() else None),
           "ended_stopped": _rate(guarded.stopped),
           "ever_stopped": _rate(guarded.ever_stopped),
           "needless_stops": _rate(guarded.stopped[survives]),
           "harmed": _rate(guarded.failed[survives]),
           "saved": _rate(~guarded.failed[fails]),
           "saved_moving": _rate((~guarded.failed & ~guarded.stopped)[fails]),
           "distance_ratio": float(np.mean(guarded.distance)) / alone_mean if alone_mean > 0 else None,
           "flagged_ticks": int(np.sum(guarded.flagged_ticks)) / ticks if ticks else None}
    return out


def percent(entry, digits=1) -> str:
    """``"12.3 % [8.1, 17.6]"`` for a `_rate` entry (``"-"`` when it has no starts)."""
    if entry is None or entry.get("rate") is None:
        return "-"
    lo, hi = entry["ci95"]
    return (f"{100 * entry['rate']:.{digits}f} % [{100 * lo:.{digits}f}, "
            f"{100 * hi:.{digits}f}]")
