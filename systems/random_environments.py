"""Families of random environments: runways, hours and skies drawn from ranges.

A `RandomEnvironments` in a run file (``train_random`` / ``test_random``) stands for
``count`` environments drawn from its ``seed``: the same fields and seed give the same
environments on any machine, and each is an ordinary `Environment` with its own
`RunwaySpec`, swept, solved and labelled like a listed one. Ranges are ``[low, high]``
(a draw is uniform in it; counts are whole numbers, both ends included).
"""

import dataclasses as dc
import math
from typing import List

import numpy as np

from .checks import short
from .environment import SKIES, Environment
from .runway import SURFACES, LightsSpec, MarkingsSpec, RunwaySpec, SurfaceSpec, TaxiwayLine


@dc.dataclass
class RandomRunwayRanges:
    """What a random runway may look like. ``half_width`` (m, B of the failure set),
    ``length`` (m), ``heading_deg`` (compass, sets where the sun is), ``pavement_tone``
    (grey level of the surface in [0, 1]), ``roughness`` (texture contrast),
    ``surfaces`` (drawn with equal odds), ``lights`` (chance the edge lights exist),
    ``threshold_stripes``, ``taxiway_lines`` and ``buildings`` (counts). Grass and
    building colours, paint widths, dash patterns and the touchdown zone are drawn from
    fixed plausible ranges."""
    half_width: List[float] = dc.field(default_factory=lambda: [8.0, 30.0])
    length: List[float] = dc.field(default_factory=lambda: [1500.0, 4000.0])
    heading_deg: List[float] = dc.field(default_factory=lambda: [0.0, 360.0])
    pavement_tone: List[float] = dc.field(default_factory=lambda: [0.18, 0.65])
    roughness: List[float] = dc.field(default_factory=lambda: [0.3, 0.6])
    surfaces: List[str] = dc.field(default_factory=lambda: list(SURFACES))
    lights: float = 0.9
    threshold_stripes: List[int] = dc.field(default_factory=lambda: [0, 16])
    taxiway_lines: List[int] = dc.field(default_factory=lambda: [0, 3])
    buildings: List[int] = dc.field(default_factory=lambda: [0, 8])

    def validate(self, where="runway"):
        limits = {"half_width": (1.0, 100.0), "length": (600.0, 6000.0),
                  "heading_deg": (0.0, 360.0), "pavement_tone": (0.0, 1.0),
                  "roughness": (0.0, 1.0)}
        for name, (lo, hi) in limits.items():
            _range(f"{where}.{name}", getattr(self, name), lo, hi)
        for name, hi in (("threshold_stripes", 40), ("taxiway_lines", 8), ("buildings", 20)):
            _range(f"{where}.{name}", getattr(self, name), 0, hi, whole=True)
        if not self.surfaces or any(s not in SURFACES for s in self.surfaces):
            raise ValueError(f"{where}.surfaces must list some of {SURFACES}, got "
                             f"{short(self.surfaces)}")
        if not _number(self.lights) or not 0.0 <= self.lights <= 1.0:
            raise ValueError(f"{where}.lights must be a chance in [0, 1], got {self.lights!r}")
        return self


#: The most environments one family may hold (each is swept, solved and labelled).
MAX_COUNT = 1000


