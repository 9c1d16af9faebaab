"""An application: one closed loop the pipeline studies, and what the generic core
needs to know about it. The pipeline, training and the report call these methods and
know nothing about the plant. An application is named by a string,
``package.module:name`` or ``path/to/file.py:name`` (a subclass of `Application`, or a
function of no arguments returning one), and loaded like a controller factory
(`load_application`): its folder is importable in the driver and in every worker, and
its fingerprint covers every ``.py`` file of that folder or package
(`reachwatch.diagrams.user_code`). Nothing here names one: which application a run
file studies when it names none is the pipeline's choice
(`reachwatch.pipeline.slot_defaults.DEFAULT_APPLICATION`).

It lives in ``reach`` because its methods speak reach's terms (a `Dynamics`, a
`Grid`, a `Probe`, swept tables and `Outcomes`), and the layers above it (training,
the pipeline) are the ones that call it.

What an application is given everywhere is the run's ``scenario`` (a
`reachwatch.diagrams.Scenario`: environment, camera, controller, monitor), the same
object its loop is built from."""

import abc
import copy
import dataclasses as dc
import functools
import importlib.util
import inspect
import sys
from pathlib import Path

import numpy as np

from reachwatch.systems.checks import clip

from .application_guard import GuardHooks
from .application_runs import RealLoopHooks
from .fingerprint import fingerprint
from .sweep import sweep, sweep_key

@dc.dataclass
class NoRandomEnvironments:
    """The random family of an application that draws none: ``count`` stays 0."""
    count: int = 0
    seed: int = 0
    prefix: str = "RND"

    def validate(self, where="random"):
        if self.count:
            raise ValueError(f"{where}.count: this application draws no random "
                             f"environments; list its environments instead")
        return self

    def environments(self):
        self.validate("random")
        return []


