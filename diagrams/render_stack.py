"""What this process renders with: a fixed small scene rendered by Drake's VTK engine,
and the OpenGL libraries that render it. Two machines (Mesa's llvmpipe on a CPU, a GPU
driver, another Mesa) may render one scene to different pixels, so every fingerprint
carries `render_stack` (a cache filled on one is not reused on the other) and a Dask
worker whose stack differs from the driver's is refused before any work."""

import functools
import hashlib
import os

#: The probe image's size (pixels); small, so the probe costs one render's setup.
PROBE_SIZE = 48

#: Shared libraries, by the start of their file name, that draw the image: the EGL and
#: GLX vendor libraries and the drivers (Mesa's gallium and DRI drivers, NVIDIA's),
#: whose file names carry their versions. Not the dispatchers (libglvnd's libGL,
#: libEGL), which draw nothing, nor LLVM, which other libraries (triton) may load too.
RENDER_LIBRARIES = ("libEGL_", "libGLX_", "libgallium", "libnvidia-egl", "libnvidia-glcore",
                    "libnvidia-gl", "swrast_dri", "kms_swrast_dri", "radeonsi_dri",
                    "iris_dri", "zink_dri", "nouveau_dri", "virtio_gpu_dri")


def _probe_image():
    """The RGBA bytes of a fixed scene (a box and a sphere, lit and coloured) rendered
    by a fresh `RenderEngineVtk`."""
    import numpy as np
    from pydrake.geometry import (Box, ClippingRange, ColorRenderCamera, GeometryInstance, MakePhongIllustrationProperties,
                                  MakeRenderEngineVtk, PerceptionProperties, RenderCameraCore,
                                  RenderEngineVtkParams, RenderLabel, Rgba, SceneGraph,
                                  Sphere)
    from pydrake.math import RigidTransform, RollPitchYaw
    from pydrake.systems.sensors import CameraInfo

    scene_graph = SceneGraph()
    scene_graph.AddRenderer("probe", MakeRenderEngineVtk(RenderEngineVtkParams()))
    source = scene_graph.RegisterSource("render_stack")
    shapes = [(Box(1.0, 0.6, 0.4), [0.0, 0.0, 0.0], Rgba(0.8, 0.3, 0.2, 1.0)),
              (Sphere(0.35), [0.7, 0.3, 0.2], Rgba(0.2, 0.5, 0.9, 1.0))]
    for i, (shape, position, color) in enumerate(shapes):
        instance = GeometryInstance(RigidTransform(position), shape, f"shape{i}")
        perception = PerceptionProperties()
        perception.AddProperty("phong", "diffuse", color)
        perception.AddProperty("label", "id", RenderLabel(i + 1))
        instance.set_perception_properties(perception)
        instance.set_illustration_properties(MakePhongIllustrationProperties(color.rgba))
        scene_graph.RegisterAnchoredGeometry(source, instance)
    context = scene_graph.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(context)
    core = RenderCameraCore("probe", CameraInfo(PROBE_SIZE, PROBE_SIZE, 0.9),
                            ClippingRange(0.1, 10.0), RigidTransform())
    camera = ColorRenderCamera(core, False)
    # the camera looks along its z axis, from above and in front, at the two shapes
    pose = RigidTransform(RollPitchYaw(-2.0, 0.0, 0.4), [1.2, -2.6, 1.6])
    image = query.RenderColorImage(camera, scene_graph.world_frame_id(), pose)
    return np.asarray(image.data).tobytes()


def _loaded_libraries() -> list:
    """File names of the rendering libraries (`RENDER_LIBRARIES`) mapped into this
    process, sorted; empty where ``/proc/self/maps`` is not readable."""
    try:
        with open("/proc/self/maps") as maps:
            names = {os.path.basename(line.split()[-1]) for line in maps
                     if len(line.split()) >= 6 and "/" in line.split()[-1]}
    except OSError:
        return []
    return sorted(n for n in names if n.startswith(RENDER_LIBRARIES))


@functools.lru_cache(maxsize=None)
def render_stack() -> dict:
    """``{"probe": SHA-256 of the probe scene's pixels, "libraries": the rendering
    libraries loaded to draw it}``, once per process. A probe that cannot render raises
    a one-line RuntimeError: reachwatch renders every label it makes."""
    try:
        pixels = _probe_image()
    except Exception as e:
        raise RuntimeError(f"rendering a probe image failed ({type(e).__name__}: "
                           f"{str(e).splitlines()[0][:200] if str(e) else ''}); reachwatch "
                           f"needs Drake's VTK renderer (headless: Mesa EGL or a GPU "
                           f"driver)") from None
    return {"probe": hashlib.sha256(pixels).hexdigest()[:32],
            "libraries": _loaded_libraries()}
