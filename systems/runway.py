"""Runway descriptions: the `RunwaySpec` a user writes, and the five catalog runways.

Everything is plain dataclasses (loadable with ``pydrake.common.yaml``). Lengths in m,
colours as linear RGB in [0, 1], angles in degrees.
"""

import dataclasses as dc
from typing import List

from .bounds import bounded, check_bounds, seed_field
from .checks import check_name, short

SURFACES = ("asphalt", "concrete")

#: Bounds of a `RunwaySpec` (m; hangars).
MAX_HALF_WIDTH = 200.0
MAX_LENGTH = 20000.0
MAX_BUILDINGS = 50
#: A colour: three numbers in [0, 1] (linear RGB).
RGB = dict(low=0.0, high=1.0, each=True, items=(3, 3))


@dc.dataclass
class SurfaceSpec:
    """Pavement and surroundings appearance."""
    kind: str = "asphalt"                    # asphalt | concrete
    tone: List[float] = bounded(default_factory=lambda: [0.30, 0.30, 0.31], **RGB)
    roughness: float = bounded(0.5, 0.0, 1.0)    # texture contrast
    grass_tone: List[float] = bounded(default_factory=lambda: [0.30, 0.42, 0.20], **RGB)
    texture_seed: int = seed_field()


@dc.dataclass
class MarkingsSpec:
    """White paint (downtrack positions in m from the threshold, py = 0)."""
    edge_lines: bool = True
    edge_line_width: float = bounded(0.9, 0.0, 10.0, low_open=True, unit="m")
    centreline: bool = True
    centreline_width: float = bounded(0.9, 0.0, 10.0, low_open=True, unit="m")
    dash_length: float = bounded(36.0, 1.0, MAX_LENGTH, unit="m")
    dash_gap: float = bounded(24.0, 0.0, MAX_LENGTH, unit="m")
    threshold_stripes: int = bounded(8, 0, 40, whole=True)   # piano keys at py in [6, 36]
    touchdown_zone: List[float] = bounded(default_factory=lambda: [150.0, 300.0, 450.0],
                                          low=0.0, high=MAX_LENGTH, unit="m", each=True,
                                          items=(0, 20))
    paint: List[float] = bounded(default_factory=lambda: [0.92, 0.92, 0.90], **RGB)


@dc.dataclass
class LightsSpec:
    """Runway-edge lights, lit at night."""
    enabled: bool = True
    spacing: float = bounded(60.0, 5.0, MAX_LENGTH, unit="m")   # between lights along each edge
    offset: float = bounded(1.5, 0.0, 100.0, unit="m")          # outside the pavement edge
    color: List[float] = bounded(default_factory=lambda: [1.0, 0.92, 0.70], **RGB)


@dc.dataclass
class TaxiwayLine:
    """A yellow lead-in line leaving the centreline at ``start`` (m downtrack)."""
    start: float = bounded(200.0, -MAX_LENGTH, MAX_LENGTH, unit="m")
    side: int = bounded(1, -1, 1, whole=True, note="+1 or -1")   # +1 exits to the left (+px)
    radius: float = bounded(60.0, 0.0, 1000.0, low_open=True, unit="m")   # turn radius
    turn_deg: float = bounded(60.0, -360.0, 360.0, unit="deg")   # total turn, then straight
    width: float = bounded(0.5, 0.0, 10.0, low_open=True, unit="m")


def stripe_room(half_width: float, edge_line_width: float) -> float:
    """The width (m) the threshold stripes share across a runway: its width less its
    edge lines and 1.5 m beside each (the scene spaces the stripes over it); a runway
    with threshold stripes needs it > 0."""
    return 2.0 * half_width - 2.0 * edge_line_width - 3.0


@dc.dataclass
class RunwaySpec:
    """A procedural runway. ``half_width`` is B of the failure set ``|px| >= B``."""
    name: str = "CUSTOM"
    half_width: float = bounded(10.0, 0.0, MAX_HALF_WIDTH, low_open=True, unit="m")
    length: float = bounded(2000.0, 300.0, MAX_LENGTH, low_open=True, unit="m")
    heading_deg: float = bounded(0.0, -360.0, 360.0, unit="deg")   # compass; sets the sun
    surface: SurfaceSpec = dc.field(default_factory=SurfaceSpec)
    markings: MarkingsSpec = dc.field(default_factory=MarkingsSpec)
    lights: LightsSpec = dc.field(default_factory=LightsSpec)
    taxiway_lines: List[TaxiwayLine] = bounded(default_factory=list, items=(0, 20))
    buildings: int = bounded(4, 0, MAX_BUILDINGS, whole=True)   # hangars beside the runway
    building_tone: List[float] = bounded(default_factory=lambda: [0.62, 0.60, 0.56], **RGB)

    def validate(self, where="runway_spec"):
        """Raise ValueError naming the first bad field (as ``where.field``). Sizes are
        bounded so that the scene stays a few thousand shapes (the pavement is tiled in
        ~8 m slabs, the centreline dashed, lights and taxiway lines built piece by
        piece)."""
        check_name(f"{where}.name", self.name)
        where = f"{where}."
        check_bounds(self, where)
        if self.surface.kind not in SURFACES:
            raise ValueError(f"{where}surface.kind must be one of {SURFACES}, got "
                             f"{short(self.surface.kind)}")
        for part in ("surface", "markings", "lights"):
            check_bounds(getattr(self, part), f"{where}{part}.")
        marks = self.markings
        if marks.threshold_stripes and stripe_room(self.half_width, marks.edge_line_width) <= 0:
            raise ValueError(f"{where}half_width {self.half_width:g} m leaves no room for the "
                             f"threshold stripes (2 x half_width - 2 x markings.edge_line_width "
                             f"must exceed 3 m): widen it, or set markings.threshold_stripes: 0")
        for i, line in enumerate(self.taxiway_lines):
            check_bounds(line, f"{where}taxiway_lines[{i}].")
            if line.side not in (-1, 1):
                raise ValueError(f"{where}taxiway_lines[{i}].side must be +1 or -1, got "
                                 f"{short(line.side)}")
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
