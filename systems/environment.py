"""An environment = runway x hour x sky, and the paper's train/test split."""

import copy
import dataclasses as dc
import math
from typing import Optional

from .bounds import bounded, check_bounds
from .checks import short, warn_once
from .runway import RUNWAYS, RunwaySpec

SKIES = ("clear", "overcast")


@dc.dataclass
class Environment:
    """Where and when the aircraft taxis.

    ``runway`` names a catalog runway (KMWH, KATL, PAEI, KSFO, KEWR) unless
    ``runway_spec`` describes one of the user's own; ``hour`` is local time in
    [0, 24); ``sky`` is clear or overcast.
    """
    runway: str = "KMWH"
    hour: float = bounded(9.0, 0.0, 24.0, high_open=True, unit="h")
    sky: str = "clear"
    runway_spec: Optional[RunwaySpec] = None

    def validate(self):
        """Raise ValueError naming the first bad field; return self."""
        if self.runway_spec is None and self.runway not in RUNWAYS:
            raise ValueError(
                f"environment.runway: unknown runway {short(self.runway)}; the catalog has "
                f"{sorted(RUNWAYS)}, or describe your own under environment.runway_spec")
        if self.runway_spec is not None:
            self.runway_spec.validate("environment.runway_spec")
            if self.runway not in (self.runway_spec.name, Environment.runway):
                warn_once(f"environment.runway {short(self.runway)} is not read beside "
                          f"runway_spec: the environment is named by runway_spec.name "
                          f"({short(self.runway_spec.name)}); set that to name it")
        check_bounds(self, "environment.")
        if self.sky not in SKIES:
            raise ValueError(f"environment.sky must be one of {SKIES}, got {short(self.sky)}")
        return self

    def spec(self) -> RunwaySpec:
        """The runway description (a copy; catalog entries are never mutated)."""
        if self.runway_spec is not None:
            return copy.deepcopy(self.runway_spec).validate()
        return copy.deepcopy(RUNWAYS[self.runway])

    @property
    def name(self) -> str:
        """A short id such as ``KMWH_9h_clear``."""
        runway = self.runway_spec.name if self.runway_spec is not None else self.runway
        return f"{runway}_{hour_text(self.hour)}h_{self.sky}"

    @property
    def half_width(self) -> float:
        """B (m): the aircraft fails when ``|px| >= B``. Read without `spec`'s copy: a
        failure rule reads it at every integrator step (the copy took 0.3 ms)."""
        spec = self.runway_spec if self.runway_spec is not None else RUNWAYS[self.runway]
        return spec.half_width


def hour_text(hour: float) -> str:
    """``hour`` as environment names write it: ``9``, ``17p5``; as many digits as it
    takes to name the hour itself (23.9999999 is not 24); -0.0 is 0, as it is."""
    hour = hour + 0.0          # -0.0 + 0.0 is 0.0: one hour, one name
    text = f"{hour:g}"
    if math.isfinite(hour) and float(text) != hour:
        text = repr(float(hour))
    return text.replace(".", "p")


def training_environments():
    """The paper's 12 training environments: {KMWH, KATL, PAEI} x {9, 21} x skies."""
    return [Environment(r, h, s) for r in ("KMWH", "KATL", "PAEI")
            for h in (9.0, 21.0) for s in SKIES]


def test_environments():
    """The paper's held-out environments: hour 17 on the training runways, and
    KSFO and KEWR at every condition."""
    envs = [Environment(r, 17.0, s) for r in ("KMWH", "KATL", "PAEI") for s in SKIES]
    envs += [Environment(r, h, s) for r in ("KSFO", "KEWR")
             for h in (9.0, 17.0, 21.0) for s in SKIES]
    return envs
