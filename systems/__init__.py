"""Drake `LeafSystem`s and scene pieces of the closed loop. Nothing here knows about
grids, datasets or files beyond the generated texture cache."""

import os

# torch's OpenMP threads spin-wait after each op by default, stealing the cores that
# Mesa's llvmpipe renders on; passive waiting made the per-state sweep ~25 % faster
# here. Only effective if set before torch is first imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# torch imports triton lazily (e.g. when an optimizer is built). triton bundles its own
# LLVM, and so does Mesa's llvmpipe, which loads at Drake's first render; loading triton
# second segfaults, so load it first. Render with pydrake only after importing reachwatch.
try:
    import triton  # noqa: F401
except ImportError:
    pass

from .camera import AircraftGeometry, CameraConfig, make_wing_camera
from .detector import (AnomalyDetector, DetectorConfig, SmallDetectorCNN, build_detector,
                       detector_input, resize_for_detector)
from .environment import SKIES, Environment, test_environments, training_environments
from .lighting import Lighting, lighting_for, render_engine_params, sun_elevation_deg
from .models import (ESTIMATE_UNITS, PreprocessConfig, SmallTaxiCNN, TaxiNetConfig,
                     TinyTaxiNet, build_taxinet, preprocess)
from .plant import MAX_STEERING_RAD, NOMINAL_SPEED_MPS, WHEELBASE_M, TaxiPlant, taxi_dynamics
from .runway import RUNWAYS, LightsSpec, MarkingsSpec, RunwaySpec, SurfaceSpec, TaxiwayLine
from .random_environments import RandomEnvironments, RandomRunwayRanges, random_runway
from .scene import add_runway_scene
from .dead_reckoning import DeadReckoning, propagate_estimate
from .history_model import (INPUT_NORMS, TEMPORAL_MODELS, HistoryMonitorConfig,
                            HistoryRiskModel, platt)
from .risk_ensemble import (MAX_MEMBERS, GroupedEncoder, HistoryRiskEnsemble, check_members,
                            grouped_gru)
from .frame_worker import FrameWorker
from .history_monitor import FrameEncoder, HistoryMonitor
from .flag_filter import FlagFilter, check_k_of_n, confirmed_flags
from .ports import weak_callback
from .switch import (DEFAULT_FALLBACKS, STEERING, STEERING_ALIASES, STRATEGIES,
                     STRATEGY_REGISTRY, Fallback, FallbackSwitch, SpeedStrategy,
                     check_resume_acceleration, fallback_name, fallback_parts, next_speed)
from .taxinet import (PX_GAIN_DEG_PER_M, THETA_GAIN, ProportionalController, TaxiNet,
                      TrueStateEstimator)

__all__ = [
    "INPUT_NORMS", "TEMPORAL_MODELS", "FrameEncoder", "FrameWorker", "HistoryMonitor",
    "HistoryMonitorConfig", "HistoryRiskModel", "platt",
    "MAX_MEMBERS", "GroupedEncoder", "HistoryRiskEnsemble", "check_members", "grouped_gru",
    "FlagFilter", "check_k_of_n", "confirmed_flags", "weak_callback",
    "RandomEnvironments", "RandomRunwayRanges", "random_runway",
    "AircraftGeometry", "CameraConfig", "make_wing_camera", "SKIES", "Environment",
    "test_environments", "training_environments", "Lighting", "lighting_for",
    "render_engine_params", "sun_elevation_deg", "NOMINAL_SPEED_MPS", "WHEELBASE_M",
    "MAX_STEERING_RAD",
    "TaxiPlant", "taxi_dynamics", "RUNWAYS", "LightsSpec", "MarkingsSpec", "RunwaySpec",
    "SurfaceSpec", "TaxiwayLine", "add_runway_scene", "ESTIMATE_UNITS", "PreprocessConfig",
    "SmallTaxiCNN", "TaxiNetConfig", "TinyTaxiNet", "build_taxinet", "preprocess",
    "PX_GAIN_DEG_PER_M", "THETA_GAIN", "ProportionalController", "TaxiNet", "TrueStateEstimator", "AnomalyDetector",
    "DetectorConfig", "SmallDetectorCNN", "build_detector", "detector_input", "resize_for_detector", "STEERING", "STEERING_ALIASES", "STRATEGIES", "STRATEGY_REGISTRY", "SpeedStrategy", "Fallback", "FallbackSwitch",
    "next_speed", "check_resume_acceleration", "DEFAULT_FALLBACKS", "fallback_name", "fallback_parts", "DeadReckoning", "propagate_estimate",
]
