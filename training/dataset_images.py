"""A dataset's images, rendered chunk by chunk on any executor (`reach.chunks`): each
chunk is a task that renders its states with the application's camera, runs the
controller's estimator and the ensemble's on the full frames, resizes them as the
detector does, and returns the arrays; the driver writes them (`dataset_files.ImageStore`).
A worker thread builds its renderer and networks once and keeps them for later chunks."""

import dataclasses as dc
import inspect

import numpy as np

from reachwatch.diagrams import ControllerProbe, make_controller, user_code
from reachwatch.diagrams.controller import estimate_size
from reachwatch.diagrams.render import check_frame_size, warn_blank_frames
from reachwatch.reach.application import ApplicationRef
from reachwatch.reach.thread_kept import ThreadKept
from reachwatch.systems import resize_for_detector


def estimator(controller):
    """A function ``(N, H, W, 3) images -> (N, k)`` estimates of ``controller`` (one batch
    when it offers ``estimate(images)``, as TaxiNet's does; else image by image through
    its ``estimate`` port), and k. A batch of another shape is refused in one line: a
    method ``estimate`` that takes one image would else be broadcast into every row."""
    size = estimate_size(controller)
    if not size:
        return (lambda images: np.zeros((len(images), 0))), 0
    if callable(getattr(controller, "estimate", None)):
        batch = controller.estimate

        def checked(images):
            out = np.asarray(batch(images))
            if out.shape != (len(images), size):
                raise ValueError(f"the controller's estimate(images) returned shape "
                                 f"{out.shape} for {len(images)} images: a batch estimate "
                                 f"returns ({len(images)}, {size}), one row per image of "
                                 f"its estimate port's size")
            return out
        return checked, size
    probe = ControllerProbe(controller)
    return (lambda images: np.stack([probe.outputs(image)[1] for image in images])), size


@dc.dataclass
class ImageTools:
    """What renders and estimates a dataset's images: the application's renderer, the
    controller's estimator (``estimate_size`` numbers per image) and the ensemble's."""
    renderer: object
    estimate: object
    estimate_size: int
    ensemble: list

    @classmethod
    def build(cls, application, scenario, ensemble=()):
        with user_code.importable(inspect.getmodule(type(application))):
            renderer = application.renderer(scenario)
            estimate, size = estimator(make_controller(scenario.controller))
            nets = [application.ensemble_estimator(c) for c in ensemble]
        return cls(renderer, estimate, size, nets)


@dc.dataclass(frozen=True)
class ImageSource:
    """Everything a chunk task needs besides its states, picklable: the application by
    its spec (`ApplicationRef`), the scenario (resolved), the ensemble's checkpoints, the
    stored image size, and ``key`` (the dataset's folder name: its content address),
    under which a worker thread keeps its `ImageTools`. ``tools``: ones built here, for
    tasks run inline (never pickled: they hold a renderer)."""
    application: ApplicationRef
    scenario: object
    ensemble: tuple
    height: int
    width: int
    key: str
    tools: ImageTools = dc.field(default=None, compare=False, repr=False)

    def __getstate__(self):
        state = dict(self.__dict__)
        state["tools"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)


#: Per worker *thread* (a render context works only on the thread that made it): source
#: key -> ImageTools, the `KEPT_TOOLS` most recently used.
KEPT_TOOLS = 2
_TOOLS = ThreadKept(KEPT_TOOLS)


def _thread_tools(source: ImageSource) -> ImageTools:
    return _TOOLS.get(source.key, lambda: ImageTools.build(
        source.application.load(), source.scenario, source.ensemble))


def render_chunk(source: ImageSource, states) -> dict:
    """The images of ``states`` ``(n, ndim)``, resized to the stored size (``images``,
    uint8), the controller's estimates of the full frames (``estimates`` ``(n, k)``)
    and the ensemble's (``ensemble`` ``(n, K, 2)``)."""
    tools = source.tools or _thread_tools(source)
    full = np.stack([tools.renderer.render(x) for x in states])
    check_frame_size(full.shape[1:], source.scenario)
    env = getattr(source.scenario, "environment", None)
    warn_blank_frames(full, f"the dataset of {env.name}" if env is not None else "a dataset")
    ensemble = np.empty((len(full), len(tools.ensemble), 2))
    for j, estimate_member in enumerate(tools.ensemble):
        out = np.asarray(estimate_member(full))
        if out.shape != (len(full), 2):     # the ensemble baseline's contract: 2 numbers
            raise ValueError(f"ensemble member {j}: the application's ensemble_estimator "
                             f"returned shape {out.shape} for {len(full)} images; the "
                             f"ensemble baseline takes ({len(full)}, 2)")
        ensemble[:, j] = out
    estimates = np.empty((len(full), tools.estimate_size))
    estimates[:] = tools.estimate(full)
    return {"images": resize_for_detector(full, source),       # as the detector system does
            "estimates": estimates, "ensemble": ensemble}
