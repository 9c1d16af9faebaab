"""Drake `LeafSystem`s and scene pieces of the closed loop. Nothing here knows about
grids, datasets or files beyond the generated texture cache."""

from .camera import AircraftGeometry, CameraConfig, make_wing_camera
from .environment import SKIES, Environment, test_environments, training_environments
from .lighting import Lighting, lighting_for, render_engine_params, sun_elevation_deg
from .plant import NOMINAL_SPEED_MPS, WHEELBASE_M, TaxiPlant, taxi_dynamics
from .runway import RUNWAYS, LightsSpec, MarkingsSpec, RunwaySpec, SurfaceSpec, TaxiwayLine
from .scene import add_runway_scene

__all__ = [
    "AircraftGeometry", "CameraConfig", "make_wing_camera", "SKIES", "Environment",
    "test_environments", "training_environments", "Lighting", "lighting_for",
    "render_engine_params", "sun_elevation_deg", "NOMINAL_SPEED_MPS", "WHEELBASE_M",
    "TaxiPlant", "taxi_dynamics", "RUNWAYS", "LightsSpec", "MarkingsSpec", "RunwaySpec",
    "SurfaceSpec", "TaxiwayLine", "add_runway_scene",
]
