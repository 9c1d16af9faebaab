from pathlib import Path

import numpy as np
import pytest

from reachwatch.diagrams import StateRenderer
from reachwatch.systems import (RUNWAYS, SKIES, AircraftGeometry, CameraConfig, Environment,
                                MarkingsSpec, RunwaySpec, TaxiwayLine, lighting_for, sun_elevation_deg)
from pydrake.geometry import SceneGraph


def test_geometry_pose_follows_state():
    sg = SceneGraph()
    geometry = AircraftGeometry(scene_graph=sg)
    context = geometry.CreateDefaultContext()
    geometry.get_state_input_port().FixValue(context, [2.0, 150.0, 0.3])
    poses = geometry.get_geometry_pose_output_port().Eval(context)
    X = poses.value(geometry.frame_id)
    np.testing.assert_allclose(X.translation(), [150.0, 2.0, 0.0])
    np.testing.assert_allclose(X.rotation().ToRollPitchYaw().yaw_angle(), 0.3)


def test_camera_mount_is_right_wing_looking_forward_and_down():
    config = CameraConfig()
    X_BC = config.X_BC()
    p = X_BC.translation()
    assert p[1] == pytest.approx(-2.17) and p[2] == pytest.approx(1.92)
    axis = X_BC.rotation().col(2)          # optical axis in the body frame
    assert axis[0] > 0.98                  # forward
    assert axis[1] < 0                     # yawed outward (right)
    assert axis[2] == pytest.approx(-np.sin(np.deg2rad(5.0)), abs=1e-9)   # 5 deg down
    assert np.degrees(config.fov_y_rad) < 80.0


def test_image_shape_and_copy(small_camera):
    r = StateRenderer(environment=Environment(), camera=small_camera)
    a = r.render([0.0, 120.0, 0.0])
    b = r.render([5.0, 120.0, 0.3])
    assert a.shape == (64, 128, 3) and a.dtype == np.uint8
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 2.0   # a was copied, not a view