@dc.dataclass
class RandomEnvironments:
    """``count`` random environments from ``seed``: an hour uniform in ``hours`` (local
    time, rounded to 0.1 h), a sky from ``skies`` with equal odds, and a runway from
    ``runway``. Names are ``{prefix}{seed}-{i}`` plus hour and sky, so two families
    with different seeds never share a name."""
    count: int = 0
    seed: int = 0
    hours: List[float] = dc.field(default_factory=lambda: [0.0, 24.0])
    skies: List[str] = dc.field(default_factory=lambda: list(SKIES))
    runway: RandomRunwayRanges = dc.field(default_factory=RandomRunwayRanges)
    prefix: str = "RND"

    def validate(self, where="random"):
        """Raise ValueError naming the first bad field (as ``where.field``); return self."""
        for name, most in (("count", MAX_COUNT), ("seed", 2 ** 31 - 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= most:
                raise ValueError(f"{where}.{name} must be a whole number >= 0 (at most {most}), "
                                 f"got {short(value)}")
        _range(f"{where}.hours", self.hours, 0.0, 24.0)
        if not self.skies or any(s not in SKIES for s in self.skies):
            raise ValueError(f"{where}.skies must list some of {SKIES}, got {short(self.skies)}")
        if not (isinstance(self.prefix, str) and self.prefix.isascii() and self.prefix.isalnum()
                and len(self.prefix) <= 16):
            raise ValueError(f"{where}.prefix must be letters and digits (1 to 16, ASCII), got "
                             f"{short(self.prefix)}")
        self.runway.validate(f"{where}.runway")
        return self

    def environments(self) -> List[Environment]:
        """The family, in order; environment ``i`` depends only on ``seed`` and ``i``."""
        self.validate()
        return [self._draw(i) for i in range(self.count)]

    def _draw(self, i) -> Environment:
        rng = np.random.default_rng([self.seed, i])
        name = f"{self.prefix}{self.seed}-{i}"
        hour = round(float(rng.uniform(*self.hours)), 1) % 24.0
        sky = self.skies[int(rng.integers(len(self.skies)))]
        return Environment(runway=name, hour=hour, sky=sky,
                           runway_spec=random_runway(rng, self.runway, name))


def random_runway(rng: np.random.Generator, ranges: RandomRunwayRanges, name: str) -> RunwaySpec:
    """One runway drawn from ``ranges`` with ``rng``; always valid."""
    u = lambda lo_hi: float(rng.uniform(*lo_hi))                      # noqa: E731
    whole = lambda lo_hi: int(rng.integers(lo_hi[0], lo_hi[1] + 1))  # noqa: E731
    grey = u(ranges.pavement_tone)
    tint = rng.uniform(-0.02, 0.02, 3)
    tone = [float(np.clip(grey + t, 0.0, 1.0)) for t in tint]
    grass = [u([0.22, 0.55]), u([0.32, 0.55]), u([0.15, 0.45])]
    markings = MarkingsSpec(
        edge_lines=bool(rng.random() < 0.9), edge_line_width=u([0.6, 1.2]),
        centreline_width=u([0.6, 1.2]), dash_length=u([25.0, 45.0]), dash_gap=u([15.0, 35.0]),
        threshold_stripes=whole(ranges.threshold_stripes),
        touchdown_zone=[150.0 * (k + 1) for k in range(int(rng.integers(0, 5)))],
        paint=[u([0.85, 0.95])] * 3)
    lights = LightsSpec(enabled=bool(rng.random() < ranges.lights), spacing=u([40.0, 70.0]),
                        offset=u([1.0, 3.0]), color=[1.0, u([0.8, 1.0]), u([0.55, 0.9])])
    lines = [TaxiwayLine(start=u([120.0, 700.0]), side=int(rng.choice([-1, 1])),
                         radius=u([40.0, 90.0]), turn_deg=u([30.0, 90.0]))
             for _ in range(whole(ranges.taxiway_lines))]
    surface = SurfaceSpec(kind=ranges.surfaces[int(rng.integers(len(ranges.surfaces)))],
                          tone=tone, roughness=u(ranges.roughness), grass_tone=grass,
                          texture_seed=int(rng.integers(1 << 16)))
    return RunwaySpec(name=name, half_width=u(ranges.half_width), length=u(ranges.length),
                      heading_deg=u(ranges.heading_deg) % 360.0, surface=surface,
                      markings=markings, lights=lights, taxiway_lines=lines,
                      buildings=whole(ranges.buildings),
                      building_tone=[u([0.3, 0.8]) for _ in range(3)]).validate()


def _number(value):
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def _range(where, value, lo, hi, *, whole=False):
    """Check a ``[low, high]`` range inside ``[lo, hi]``."""
    kind = "whole numbers" if whole else "numbers"
    ok = (isinstance(value, (list, tuple)) and len(value) == 2
          and all(_number(v) and (not whole or float(v).is_integer()) for v in value))
    if not ok or not lo <= value[0] <= value[1] <= hi:
        raise ValueError(f"{where} must be [low, high], {kind} with {lo} <= low <= high <= "
                         f"{hi}, got {short(value)}")