class Application(GuardHooks, RealLoopHooks, abc.ABC):
    """What the pipeline needs from a closed loop. Subclasses define the abstract
    methods; the others have generic defaults. Every method takes the ``scenario`` the
    loop is built from; ``states`` are ``(N, n)`` arrays in the order of `axes`. What
    the guard stage asks (its fallbacks, the detector's score along runs, the guarded
    loop's runs) is in its base `reach.application_guard.GuardHooks`; the batches of
    real-loop runs the stages ask (outcomes, recordings, missions, paths), in its base
    `reach.application_runs.RealLoopHooks`."""

    #: A short name for logs and reports (e.g. ``"taxi"``).
    name = "application"
    #: The state's axis names, in order (e.g. ``("px", "py", "theta")``).
    axes = ()
    #: Their units, in the same order, as reports write a state (e.g. ``("m", "m",
    #: "rad")``; () = none said).
    axis_units = ()
    #: The axes along which a run may leave the grid's box without failing (its
    #: ``left_box`` counts the runs that did, where the swept table is clamped).
    open_axes = ()
    #: The axis of the plant's heading (rad), whose largest ``|value|`` along each
    #: real run the real-loop check reports (``max_abs_theta``; the taxi's: 2); None:
    #: none reported.
    heading_axis = None
    #: The string the application is loaded from (`load_application` sets it), which
    #: workers load it again by. An application of an importable package may name
    #: itself here (``"package.module:name"``), so that an instance made directly runs
    #: in workers too.
    spec = ""
    #: Files the loop reads that are not Python (a model of the plant, a mesh, a table
    #: of parameters): their contents are part of every key of this application, as its
    #: ``.py`` files are, so that a result is never answered from the caches after an
    #: edit to one (`data_digest`). Paths absolute, or relative to the folder of the
    #: file the application is loaded from (the run file's ``application``).
    data_files = ()

    # --- the run file's environments -------------------------------------------------
    #: The dataclass a run file's environments are loaded as (``train``, ``test``,
    #: ``guard.environments``, ``monitor.also_held_out``, ...; the run hands each to
    #: the loop as ``scenario.environment``): it has a ``name`` (a label: an
    #: environment's files and report rows are named by it) and ``validate()``, which
    #: raises a ValueError naming a bad field. None: the application names none, and a
    #: run file cannot be loaded for it.
    environment_type = None
    #: The dataclass of a family of random environments (``train_random``,
    #: ``test_random``, ``monitor.family``): fields ``count``, ``seed`` and ``prefix``,
    #: ``validate(where)``, and ``environments()``, the family's `environment_type`
    #: instances in order, each depending only on ``seed`` and its index. None: the
    #: application draws none (`NoRandomEnvironments`).
    random_environments_type = None

    #: Components of the plant's state that the controller estimates from the camera:
    #: what a history monitor's encoder also learns to estimate from each frame in
    #: training when the run file's ``monitor.state_targets`` is left out. Empty: none.
    estimated_state = ()

    def default_environment(self, role: str):
        """The environment a run file's field takes when left out (``role``:
        ``"incremental"``); default: ``environment_type()``."""
        return self.run_file_types()[0]()

    def default_random_environments(self, role: str):
        """The family a run file's field takes when left out (``role``: ``"train"``,
        ``"test"`` or ``"monitor"``); default: none drawn."""
        return self.run_file_types()[1]()

    def same_environment(self, a, b) -> bool:
        """Whether two environments a run file names alike are one (two that differ
        would mix their files and stage records); default ``a == b``."""
        return a == b

    def environment_content(self, env) -> str:
        """``env`` as what the loop sees, its name aside: two environments with the same
        content are one for training and judging, whatever they are called (a family
        drawn from the same seed under another prefix, say); default ``repr(env)``."""
        return repr(env)

    def run_file_types(self):
        """``(environment type, random family type)`` a run file is loaded with; a
        one-line ValueError when the application names no environment type, or one
        that is not a dataclass importable by its module's name (environments travel
        to workers inside scenarios: a class defined in an application's own file,
        which workers import only once a task runs, cannot)."""
        if self.environment_type is None:
            raise ValueError(f"application {self.name!r} sets no environment_type: name the "
                             f"dataclass its run files' environments are (e.g. "
                             f"reachwatch.systems.Environment, the taxi's runways)")
        types = (self.environment_type, self.random_environments_type or NoRandomEnvironments)
        for what, kind in zip(("environment_type", "random_environments_type"), types):
            if not (isinstance(kind, type) and dc.is_dataclass(kind)):
                raise ValueError(f"application {self.name!r}: {what} must be a dataclass "
                                 f"(the class itself), got {type(kind).__name__} "
                                 f"{clip(repr(kind), 80)}")
            module = sys.modules.get(kind.__module__)
            if (module is None or getattr(module, kind.__qualname__, None) is not kind
                    or kind.__module__.startswith("reachwatch_user_")):
                raise ValueError(f"application {self.name!r}: {what} {kind.__qualname__} must "
                                 f"be a dataclass defined at the top of an importable module "
                                 f"(a package, not the application's own file): workers "
                                 f"unpickle environments by their module's name")
            if any(f.default is dc.MISSING and f.default_factory is dc.MISSING
                   for f in dc.fields(kind) if f.init):
                raise ValueError(f"application {self.name!r}: {what} {kind.__qualname__} must "
                                 f"give every field a default (a run file may leave any "
                                 f"key out)")
        return types

    # --- the loop -----------------------------------------------------------------
    @abc.abstractmethod
    def loop_diagram(self, scenario, *, guarded: bool = False):
        """The closed-loop Drake diagram of ``scenario``: the plant, its camera, the
        controller (``reachwatch.diagrams.make_controller(scenario.controller)``);
        ``guarded``: with the monitor and fallback of ``scenario.monitor`` too. It
        exports ``state`` (the plant's state) as the loops of `reachwatch.diagrams` do.
        Sweeps and batches of real-loop runs set each run's start state and duration
        themselves: they build the loop from ``scenario`` with its ``initial_state``,
        ``duration`` and ``seed`` at their defaults (`without_run_settings`) and key their
        caches without them, so the loop must not read them (randomness of its own:
        seed it from a field of its controller's or environment's settings)."""

    @abc.abstractmethod
    def probe(self, scenario, *, guarded: bool = False):
        """The `Probe` a sweep reads the loop with: the plant subsystem whose continuous
        state the grid sets, the control port, and (``guarded``) the detector's score."""

    def loop_factory(self, scenario, *, guarded: bool = False):
        """A picklable, fingerprintable function of no arguments building
        `loop_diagram` (what sweeps run in workers and key their caches by)."""
        return functools.partial(build_loop, ApplicationRef(self._loaded_as()),
                                 sweep_scenario(self.resolved(scenario), guarded), guarded)

    def _loaded_as(self) -> str:
        """`spec`, which workers load the application by; a ValueError for an instance
        made directly rather than by `load_application` whose class names no `spec`
        of its own (one inherited would load the parent in workers)."""
        kind = f"{type(self).__module__}:{type(self).__qualname__}"
        if not self.spec or not ("spec" in vars(self) or "spec" in vars(type(self))):
            raise ValueError(f"application {kind}: load it with load_application("
                             f"'path/to/file.py:{type(self).__qualname__}') (or name it in the "
                             f"run file), so that workers and cache keys find its code")
        return self.spec

    def resolved(self, scenario):
        """``scenario`` with its file paths made absolute (default: as it is)."""
        return scenario

    # --- the plant ----------------------------------------------------------------
    @abc.abstractmethod
    def dynamics(self, scenario):
        """The plant's `reachwatch.reach.Dynamics` for the solver (its ``target`` > 0
        is the safe set)."""

    def failed(self, scenario, states) -> np.ndarray:
        """The failure rule: whether each state has failed (default: the dynamics'
        ``target(x) <= 0``)."""
        import torch
        target = self.dynamics(scenario).target(torch.as_tensor(np.asarray(states, float)))
        return np.asarray(target) <= 0

    # --- the grid and the starts --------------------------------------------------
    @abc.abstractmethod
    def grid(self, scenario, shape, **widen):
        """The `Grid` states are labelled and checked on, at ``shape``; ``widen``: the
        run file's widening of the solved box (``theta_deg``, ``py_max`` for the taxi;
        an application may ignore them)."""

    def starts(self, scenario, box, count: int, seed) -> np.ndarray:
        """``count`` seeded start states of ``box`` (a `Grid` or ``(lo, hi)``): the
        start distribution of checks and datasets. Default: uniform in the box, less
        nothing (an application restricts it to states not yet failed)."""
        lo, hi = (box.lo, box.hi) if hasattr(box, "lo") else box
        lo, hi = np.array(lo, float), np.array(hi, float)
        return lo + np.random.default_rng(seed).uniform(size=(count, len(lo))) * (hi - lo)

    def box_exit_share(self, scenario, horizon: float, **widen):
        """Known before anything is swept: the share of the check's starts bound to
        leave the solved box (the `grid` widened by ``widen``) within ``horizon`` s
        without failing, as ``{"share", "problem", "fix"}`` (the last two: sentences
        naming the run-file keys), or None when unknown (default)."""
        return None

    # --- sweeps -------------------------------------------------------------------
    def sweep_name(self, scenario, *, guarded: bool = False) -> str:
        return scenario.environment.name + ("_guarded" if guarded else "")

    def sweep(self, scenario, grid, *, guarded: bool = False, cache_dir, executor=None,
              chunk_size: int = 1024, progress: bool = True):
        """The loop's `probe` outputs at every node of ``grid`` (`reach.sweep`)."""
        return sweep(self.loop_factory(scenario, guarded=guarded), grid,
                     probe=self.probe(scenario, guarded=guarded),
                     name=self.sweep_name(scenario, guarded=guarded), cache_dir=cache_dir,
                     executor=executor, chunk_size=chunk_size, progress=progress,
                     label=f"{'guarded ' if guarded else ''}{scenario.environment.name} "
                           f"{'x'.join(map(str, grid.shape))}")

    def sweep_key(self, scenario, grid, *, guarded: bool = False) -> str:
        """The cache folder of `sweep` (no rendering)."""
        return sweep_key(self.loop_factory(scenario, guarded=guarded), grid,
                         self.probe(scenario, guarded=guarded),
                         name=self.sweep_name(scenario, guarded=guarded))

    def refine(self, scenario, table, *, solve, levels: int, band: float, variation=None,
               cache_dir, executor=None, progress: bool = True):
        """`reach.refine.refine_adaptively` of a swept ``table``."""
        from .refine import refine_adaptively
        return refine_adaptively(self.loop_factory(scenario), table, probe=self.probe(scenario),
                                 solve=solve, levels=levels, band=band, variation=variation,
                                 cache_dir=cache_dir, executor=executor, progress=progress,
                                 label=scenario.environment.name)

    # --- images -----------------------------------------------------------------------
    def renderer(self, scenario):
        """An object whose ``render(state)`` is the camera's RGB image ``(H, W, 3)``
        uint8 at one state (what datasets store). Default: the loop's camera, set by
        `render_at_states` through `probe`'s plant and `camera_port`."""
        from .loop_runs import subsystem_port
        diagram = self.loop_diagram(scenario)
        subsystem_port(self, diagram, self.camera_port, "camera_port")   # one line if none
        return _LoopRenderer(diagram, self.probe(scenario).plant, self.camera_port)

    #: The loop's camera image port (``"system.port"``), for the default `renderer`.
    camera_port = "wing_camera.color_image"

    def view_state(self, scenario) -> np.ndarray:
        """A state to show the camera's view at (the report's figure of the
        environments): default the middle of the `grid`'s box."""
        grid = self.grid(scenario, (3,) * len(self.axes))
        return (np.asarray(grid.lo, float) + np.asarray(grid.hi, float)) / 2

    def start_state(self, scenario) -> np.ndarray:
        """The state ``reachwatch simulate`` starts the loop from when it is given none:
        default `view_state` (the taxi's: the scenario's ``initial_state``)."""
        return self.view_state(scenario)

    def timing_starts(self, scenario, grid) -> np.ndarray:
        """The starts the guard stage times the loop alone and guarded from (the online
        tick rates), one per round in turn. Default: 5 seeded `starts` in ``grid``'s box."""
        return self.starts(scenario, grid, 5, 0)

    def has_ensemble(self) -> bool:
        """Whether the application trains an ensemble baseline (it defines
        `ensemble_config`); without one, the run file's default ``ensemble.seeds`` are none,
        and seeds it names are refused before anything runs."""
        return type(self).ensemble_config is not Application.ensemble_config

    def ensemble_estimator(self, checkpoint):
        """A function ``(N, H, W, 3) images -> (N, 2)`` estimates of one member of the
        ensemble baseline (a checkpoint of the controller's estimator)."""
        raise ValueError(f"the application '{self.name}' has no ensemble baseline: set "
                         f"ensemble.seeds: []")

    def ensemble_config(self, scenario, *, samples: int, epochs: int):
        """How the ensemble baseline's members are trained (the run file's ``ensemble``:
        ``samples`` labelled images, ``epochs``): a dataclass whose fields, with the
        seeds, key the folder of the checkpoints `train_ensemble` writes."""
        raise ValueError(f"the application '{self.name}' has no ensemble baseline: set "
                         f"ensemble.seeds: []")

    def train_ensemble(self, config, paths, seeds, *, progress=None):
        """Train one member of the ensemble baseline per seed of ``seeds`` from
        ``config`` (`ensemble_config`), the member of ``seeds[i]`` written to
        ``paths[i]`` (a checkpoint `ensemble_estimator` reads; the dataset stage names
        them)."""
        raise ValueError(f"the application '{self.name}' has no ensemble baseline: set "
                         f"ensemble.seeds: []")

    # --- plots ------------------------------------------------------------------------
    def plot_slices(self, value_functions, *, scenario, at, path, title="", points=None):
        """One panel per (label, `ValueFunction`) of a 2-D slice of the state space
        through ``at`` (the run file's ``slice_py`` for the taxi); ``points``: optional
        (label, states, matplotlib style) overlays. Returns the figure's path. The
        default (`reach.slices.plot_value_slices`) draws the grid's first two axes, the
        others at the box's centre, and does not read ``at``: define it for a slice of
        your own."""
        from .slices import plot_value_slices
        return plot_value_slices(value_functions, path=path, title=title, points=points)

    def plot_failure_sets(self, failures, grid, horizon, *, scenario, at, path, title=""):
        """`plot_slices` of failure sets (``{label: bool per grid node}``)."""
        from .value_function import ValueFunction
        sets = {k: ValueFunction(grid, np.where(np.asarray(v).reshape(grid.shape), -1.0, 1.0),
                                 horizon, "rollouts") for k, v in failures.items()}
        return self.plot_slices(sets, scenario=scenario, at=at, path=path, title=title)

    # --- words for reports --------------------------------------------------------------
    #: What the report puts before "starts" and "states" drawn where the plant has not
    #: failed (the taxi's: "on-runway"; "" = nothing).
    start_word = ""
    #: What a run that failed did, after "the real loop" (the taxi's: "left the runway").
    failure_words = "failed"
    #: The same, after "runs that" (the taxi's: "leave the runway").
    fail_words = "fail"
    #: The report's note on the check's starts (the taxi's names its failure rule).
    starts_note = "a start that has already failed agrees with any BRT"
    #: The box the grid spans, as the report names it (the taxi's: "the paper's box").
    box_words = "the application's box"
    #: Where `plot_slices` cuts the state space, formatted with ``at`` (the taxi's:
    #: "slices at py = {at:g} m"); "" = the report says nothing.
    slice_words = ""
    #: The run file's keys of the solved box and the slices that this application reads:
    #: ``solved_theta_deg`` and ``solved_py_max`` (its `grid` and `box_exit_share` take
    #: them as ``theta_deg`` and ``py_max``) and ``slice_py`` (its `plot_slices`'
    #: ``at``). A run file that sets one it does not read is refused in one line.
    reads_keys: tuple = ()

    def starts_text(self, noun="starts") -> str:
        """``noun`` qualified by `start_word` (``"on-runway starts"``)."""
        return f"{self.start_word} {noun}" if self.start_word else noun

    # --- incremental training (the incremental stage) ----------------------------------
    #: How reports and figures name the controller whose estimator is fine-tuned (the
    #: taxi's: "TaxiNet").
    controller_words = "controller"
    #: The fine-tuned checkpoint's file name stem in the run's ``incremental/`` folder.
    fine_tuned_name = "controller"

    def check_incremental(self, scenario):
        """Before anything runs: a ValueError in one line when the incremental stage
        cannot fine-tune this application's controller (default: unless `fine_tune` is
        defined)."""
        if type(self).fine_tune is Application.fine_tune:
            raise ValueError(f"incremental.enabled: the application '{self.name}' defines no "
                             f"fine_tune; set incremental: {{enabled: false}}")

    def fine_tune(self, scenario, checkpoint, datasets, config, path, *, progress=None) -> dict:
        """The controller's estimator in ``checkpoint`` ("" when the scenario names
        none) fine-tuned on the anomalous states of ``datasets`` (``[(Environment,
        LabelledData)]``, the training environments') as the run file's ``incremental``
        section ``config`` says, written to ``path`` (the loop reads it as
        ``scenario.controller.checkpoint``); returns its metadata (JSON-able;
        ``fine_tune_seconds`` among it, ``mined_states`` and ``replayed_states`` when it
        mined and replayed states, for the report)."""
        raise NotImplementedError(f"Application.fine_tune: the application '{self.name}' "
                                  f"fine-tunes no controller; set incremental: {{enabled: false}}")

    def fine_tuned_metadata(self, path) -> dict:
        """The metadata `fine_tune` returned for the checkpoint at ``path``, read again when
        the stage reuses it: default the JSON file the stage wrote beside it."""
        import json
        from pathlib import Path
        side = Path(f"{path}.json")
        return json.loads(side.read_text()) if side.is_file() else {}

    def run_from(self, scenario, start, duration: float):
        """``(trajectory, failed)``: the loop of ``scenario`` from the state ``start`` for
        ``duration`` s, stopped at the integrator step where `failed` holds (``reachwatch
        simulate``'s run, and the incremental stage's runs from its starred start).
        ``trajectory``: a `reachwatch.diagrams.Trajectory`, its ``failed`` and
        ``failure_time`` set."""
        from .loop_runs import failure_rule, run_until_failed
        return run_until_failed(self.loop_diagram(scenario), scenario,
                                failure_rule(self, scenario), start, duration)

    def plot_runs(self, runs, *, scenario, path, title=""):
        """A figure of ``runs`` (``[(Trajectory, label)]``) from one start; its path, or
        None (the default: no figure)."""
        return None

    def draw_runs(self, runs, *, scenario, path, title=""):
        """`plot_runs`' figure of ``runs``, or where it draws none each state axis (and
        the speed and flags, where logged) against time
        (`reachwatch.diagrams.plots.plot_runs_over_time`); its path."""
        drawn = self.plot_runs(runs, scenario=scenario, path=path, title=title)
        if drawn is None:
            from reachwatch.diagrams.plots import plot_runs_over_time
            drawn = plot_runs_over_time(runs, axes=self.axes, units=self.axis_units,
                                        path=path, title=title)
        return drawn

    # --- identity -------------------------------------------------------------------------
    def _data_folder(self) -> Path:
        """The folder `data_files` are relative to: that of the file the application was
        loaded from (its spec's ``path/to/file.py``, or its ``package.module``'s file);
        for one not loaded by name, that of its class's module, else the working
        directory."""
        target = self.spec.rpartition(":")[0]
        origin = None
        if target.endswith(".py"):
            origin = target
        elif target:
            found = importlib.util.find_spec(target)
            origin = getattr(found, "origin", None)
        if origin is None:
            origin = getattr(sys.modules.get(type(self).__module__), "__file__", None)
        return Path(origin).resolve().parent if origin else Path.cwd()

    def data_digest(self) -> dict:
        """``{path as given in data_files: digest of its content}`` (`file_hash`); a
        one-line ValueError naming a file that cannot be read."""
        from reachwatch.diagrams import file_hash
        folder = self._data_folder()
        digests = {}
        for given in self.data_files:
            path = folder / str(given)
            try:
                digests[str(given)] = file_hash(path)
            except OSError as e:
                raise ValueError(f"application '{self._loaded_as() or self.name}': data_files: "
                                 f"cannot read {clip(path, 200)} ({e.strerror})") from None
        return digests

    def key(self):
        """What the application adds to the keys of cached results: its spec, the
        fingerprint of its code and that of its `data_files` (`ApplicationRef`)."""
        return ApplicationRef(self._loaded_as()).__fingerprint__()


