"""Runway descriptions: the `RunwaySpec` a user writes, and the five catalog runways.

Everything is plain dataclasses (loadable with ``pydrake.common.yaml``). Lengths in m,
colours as linear RGB in [0, 1], angles in degrees.
"""

import dataclasses as dc
import math
from typing import List

from .checks import check_name, short

SURFACES = ("asphalt", "concrete")


@dc.dataclass
class SurfaceSpec:
    """Pavement and surroundings appearance."""
    kind: str = "asphalt"                    # asphalt | concrete
    tone: List[float] = dc.field(default_factory=lambda: [0.30, 0.30, 0.31])
    roughness: float = 0.5                   # texture contrast in [0, 1]
    grass_tone: List[float] = dc.field(default_factory=lambda: [0.30, 0.42, 0.20])
    texture_seed: int = 0


@dc.dataclass
class MarkingsSpec:
    """White paint (downtrack positions in m from the threshold, py = 0)."""
    edge_lines: bool = True
    edge_line_width: float = 0.9
    centreline: bool = True
    centreline_width: float = 0.9
    dash_length: float = 36.0
    dash_gap: float = 24.0
    threshold_stripes: int = 8               # piano keys at py in [6, 36]; 0 = none
    touchdown_zone: List[float] = dc.field(default_factory=lambda: [150.0, 300.0, 450.0])
    paint: List[float] = dc.field(default_factory=lambda: [0.92, 0.92, 0.90])


@dc.dataclass
class LightsSpec:
    """Runway-edge lights, lit at night."""
    enabled: bool = True
    spacing: float = 60.0                    # m between lights along each edge
    offset: float = 1.5                      # m outside the pavement edge
    color: List[float] = dc.field(default_factory=lambda: [1.0, 0.92, 0.70])


@dc.dataclass
class TaxiwayLine:
    """A yellow lead-in line leaving the centreline at ``start`` (m downtrack)."""
    start: float = 200.0
    side: int = 1                            # +1 exits to the left (+px), -1 right
    radius: float = 60.0                     # turn radius (m)
    turn_deg: float = 60.0                   # total turn before running straight
    width: float = 0.5


@dc.dataclass
class RunwaySpec:
    """A procedural runway. ``half_width`` is B of the failure set ``|px| >= B``."""
    name: str = "CUSTOM"
    half_width: float = 10.0
    length: float = 2000.0
    heading_deg: float = 0.0                 # compass heading; sets where the sun is
    surface: SurfaceSpec = dc.field(default_factory=SurfaceSpec)
    markings: MarkingsSpec = dc.field(default_factory=MarkingsSpec)
    lights: LightsSpec = dc.field(default_factory=LightsSpec)
    taxiway_lines: List[TaxiwayLine] = dc.field(default_factory=list)
    buildings: int = 4                       # hangars beside the runway
    building_tone: List[float] = dc.field(default_factory=lambda: [0.62, 0.60, 0.56])

    def validate(self):
        """Raise ValueError naming the first bad field. Sizes are bounded so that the
        scene stays a few thousand shapes (the pavement is tiled in ~8 m slabs, the
        centreline dashed, lights and taxiway lines built piece by piece)."""
        check_name("runway_spec.name", self.name)

        def bad(field, why):
            raise ValueError(f"runway '{self.name}': {field} {why}")

        def number(field, value, lo, hi, *, lo_open=False):
            ok = (not isinstance(value, bool) and isinstance(value, (int, float))
                  and math.isfinite(value) and lo <= value <= hi and not (lo_open and value == lo))
            if not ok:
                bad(field, f"must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}], got "
                           f"{short(value)}")

        def whole(field, value, hi):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= hi:
                bad(field, f"must be a whole number in [0, {hi}], got {short(value)}")

        number("half_width", self.half_width, 0.0, MAX_HALF_WIDTH, lo_open=True)
        if not self.length > 300:
            bad("length", f"must be > 300 m, got {short(self.length)}")
        number("length", self.length, 300.0, MAX_LENGTH)
        number("heading_deg", self.heading_deg, -360.0, 360.0)
        if self.surface.kind not in SURFACES:
            bad("surface.kind", f"must be one of {SURFACES}, got {short(self.surface.kind)}")
        number("surface.roughness", self.surface.roughness, 0.0, 1.0)
        whole("surface.texture_seed", self.surface.texture_seed, 2 ** 31 - 1)
        for field, rgb in [("surface.tone", self.surface.tone),
                           ("surface.grass_tone", self.surface.grass_tone),
                           ("markings.paint", self.markings.paint),
                           ("lights.color", self.lights.color),
                           ("building_tone", self.building_tone)]:
            if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
                bad(field, f"must be 3 numbers in [0, 1], got {short(rgb)}")
        if not (self.markings.dash_length > 0 and self.markings.dash_gap >= 0):
            bad("markings.dash_length/dash_gap", "must be > 0 and >= 0")
        number("markings.dash_length", self.markings.dash_length, 1.0, MAX_LENGTH)
        number("markings.dash_gap", self.markings.dash_gap, 0.0, MAX_LENGTH)
        number("markings.edge_line_width", self.markings.edge_line_width, 0.0, 10.0)
        number("markings.centreline_width", self.markings.centreline_width, 0.0, 10.0)
        whole("markings.threshold_stripes", self.markings.threshold_stripes, 40)
        if len(self.markings.touchdown_zone) > 20:
            bad("markings.touchdown_zone", f"lists at most 20 positions, got "
                                           f"{len(self.markings.touchdown_zone)}")
        for i, x in enumerate(self.markings.touchdown_zone):
            number(f"markings.touchdown_zone[{i}]", x, 0.0, MAX_LENGTH)
        if not self.lights.spacing > 0:
            bad("lights.spacing", f"must be > 0 m, got {short(self.lights.spacing)}")
        number("lights.spacing", self.lights.spacing, 5.0, MAX_LENGTH)
        number("lights.offset", self.lights.offset, 0.0, 100.0)
        if len(self.taxiway_lines) > 20:
            bad("taxiway_lines", f"lists at most 20 lines, got {len(self.taxiway_lines)}")
        for i, line in enumerate(self.taxiway_lines):
            if line.side not in (-1, 1):
                bad(f"taxiway_lines[{i}].side", f"must be +1 or -1, got {short(line.side)}")
            if not line.radius > 0:
                bad(f"taxiway_lines[{i}].radius", f"must be > 0 m, got {short(line.radius)}")
            number(f"taxiway_lines[{i}].radius", line.radius, 0.0, 1000.0, lo_open=True)
            number(f"taxiway_lines[{i}].start", line.start, -MAX_LENGTH, MAX_LENGTH)
            number(f"taxiway_lines[{i}].turn_deg", line.turn_deg, -360.0, 360.0)
            number(f"taxiway_lines[{i}].width", line.width, 0.0, 10.0)
        whole("buildings", self.buildings, MAX_BUILDINGS)
        return self


