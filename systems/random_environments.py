"""Families of random environments: runways, hours and skies drawn from ranges.

A `RandomEnvironments` in a run file (``train_random`` / ``test_random``) stands for
``count`` environments drawn from its ``seed``: the same fields and seed give the same
environments on any machine, and each is an ordinary `Environment` with its own
`RunwaySpec`, swept, solved and labelled like a listed one. Ranges are ``[low, high]``
(a draw is uniform in it; counts are whole numbers, both ends included).
"""

import dataclasses as dc
from typing import List

import numpy as np

from .bounds import bounded, check_bounds, seed_field
from .checks import short
from .environment import SKIES, Environment
from .runway import (SURFACES, LightsSpec, MarkingsSpec, RunwaySpec, SurfaceSpec, TaxiwayLine,
                     stripe_room)


#: The most environments one family may hold (each is swept, solved and labelled).
MAX_COUNT = 1000


def _range_of(lo, hi) -> dict:
    """The bound of a ``[low, high]`` range inside ``[lo, hi]`` (low <= high is checked
    by `_check_ranges`)."""
    return dict(low=lo, high=hi, each=True, items=(2, 2), note="low <= high")


#: The widest edge line a random runway draws (m).
MAX_EDGE_LINE = 1.2


@dc.dataclass
class RandomRunwayRanges:
    """What a random runway may look like. ``half_width`` (m, B of the failure set),
    ``length`` (m), ``heading_deg`` (compass, sets where the sun is), ``pavement_tone``
    (grey level of the surface in [0, 1]), ``roughness`` (texture contrast),
    ``surfaces`` (drawn with equal odds), ``lights`` (chance the edge lights exist),
    ``threshold_stripes``, ``taxiway_lines`` and ``buildings`` (counts). Grass and
    building colours, paint widths, dash patterns and the touchdown zone are drawn from
    fixed plausible ranges."""
    half_width: List[float] = bounded(default_factory=lambda: [8.0, 30.0],
                                      **_range_of(1.0, 100.0), unit="m")
    length: List[float] = bounded(default_factory=lambda: [1500.0, 4000.0],
                                  **_range_of(600.0, 6000.0), unit="m")
    heading_deg: List[float] = bounded(default_factory=lambda: [0.0, 360.0],
                                       **_range_of(0.0, 360.0), unit="deg")
    pavement_tone: List[float] = bounded(default_factory=lambda: [0.18, 0.65],
                                         **_range_of(0.0, 1.0))
    roughness: List[float] = bounded(default_factory=lambda: [0.3, 0.6], **_range_of(0.0, 1.0))
    surfaces: List[str] = dc.field(default_factory=lambda: list(SURFACES))
    lights: float = bounded(0.9, 0.0, 1.0)
    threshold_stripes: List[int] = bounded(default_factory=lambda: [0, 16],
                                           **_range_of(0, 40), whole=True)
    taxiway_lines: List[int] = bounded(default_factory=lambda: [0, 3], **_range_of(0, 8),
                                       whole=True)
    buildings: List[int] = bounded(default_factory=lambda: [0, 8], **_range_of(0, 20),
                                   whole=True)

    def validate(self, where="runway"):
        _check_ranges(self, where)
        if self.threshold_stripes[1] > 0 and stripe_room(self.half_width[0], MAX_EDGE_LINE) <= 0:
            raise ValueError(f"{where}.half_width from {self.half_width[0]:g} m leaves no room "
                             f"for threshold stripes between edge lines of up to "
                             f"{MAX_EDGE_LINE:g} m: start it at {1.5 + MAX_EDGE_LINE + 0.1:g} m "
                             f"or more, or set {where}.threshold_stripes: [0, 0]")
        if not self.surfaces or any(s not in SURFACES for s in self.surfaces):
            raise ValueError(f"{where}.surfaces must list some of {SURFACES}, got "
                             f"{short(self.surfaces)}")
        return self


@dc.dataclass
class RandomEnvironments:
    """``count`` random environments from ``seed``: an hour uniform in ``hours`` (local
    time, rounded to 0.1 h), a sky from ``skies`` with equal odds, and a runway from
    ``runway``. Names are ``{prefix}{seed}-{i}`` plus hour and sky, so two families
    with different seeds never share a name."""
    count: int = bounded(0, 0, MAX_COUNT, whole=True)
    seed: int = seed_field()
    hours: List[float] = bounded(default_factory=lambda: [0.0, 24.0], **_range_of(0.0, 24.0),
                                 unit="h")
    skies: List[str] = dc.field(default_factory=lambda: list(SKIES))
    runway: RandomRunwayRanges = dc.field(default_factory=RandomRunwayRanges)
    prefix: str = "RND"

    def validate(self, where="random"):
        """Raise ValueError naming the first bad field (as ``where.field``); return self."""
        _check_ranges(self, where)
        if not self.skies or any(s not in SKIES for s in self.skies):
            raise ValueError(f"{where}.skies must list some of {SKIES}, got {short(self.skies)}")
        if not (isinstance(self.prefix, str) and self.prefix.isascii() and self.prefix.isalnum()
                and len(self.prefix) <= 16 and not self.prefix[-1].isdigit()):
            raise ValueError(f"{where}.prefix must be letters and digits (1 to 16, ASCII) "
                             f"ending in a letter (the seed follows it: RND1 with seed 1 and "
                             f"RND with seed 11 would name alike), got {short(self.prefix)}")
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
        edge_lines=bool(rng.random() < 0.9), edge_line_width=u([0.6, MAX_EDGE_LINE]),
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


def _check_ranges(obj, where):
    """`check_bounds` of ``obj``'s fields, and each ``[low, high]`` range in order."""
    check_bounds(obj, f"{where}.")
    for f in dc.fields(obj):
        bound = f.metadata.get("bound")
        value = getattr(obj, f.name)
        if bound is not None and bound.items == (2, 2) and value[0] > value[1]:
            raise ValueError(f"{where}.{f.name} must be [low, high] with low <= high, got "
                             f"{short(value)}")