class _LoopRenderer:
    """`render_at_states` of one loop, one state at a time, on one reused Context."""

    def __init__(self, diagram, plant, image_port):
        self.diagram, self.plant, self.image_port = diagram, plant, image_port
        self.context = diagram.CreateDefaultContext()

    def render(self, state):
        from reachwatch.diagrams import render_at_states
        return render_at_states(self.diagram, plant=self.plant, image_port=self.image_port,
                                states=np.asarray(state, float)[None], context=self.context)[0]


@dc.dataclass(frozen=True)
class ApplicationRef:
    """An application by the string it is loaded from: picklable (a worker loads it
    again) and fingerprinted by the code it names."""
    spec: str

    def __fingerprint__(self):
        return {"spec": self.spec, "code": application_code_hash(self.spec),
                "data": load_application(self.spec).data_digest()}

    def load(self) -> Application:
        return load_application(self.spec)


def without_run_settings(scenario):
    """A copy of ``scenario`` whose start state, duration and seed are the defaults: a
    sweep sets the state, and a batch of real-loop runs its starts and duration, so
    neither reads them, and a run file that changes them reuses their caches. Its
    monitor encodes in the loop (``monitor.encoder_process`` off): a batch keeps every
    core busy with loops of its own, and a process a loop would be one more for each
    loop kept, for the same scores."""
    scenario, defaults = copy.deepcopy(scenario), type(scenario)()
    for name in scenario.SINGLE_RUN_FIELDS:
        setattr(scenario, name, getattr(defaults, name))
    monitor = getattr(scenario, "monitor", None)
    if getattr(monitor, "encoder_process", False):
        scenario.monitor = dc.replace(monitor, encoder_process=False)
    return scenario