#: Bounds of a `RunwaySpec` (m; hangars).
MAX_HALF_WIDTH = 200.0
MAX_LENGTH = 20000.0
MAX_BUILDINGS = 50


def _catalog():
    yellow_exits = [TaxiwayLine(start=140.0, side=1, radius=70.0, turn_deg=45.0),
                    TaxiwayLine(start=330.0, side=-1, radius=55.0, turn_deg=90.0),
                    TaxiwayLine(start=520.0, side=1, radius=80.0, turn_deg=30.0)]
    return {
        # Grant County: narrow, dark weathered asphalt, green-brown grass.
        "KMWH": RunwaySpec(
            name="KMWH", half_width=10.0, length=2982.0, heading_deg=53.7,
            surface=SurfaceSpec("asphalt", [0.26, 0.26, 0.27], 0.55, [0.36, 0.40, 0.22], 1),
            markings=MarkingsSpec(threshold_stripes=6, touchdown_zone=[150.0, 300.0]),
            buildings=3, building_tone=[0.70, 0.66, 0.58]),
        # Atlanta: wide, light concrete slabs, lush grass.
        "KATL": RunwaySpec(
            name="KATL", half_width=18.0, length=2678.0, heading_deg=90.0,
            surface=SurfaceSpec("concrete", [0.62, 0.61, 0.58], 0.35, [0.24, 0.44, 0.18], 2),
            markings=MarkingsSpec(threshold_stripes=12, centreline_width=1.0,
                                  touchdown_zone=[150.0, 300.0, 450.0, 600.0]),
            lights=LightsSpec(spacing=50.0, color=[1.0, 1.0, 0.9]),
            buildings=6, building_tone=[0.55, 0.57, 0.62]),
        # Fairbanks: grey asphalt, pale tundra-like surroundings.
        "PAEI": RunwaySpec(
            name="PAEI", half_width=16.0, length=4361.0, heading_deg=159.2,
            surface=SurfaceSpec("asphalt", [0.38, 0.38, 0.40], 0.45, [0.52, 0.52, 0.44], 3),
            markings=MarkingsSpec(threshold_stripes=10, dash_length=30.0, dash_gap=30.0),
            lights=LightsSpec(spacing=60.0, color=[1.0, 0.85, 0.6]),
            buildings=2, building_tone=[0.45, 0.40, 0.36]),
        # San Francisco (test): very wide concrete, yellow taxiway lead-ins.
        "KSFO": RunwaySpec(
            name="KSFO", half_width=25.0, length=3484.0, heading_deg=117.9,
            surface=SurfaceSpec("concrete", [0.55, 0.54, 0.52], 0.40, [0.40, 0.46, 0.26], 4),
            markings=MarkingsSpec(threshold_stripes=16, centreline_width=1.0,
                                  touchdown_zone=[150.0, 300.0, 450.0]),
            lights=LightsSpec(spacing=50.0),
            taxiway_lines=yellow_exits, buildings=8, building_tone=[0.75, 0.75, 0.78]),
        # Newark (test): asphalt, yellow taxiway lead-ins.
        "KEWR": RunwaySpec(
            name="KEWR", half_width=17.0, length=1920.0, heading_deg=95.0,
            surface=SurfaceSpec("asphalt", [0.22, 0.22, 0.24], 0.50, [0.28, 0.36, 0.20], 5),
            markings=MarkingsSpec(threshold_stripes=12, dash_length=40.0, dash_gap=20.0),
            taxiway_lines=[TaxiwayLine(start=180.0, side=-1, radius=60.0, turn_deg=60.0),
                           TaxiwayLine(start=420.0, side=1, radius=50.0, turn_deg=90.0)],
            buildings=5, building_tone=[0.50, 0.36, 0.30]),
    }


#: The five catalog runways, named after the paper's airports.
RUNWAYS = {name: spec.validate() for name, spec in _catalog().items()}
