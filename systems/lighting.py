"""Sun, sky and night lighting for an `Environment`, as `RenderEngineVtkParams`.

VTK's Phong model has no ambient term, so a dim "sky" fill light stands in for it.
At night a horizontal light travelling down the runway lights only vertical faces
(the lamp housings), so edge lights glow while the pavement stays dark, and the
aircraft's taxi light (a spot in the camera frame) lights the pavement ahead.
"""

import dataclasses as dc

import numpy as np
from pydrake.geometry import LightParameter, RenderEngineVtkParams
from pydrake.geometry import Rgba

SUNRISE_H, SUNSET_H, NOON_ELEVATION_DEG = 6.0, 18.5, 55.0


def sun_elevation_deg(hour: float) -> float:
    """Solar elevation (deg) at local ``hour``; negative below the horizon."""
    day = (hour - SUNRISE_H) / (SUNSET_H - SUNRISE_H)
    if 0.0 <= day <= 1.0:
        return NOON_ELEVATION_DEG * np.sin(np.pi * day)
    hours_dark = min(abs(hour - SUNSET_H) % 24, abs(hour + 24 - SUNSET_H) % 24,
                     abs(SUNRISE_H - hour) % 24)
    return -min(30.0, 8.0 * hours_dark)


def sun_direction(hour: float, runway_heading_deg: float) -> np.ndarray:
    """Unit vector the sunlight travels along, in the runway world frame
    (x downtrack, y left, z up)."""
    elevation = np.deg2rad(sun_elevation_deg(hour))
    azimuth = 90.0 + 180.0 * (hour - SUNRISE_H) / (SUNSET_H - SUNRISE_H)  # compass
    relative = np.deg2rad(azimuth - runway_heading_deg)                   # clockwise
    to_sun = np.array([np.cos(elevation) * np.cos(relative),
                       -np.cos(elevation) * np.sin(relative), np.sin(elevation)])
    return -to_sun


@dc.dataclass
class Lighting:
    """What the renderer needs for one environment."""
    lights: list
    sky_rgb: np.ndarray
    daylight: float          # 0 (night) .. 1 (full day)
    lamps_lit: bool


def _mix(a, b, t):
    return (1.0 - t) * np.asarray(a, float) + t * np.asarray(b, float)


def lighting_for(environment) -> Lighting:
    """Lights and sky colour for ``environment`` (hour and sky of an `Environment`)."""
    spec = environment.spec()
    elevation = sun_elevation_deg(environment.hour)
    daylight = float(np.clip((elevation + 6.0) / 21.0, 0.0, 1.0))   # ramps over -6..15 deg
    warmth = float(np.clip((35.0 - elevation) / 18.0, 0.0, 1.0))    # low sun is warm
    overcast = environment.sky == "overcast"
    sun_rgb = _mix([1.0, 0.97, 0.92], [1.0, 0.62, 0.36], warmth)
    if overcast:   # no direct sun: brightness follows the sun's height, colour stays grey
        daylight *= 0.65 + 0.35 * float(np.clip(elevation / 35.0, 0.0, 1.0))
        sky = _mix([0.05, 0.05, 0.06], [0.66, 0.68, 0.70], daylight)
    else:
        sky = _mix([0.02, 0.03, 0.07], _mix([0.50, 0.68, 0.92], [0.93, 0.64, 0.45], warmth),
                   daylight)
    lights = []
    if daylight > 0.0:
        if overcast:   # flat, diffuse: light from straight above plus a soft fill
            lights.append(LightParameter(type="directional", frame="world",
                                         direction=[0.1, 0.05, -1.0],
                                         color=Rgba(0.95, 0.96, 1.0), intensity=0.85 * daylight))
            lights.append(LightParameter(type="directional", frame="world",
                                         direction=[0.6, 0.3, -0.4],
                                         color=Rgba(0.9, 0.92, 0.95), intensity=0.35 * daylight))
        else:
            lights.append(LightParameter(
                type="directional", frame="world",
                direction=sun_direction(environment.hour, spec.heading_deg).tolist(),
                color=Rgba(*sun_rgb), intensity=1.15 * daylight))
            lights.append(LightParameter(type="directional", frame="world",
                                         direction=[0.0, 0.0, -1.0],
                                         color=Rgba(0.75, 0.82, 1.0), intensity=0.35 * daylight))
    lamps_lit = daylight < 0.5 and spec.lights.enabled
    if daylight < 1.0:
        night = 1.0 - daylight
        if overcast:    # no moon; low cloud reflects the airfield's glow
            sky = np.maximum(sky, [0.10, 0.09, 0.08])
        else:
            lights.append(LightParameter(type="directional", frame="world",     # moon
                                         direction=[0.3, -0.2, -1.0],
                                         color=Rgba(0.6, 0.7, 1.0), intensity=0.10 * night))
        lights.append(LightParameter(type="spot", frame="camera",           # taxi light
                                     position=[0.0, 0.0, 0.0], direction=[0.0, 0.25, 1.0],
                                     color=Rgba(1.0, 0.95, 0.85), intensity=2.0 * night,
                                     cone_angle=50.0, attenuation_values=[1.0, 0.0, 0.0004]))
    if lamps_lit:       # horizontal: lights the lamp faces, never the flat ground
        lights.append(LightParameter(type="directional", frame="world",
                                     direction=[1.0, 0.0, 0.0],
                                     color=Rgba(*spec.lights.color), intensity=3.0))
    return Lighting(lights=lights, sky_rgb=sky, daylight=daylight, lamps_lit=lamps_lit)


def render_engine_params(lighting: Lighting, *, shadows: bool = False) -> RenderEngineVtkParams:
    """`RenderEngineVtkParams` for ``lighting``; shadows (costly on the CPU) optional."""
    params = RenderEngineVtkParams(lights=lighting.lights,
                                   default_clear_color=lighting.sky_rgb.tolist())
    if shadows:
        params.cast_shadows = True
        params.shadow_map_size = 1024
        params.force_to_pbr = True
    return params