def sweep_scenario(scenario, guarded: bool = False):
    """What a swept table of ``scenario``'s loop depends on, and nothing else: a copy
    without run settings (`without_run_settings`) and with the default fallback settings
    (a sweep reads ports that do not depend on them; a guarded one keeps the monitor's
    detector), so a run that changes them reuses its sweeps."""
    scenario = without_run_settings(scenario)
    scenario.monitor = type(scenario.monitor).watching(
        scenario.monitor.detector if guarded else "")
    return scenario


def build_loop(ref: ApplicationRef, scenario, guarded: bool):
    """``ref``'s `Application.loop_diagram` of ``scenario`` (a sweep's factory)."""
    application = ref.load()
    from reachwatch.diagrams import user_code
    with user_code.importable(inspect.getmodule(type(application))):
        return application.loop_diagram(scenario, guarded=guarded)


_LOADED = {}


def _check_axes(application: Application, spec: str):
    """A ValueError in one line when the application's `open_axes`, `heading_axis` or
    `estimated_state` names an axis its state does not have (the runs would fail in a
    worker, or a monitor's training after its runs, late), or names no axes at all."""
    n = len(application.axes)
    if n == 0 or not all(isinstance(name, str) and name for name in application.axes):
        raise ValueError(f"application '{spec or application.name}': axes must name each axis "
                         f"of its state (a tuple of names: ('x', 'y', 'heading')), got "
                         f"{application.axes!r}")
    named = {"open_axes": tuple(application.open_axes),
             "heading_axis": () if application.heading_axis is None
             else (application.heading_axis,),
             "estimated_state": tuple(application.estimated_state)}
    for what, indices in named.items():
        for i in indices:
            if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < n:
                raise ValueError(f"application '{spec or application.name}': {what} names axis "
                                 f"{i!r}, but its state has {n} ({', '.join(application.axes)})")