def _paint_column(image):
    """Mean column of bright (white paint) pixels in the lower half."""
    lower = image[image.shape[0] // 2:].astype(int)
    rows, cols = np.nonzero(lower.min(axis=2) > 180)
    assert len(cols) > 5, "no paint visible"
    return cols.mean()


def _centreline_only(camera):
    """A wide runway whose only paint in view is the centreline."""
    spec = RunwaySpec(name="WIDE", half_width=60.0,
                      markings=MarkingsSpec(threshold_stripes=0, touchdown_zone=[]))
    return StateRenderer(environment=Environment(runway="WIDE", runway_spec=spec),
                         camera=camera)


def test_centreline_moves_right_in_image_when_aircraft_is_left(small_camera):
    r = _centreline_only(small_camera)
    left = _paint_column(r.render([3.0, 70.0, 0.0]))     # px > 0: aircraft left of centre
    centre = _paint_column(r.render([0.0, 70.0, 0.0]))
    right = _paint_column(r.render([-3.0, 70.0, 0.0]))
    assert left > centre + 3 > right + 6


def test_heading_left_shifts_scene_right(small_camera):
    r = _centreline_only(small_camera)
    assert _paint_column(r.render([0.0, 70.0, np.deg2rad(8)])) > \
        _paint_column(r.render([0.0, 70.0, np.deg2rad(-8)])) + 5


def test_night_is_darker_than_morning_and_evening_is_warm(small_camera):
    state = [0.0, 150.0, 0.0]
    mean = {h: StateRenderer(environment=Environment("KATL", h, "clear"),
                             camera=small_camera).render(state).reshape(-1, 3).mean(0)
            for h in (9.0, 17.0, 21.0)}
    assert mean[21.0].mean() < 0.5 * mean[9.0].mean()
    assert mean[17.0][0] - mean[17.0][2] > mean[9.0][0] - mean[9.0][2]   # redder


def test_night_lights_are_lit():
    assert lighting_for(Environment("KMWH", 21.0, "clear")).lamps_lit
    assert not lighting_for(Environment("KMWH", 9.0, "clear")).lamps_lit
    assert sun_elevation_deg(21.0) < 0 < sun_elevation_deg(17.0) < sun_elevation_deg(9.0)


def test_overcast_differs_from_clear(small_camera):
    a = StateRenderer(environment=Environment("KMWH", 9.0, "clear"),
                      camera=small_camera).render([0.0, 150.0, 0.0])
    b = StateRenderer(environment=Environment("KMWH", 9.0, "overcast"),
                      camera=small_camera).render([0.0, 150.0, 0.0])
    sky_a, sky_b = a[:8].reshape(-1, 3).mean(0), b[:8].reshape(-1, 3).mean(0)
    assert sky_a[2] - sky_a[0] > 40 and abs(sky_b[2] - sky_b[0]) < 15   # blue vs grey


@pytest.mark.parametrize("runway", sorted(RUNWAYS))
def test_every_catalog_environment_renders(runway, tiny_camera):
    images = [StateRenderer(environment=Environment(runway, h, s),
                            camera=tiny_camera).render([0.0, 150.0, 0.0])
              for h in (9.0, 17.0, 21.0) for s in SKIES]
    assert all(im.shape == (32, 64, 3) for im in images)
    assert len({im.tobytes() for im in images}) == len(images)   # all conditions differ


def test_runways_look_different(small_camera):
    state = [0.0, 150.0, 0.0]
    images = {r: StateRenderer(environment=Environment(r, 9.0, "clear"),
                               camera=small_camera).render(state).astype(int)
              for r in RUNWAYS}
    names = sorted(images)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.abs(images[a] - images[b]).mean() > 3.0, (a, b)


def test_yellow_taxiway_lines_only_on_test_runways():
    assert RUNWAYS["KSFO"].taxiway_lines and RUNWAYS["KEWR"].taxiway_lines
    assert not any(RUNWAYS[r].taxiway_lines for r in ("KMWH", "KATL", "PAEI"))


def test_custom_runway_renders_its_own_paint(small_camera):
    spec = RunwaySpec(name="MINE", half_width=12.0,
                      taxiway_lines=[TaxiwayLine(start=80.0, side=-1, radius=40.0)])
    image = StateRenderer(environment=Environment(runway="MINE", runway_spec=spec),
                          camera=small_camera).render([0.0, 70.0, 0.0])
    yellow = (image[..., 0] > 150) & (image[..., 1] > 100) & (image[..., 2] < 80)
    assert yellow.sum() > 10


def test_bad_environment_fields_named():
    with pytest.raises(ValueError, match="environment.runway"):
        Environment(runway="EGLL").validate()
    with pytest.raises(ValueError, match="hour"):
        Environment(hour=24.0).validate()
    with pytest.raises(ValueError, match="sky"):
        Environment(sky="foggy").validate()
    with pytest.raises(ValueError, match="half_width"):
        Environment(runway_spec=RunwaySpec(half_width=-1.0)).validate()


def test_a_dropped_world_is_freed(tiny_camera):
    """A renderer's diagram (scene, renderer and all) is freed once dropped: no Python
    system of it outlives a garbage collection (pydrake keeps a system alive for good
    when its abstract output port calls a bound method of its own)."""
    import gc
    import weakref
    renderer = StateRenderer(environment=Environment("KMWH", 9.0, "clear"), camera=tiny_camera)
    renderer.render([0.0, 150.0, 0.0])
    geometry = weakref.ref(renderer.world.geometry)
    del renderer
    gc.collect()
    assert geometry() is None


def test_weak_callback_computes_and_lets_its_system_go():
    import gc
    import weakref
    from pydrake.common.value import AbstractValue
    from pydrake.systems.framework import DiagramBuilder, LeafSystem
    from reachwatch.systems import weak_callback

    class Doubler(LeafSystem):
        def __init__(self):
            super().__init__()
            self._x = self.DeclareVectorInputPort("x", 1)
            self.DeclareAbstractOutputPort("twice", lambda: AbstractValue.Make(0.0),
                                           weak_callback(self._calc))

        def _calc(self, context, output):
            output.set_value(2.0 * float(self._x.Eval(context)[0]))

    builder = DiagramBuilder()
    system = builder.AddSystem(Doubler())
    diagram = builder.Build()
    context = system.GetMyContextFromRoot(diagram.CreateDefaultContext())
    system.get_input_port(0).FixValue(context, [1.5])
    assert system.get_output_port(0).Eval(context) == 3.0
    alive = weakref.ref(system)
    del builder, system, diagram, context
    gc.collect()
    assert alive() is None


def test_a_generated_texture_is_named_after_the_code_that_made_it(monkeypatch):
    """A texture file made by other generator code (or another numpy) is another file,
    not one read back as this code's."""
    from reachwatch.systems import textures
    first = textures.texture_png("grass", (0.2, 0.5, 0.2), 0.5, seed=3, size=8)
    assert textures.texture_png("grass", (0.2, 0.5, 0.2), 0.5, seed=3, size=8) == first
    monkeypatch.setattr(textures, "GENERATOR", ("edited", textures.GENERATOR[1]))
    again = textures.texture_png("grass", (0.2, 0.5, 0.2), 0.5, seed=3, size=8)
    assert again != first and Path(again).is_file()


def test_frames_of_one_colour_are_warned_of_once(caplog, monkeypatch):
    """A renderer that fails gives blank frames without an error: a table, dataset or
    recording of them is wrong without a word. A frame with anything in it is not."""
    import logging
    import numpy as np
    import reachwatch.systems.checks as checks
    from reachwatch.diagrams.render import warn_blank_frames
    monkeypatch.setattr(checks, "WARNED", set())
    frames = np.zeros((3, 4, 5, 4), np.uint8)
    frames[..., 3] = 255                                    # alpha aside
    frames[1, 0, 0, 1] = 9                                  # one frame with a detail
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        warn_blank_frames(frames, "the dataset of KSFO_21h_clear")
        warn_blank_frames(frames, "the dataset of KSFO_21h_clear")          # said once
        warn_blank_frames(frames[1:2], "the dataset of KEWR_21h_clear")      # nothing
    assert [r.getMessage() for r in caplog.records] == [
        "the dataset of KSFO_21h_clear: 2 of 3 frames the camera rendered are of one "
        "colour: a renderer that fails gives such frames without an error; look at one "
        "with 'reachwatch render'"]


def test_runways_and_cameras_the_scene_cannot_build_are_refused_naming_the_field():
    """Before: each validated, then Drake failed building the scene or the camera with a
    message naming no field (a box of negative depth; a depth range past its end)."""
    import pytest
    from pydrake.geometry import SceneGraph
    from reachwatch.systems import CameraConfig, MarkingsSpec, RunwaySpec, TaxiwayLine
    from reachwatch.systems.camera import make_wing_camera
    for spec, message in [
            (RunwaySpec(half_width=2.0), r"runway_spec.half_width 2 m leaves no room for the "
                                         r"threshold stripes"),
            (RunwaySpec(markings=MarkingsSpec(edge_line_width=0.0)),
             r"runway_spec.markings.edge_line_width must be"),
            (RunwaySpec(markings=MarkingsSpec(centreline_width=0.0)),
             r"runway_spec.markings.centreline_width must be"),
            (RunwaySpec(taxiway_lines=[TaxiwayLine(width=0.0)]),
             r"runway_spec.taxiway_lines\[0\].width must be")]:
        with pytest.raises(ValueError, match=message):
            spec.validate()
    RunwaySpec(half_width=2.0, markings=MarkingsSpec(threshold_stripes=0)).validate()
    for config in (CameraConfig(near=60.0), CameraConfig(near=0.5, far=50.0)):
        make_wing_camera(frame_id=SceneGraph().world_frame_id(), config=config,
                         renderer_name="renderer")
