"""The runway scene: anchored perception geometry registered in a `SceneGraph`.

World frame: x downtrack (py, threshold at 0), y left (px), z up.
"""

import numpy as np
from pydrake.geometry import (Box, GeometryInstance, Mesh, PerceptionProperties,
                              RenderLabel, Rgba, SceneGraph)
from pydrake.math import RigidTransform, RotationMatrix

from .runway import stripe_room
from .textures import texture_png, tiled_quad_obj

#: How far the scene reaches (m): behind the threshold, sideways, and ahead.
GROUND_X = (-400.0, 3000.0)
GROUND_Y = (-700.0, 700.0)
LABELS = {"ground": 1, "runway": 2, "paint": 3, "taxiway_paint": 4, "lamp": 5, "building": 6}


def _props(label, rgb=None, texture=None):
    props = PerceptionProperties()
    if texture is not None:
        props.AddProperty("phong", "diffuse_map", texture)
    else:
        props.AddProperty("phong", "diffuse", Rgba(*rgb, 1.0))
    props.AddProperty("label", "id", RenderLabel(LABELS[label]))
    return props


class _Registrar:
    def __init__(self, scene_graph: SceneGraph, source_name: str):
        self._sg = scene_graph
        self._source = scene_graph.RegisterSource(source_name)
        self.count = 0

    def add(self, name, shape, pose, props):
        instance = GeometryInstance(pose, shape, name)
        instance.set_perception_properties(props)
        self._sg.RegisterAnchoredGeometry(self._source, instance)
        self.count += 1

    def box(self, name, center, size, props, yaw=0.0):
        self.add(name, Box(*size), RigidTransform(RotationMatrix.MakeZRotation(yaw), center),
                 props)


def _paint_rectangle(reg, name, x0, x1, y0, y1, props, z=0.012):
    reg.box(name, [(x0 + x1) / 2, (y0 + y1) / 2, z / 2], [x1 - x0, y1 - y0, z], props)


def _taxiway_line(reg, index, line, props):
    """A yellow lead-in line: a circular arc off the centreline, then straight."""
    step = 3.0
    s, r = line.side, line.radius
    turn = np.deg2rad(line.turn_deg)
    n_arc = max(2, int(np.ceil(r * turn / step)))
    points = [(line.start + r * np.sin(a), s * r * (1 - np.cos(a)))
              for a in np.linspace(0.0, turn, n_arc + 1)]
    heading = s * turn
    x, y = points[-1]
    for k in range(1, 15):
        points.append((x + k * step * np.cos(heading), y + k * step * np.sin(heading)))
    for k, ((xa, ya), (xb, yb)) in enumerate(zip(points[:-1], points[1:])):
        length = np.hypot(xb - xa, yb - ya) + 0.2
        reg.box(f"taxiway_{index}_{k}", [(xa + xb) / 2, (ya + yb) / 2, 0.007],
                [length, line.width, 0.014], props, yaw=np.arctan2(yb - ya, xb - xa))


def add_runway_scene(scene_graph: SceneGraph, spec, *, lamps_lit: bool = False,
                     source_name: str = "runway_scene") -> int:
    """Registers ground, pavement, markings, lights and buildings of ``spec``
    (a `RunwaySpec`) as anchored perception geometry. Returns the geometry count."""
    reg = _Registrar(scene_graph, source_name)
    surf, marks, B = spec.surface, spec.markings, spec.half_width
    grass = texture_png("grass", surf.grass_tone, 0.6, surf.texture_seed)
    reg.add("ground", Mesh(tiled_quad_obj(GROUND_X, GROUND_Y, -0.02, 40.0)),
            RigidTransform(), _props("ground", texture=grass))
    pavement = texture_png(surf.kind, surf.tone, surf.roughness, surf.texture_seed)
    x_end = min(spec.length, GROUND_X[1])
    slab = 2.0 * B / max(1, round(2.0 * B / 8.0))
    reg.add("runway", Mesh(tiled_quad_obj((-60.0, x_end), (-B, B), 0.0, slab)),
            RigidTransform(), _props("runway", texture=pavement))

    paint = _props("paint", rgb=marks.paint)
    if marks.edge_lines:
        w = marks.edge_line_width
        for side in (-1, 1):
            y_in = side * (B - w)
            _paint_rectangle(reg, f"edge_{side}", -60.0, x_end, min(y_in, side * B),
                             max(y_in, side * B), paint)
    if marks.centreline:
        half = marks.centreline_width / 2
        x = 60.0
        while x + marks.dash_length < x_end:
            _paint_rectangle(reg, f"centre_{int(x)}", x, x + marks.dash_length, -half, half,
                             paint)
            x += marks.dash_length + marks.dash_gap
    if marks.threshold_stripes:
        n = marks.threshold_stripes
        usable = stripe_room(B, marks.edge_line_width)
        pitch = usable / (n + 1)
        for k in range(n):
            y = -usable / 2 + pitch * (k + 0.5 + (k >= n // 2))   # gap at the centre
            _paint_rectangle(reg, f"threshold_{k}", 6.0, 36.0, y - 0.45 * pitch,
                             y + 0.45 * pitch, paint)
    for j, x0 in enumerate(marks.touchdown_zone):
        bars = 3 if j == 0 else 2
        for side in (-1, 1):
            for k in range(bars):
                y_in = side * (3.0 + 2.0 * k)
                _paint_rectangle(reg, f"tdz_{j}_{side}_{k}", x0, x0 + 22.5,
                                 min(y_in, y_in + side * 1.2), max(y_in, y_in + side * 1.2),
                                 paint)
    yellow = _props("taxiway_paint", rgb=[0.95, 0.75, 0.10])
    for i, line in enumerate(spec.taxiway_lines):
        _taxiway_line(reg, i, line, yellow)

    if spec.lights.enabled:
        lamp_rgb = spec.lights.color if lamps_lit else list(0.55 * np.asarray(spec.lights.color))
        lamp = _props("lamp", rgb=lamp_rgb)
        x, k = 0.0, 0
        while x < x_end:
            for side in (-1, 1):
                reg.box(f"lamp_{k}_{side}", [x, side * (B + spec.lights.offset), 0.25],
                        [0.35, 0.35, 0.5], lamp)
            x += spec.lights.spacing
            k += 1
    building = _props("building", rgb=spec.building_tone)
    rng = np.random.default_rng(surf.texture_seed)
    for k in range(spec.buildings):
        side = 1 if k % 2 == 0 else -1
        size = rng.uniform([25, 20, 8], [60, 40, 18])
        center = [rng.uniform(150, 1200), side * (B + rng.uniform(90, 260)), size[2] / 2]
        reg.box(f"building_{k}", center, size, building, yaw=rng.uniform(-0.3, 0.3))
    return reg.count