def application_code_hash(spec: str) -> str:
    """The fingerprint of the code of the application ``spec`` names
    (`reachwatch.diagrams.user_code.factory_code_hash`); "" for one in reachwatch's
    own loop packages, whose source every fingerprint carries already
    (`reach.fingerprint.LOOP_CODE`)."""
    from reachwatch.diagrams import user_code
    from .fingerprint import LOOP_CODE
    module = spec.rpartition(":")[0]
    if any(module == package or module.startswith(f"{package}.") for package in LOOP_CODE):
        return ""
    return user_code.factory_code_hash(spec, where="application")


def load_application(spec: str) -> Application:
    """The application ``spec`` names (``package.module:name`` or
    ``path/to/file.py:name``: an `Application` subclass, or a function of no arguments
    returning an instance). A ValueError in one line when it names none, cannot be
    loaded or is not an application."""
    spec = str(spec or "")
    if not spec:
        raise ValueError("application: name one, as package.module:name or "
                         "path/to/file.py:name")
    from reachwatch.diagrams import user_code
    from reachwatch.diagrams.user_errors import call_failure
    code = application_code_hash(spec)
    module, factory = user_code.resolve(spec, where="application")
    if (spec, code) in _LOADED:
        return _LOADED[spec, code]
    try:
        with user_code.importable(module):
            application = factory()
    except TypeError as e:
        raise ValueError(f"application '{spec}': calling it with no arguments failed "
                         f"(TypeError: {e}); name an Application subclass or a function "
                         f"of no arguments that returns one") from e
    except ValueError:
        raise                                   # the application's own one-line complaint
    except (Exception, SystemExit) as e:      # sys.exit(): was a silent exit
        raise call_failure(spec, e, module, where="application") from e
    if not isinstance(application, Application):
        raise ValueError(f"application '{spec}': it returned a {type(application).__name__}, "
                         f"not a reachwatch.reach.application.Application")
    _check_axes(application, spec)
    application.spec = spec
    application.data_digest()                   # a data file it names is there, or one line
    # two threads of a worker loading it at once both get the first one kept
    return _LOADED.setdefault((spec, code), application)


def application_key(application: Application) -> str:
    """`Application.key` as a short digest."""
    return fingerprint(application.key())[:16]
