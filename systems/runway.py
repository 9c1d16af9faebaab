"""Runway descriptions: the `RunwaySpec` a user writes, and the five catalog runways.

Everything is plain dataclasses (loadable with ``pydrake.common.yaml``). Lengths in m,
colours as linear RGB in [0, 1], angles in degrees.
"""

import dataclasses as dc
from typing import List

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
        """Raise ValueError naming the first bad field."""
        def bad(field, why):
            raise ValueError(f"runway '{self.name}': {field} {why}")
        if not self.half_width > 0:
            bad("half_width", f"must be > 0 m, got {self.half_width}")
        if not self.length > 300:
            bad("length", f"must be > 300 m, got {self.length}")
        if self.surface.kind not in SURFACES:
            bad("surface.kind", f"must be one of {SURFACES}, got '{self.surface.kind}'")
        for field, rgb in [("surface.tone", self.surface.tone),
                           ("surface.grass_tone", self.surface.grass_tone),
                           ("markings.paint", self.markings.paint),
                           ("lights.color", self.lights.color),
                           ("building_tone", self.building_tone)]:
            if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
                bad(field, f"must be 3 numbers in [0, 1], got {rgb}")
        if self.markings.dash_length <= 0 or self.markings.dash_gap < 0:
            bad("markings.dash_length/dash_gap", "must be > 0 and >= 0")
        if self.lights.spacing <= 0:
            bad("lights.spacing", f"must be > 0 m, got {self.lights.spacing}")
        for i, line in enumerate(self.taxiway_lines):
            if line.side not in (-1, 1):
                bad(f"taxiway_lines[{i}].side", f"must be +1 or -1, got {line.side}")
            if line.radius <= 0:
                bad(f"taxiway_lines[{i}].radius", f"must be > 0 m, got {line.radius}")
        return self


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
