"""What this process renders with: a fixed small scene rendered by Drake's VTK engine,
and the OpenGL libraries that render it. Two machines (Mesa's llvmpipe on a CPU, a GPU
driver, another Mesa) may render one scene to different pixels, so every fingerprint
carries `render_stack` (a cache filled on one is not reused on the other) and a Dask
worker whose stack differs from the driver's is refused before any work."""

import hashlib
import os
import threading

from reachwatch.systems.files import file_hash

#: The probe image's size (pixels); small, so the probe costs one render's setup.
PROBE_SIZE = 48

#: The drivers that draw the image, by the start of their file name: Mesa's gallium
#: and DRI drivers, NVIDIA's GL cores. Each one loaded is named in the render stack
#: with a hash of its file (a Mesa build's file names carry no version); Mesa's
#: llvmpipe also by the LLVM it compiles with (``libLLVM-15``: named, not hashed).
#: Not the dispatchers (libglvnd's libGL, libEGL) nor the EGL or GLX vendor front ends,
#: which draw nothing and which a process may load either or both of.
RENDER_DRIVERS = ("libgallium", "swrast_dri", "kms_swrast_dri", "radeonsi_dri", "iris_dri",
                  "zink_dri", "nouveau_dri", "virtio_gpu_dri", "libnvidia-glcore",
                  "libnvidia-eglcore")
COMPILERS = ("libLLVM",)


def _probe_image(*, shadows: bool = False):
    """The RGBA bytes of a fixed scene (a box and a sphere, lit and coloured) rendered
    by a fresh `RenderEngineVtk`; with ``shadows``, by one that casts shadows in
    physically based shading, as a scenario with ``shadows`` renders."""
    import numpy as np
    from pydrake.geometry import (Box, ClippingRange, ColorRenderCamera, GeometryInstance,
                                  LightParameter, MakePhongIllustrationProperties,
                                  MakeRenderEngineVtk, PerceptionProperties, RenderCameraCore,
                                  RenderEngineVtkParams, RenderLabel, Rgba, SceneGraph,
                                  Sphere)
    from pydrake.math import RigidTransform, RollPitchYaw
    from pydrake.systems.sensors import CameraInfo

    params = RenderEngineVtkParams()
    if shadows:
        params.lights = [LightParameter(type="directional", frame="world",
                                        direction=[0.4, 0.3, -1.0], color=Rgba(1, 1, 1),
                                        intensity=1.0)]
        params.cast_shadows = True
        params.shadow_map_size = 256
        params.force_to_pbr = True
    scene_graph = SceneGraph()
    scene_graph.AddRenderer("probe", MakeRenderEngineVtk(params))
    source = scene_graph.RegisterSource("render_stack")
    shapes = [(Box(1.0, 0.6, 0.4), [0.0, 0.0, 0.0], Rgba(0.8, 0.3, 0.2, 1.0)),
              (Sphere(0.35), [0.7, 0.3, 0.2], Rgba(0.2, 0.5, 0.9, 1.0)),
              (Box(4.0, 4.0, 0.02), [0.0, 0.0, -0.21], Rgba(0.6, 0.6, 0.55, 1.0))]
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
    # the camera looks along its z axis, from above and in front, at the shapes
    pose = RigidTransform(RollPitchYaw(-2.0, 0.0, 0.4), [1.2, -2.6, 1.6])
    image = query.RenderColorImage(camera, scene_graph.world_frame_id(), pose)
    return np.asarray(image.data).tobytes()


def _loaded_libraries() -> dict:
    """``{file name: hash of the file}`` of the drivers (`RENDER_DRIVERS`) mapped into
    this process, and ``{file name: ""}`` of the `COMPILERS`; empty where
    ``/proc/self/maps`` is not readable."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps
                     if len(line.split()) >= 6 and line.split()[-1].startswith("/")}
    except OSError:
        return {}
    found = {}
    for path in sorted(paths):
        name = os.path.basename(path)
        if name.startswith(RENDER_DRIVERS):
            try:
                found[name] = file_hash(path, 16)
            except OSError:
                found[name] = "unreadable"
        elif name.startswith(COMPILERS):
            found[name] = ""
    return found


#: Held while a thread of this process builds a renderer (a diagram with a camera and
#: its Context, or the probe scene): two renderers built at once in one process (VTK
#: over EGL, llvmpipe) do not always draw the same pixels afterwards. Rendering itself
#: needs no lock. Reentrant: a build may build within it.
BUILD_LOCK = threading.RLock()

_STACK = []


def render_stack() -> dict:
    """``{"probe": SHA-256 of the probe scene's pixels, plain and with shadows,
    "libraries": the drivers that drew them (`_loaded_libraries`)}``, once per process.
    A probe that cannot render raises a one-line RuntimeError: reachwatch renders every
    label it makes."""
    if _STACK:
        return dict(_STACK[0])
    with BUILD_LOCK:
        if not _STACK:
            try:
                pixels = _probe_image() + _probe_image(shadows=True)
            except Exception as e:
                raise RuntimeError(f"rendering a probe image failed ({type(e).__name__}: "
                                   f"{str(e).splitlines()[0][:200] if str(e) else ''}); "
                                   f"reachwatch needs Drake's VTK renderer (headless: Mesa "
                                   f"EGL or a GPU driver)") from None
            _STACK.append({"probe": hashlib.sha256(pixels).hexdigest()[:32],
                           "libraries": _loaded_libraries()})
        return dict(_STACK[0])
