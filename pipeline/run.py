"""``reachwatch run``: scenario file to report in one command.

Stages run in order sweep -> solve -> dataset -> fidelity -> train -> evaluate -> guard ->
monitor -> incremental -> report; each is skipped when its record in ``OUT/stages/`` has the
same key (a digest of its inputs: the settings it reads and, for the stages before it whose
outputs it reads, `Run.content_key`: their keys and the content of every file they wrote),
and resumes its chunked work when it was killed."""

import contextlib
import errno
import fcntl
import os
from pathlib import Path

import numpy as np

from reachwatch.reach.application import load_application
from reachwatch.reach.fingerprint import LIBRARY, modules_source_digest
from reachwatch.systems.checks import short

from .checked_page import write_checked_page
from .console import log
from .fidelity_stages import check_downtrack_room, stage_fidelity
from .incremental_stage import stage_incremental
from .online_stages import stage_guard
from .report import write_report
from .keys import digest
from .spec import RunSpec, dump_run_spec
from .brt_stages import stage_solve, stage_sweep
from .dataset_stages import dataset_key, stage_dataset
from .monitor_study import stage_monitor
from .detector_stages import controller_name, evaluate_key, stage_evaluate, stage_train, train_key
from .slot_defaults import is_default_application
from .stages import Run, record_check

STAGES = ("sweep", "solve", "dataset", "fidelity", "train", "evaluate", "guard", "monitor",
          "incremental", "report")
REPORT_FORMAT = 1


#: The last stage a slice (``only``) may run: every later one pools all environments.
SLICE_UNTIL = "fidelity"


def run_pipeline(spec: RunSpec, out, *, executor=None, until="report", progress=True,
                 log=log.info, sweep_cache=None, only=None, after_stage=None,
                 folder_held: bool = False) -> Run:
    """Run (or resume) every stage up to ``until``; returns the `Run` with its records.

    ``only`` (environment names) runs a slice: the per-environment stages (sweep,
    solve, dataset, fidelity) for those environments alone, whose records are the ones
    the whole run gives them (each depends on its environment only). A long study
    can so run in pieces, on machines that share nothing, and its per-environment
    figures be read as they come: a slice up to fidelity writes ``checked.html`` (and
    ``.md``), the fidelity section over every environment checked so far in ``out``
    (`write_checked_page`). ``after_stage(name)`` is called after each stage (a
    `RunMirror` pushes the run directory to its URL there). The run holds ``out``
    while it runs (`run_folder_held`), unless the caller does (``folder_held``)."""
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got '{until}'")
    spec.validate()
    if only is not None:
        check_slice(spec, only, until)
    if STAGES.index(until) >= STAGES.index("fidelity"):
        check_downtrack_room(spec)
    check_controller_builds(spec, log=log)
    with contextlib.nullcontext() if folder_held else run_folder_held(out):
        run = Run(spec, out, executor=executor, progress=progress, log=log, sweep_cache=sweep_cache,
                  only=only)
        if only is not None:
            log(f"a slice of {len(run.environments())} of the run's {len(spec.all_environments())} "
                f"environments, up to {until}: {', '.join(e.name for e in run.environments())}")
        for env in run.environments():      # a box the application refuses, before any work
            run.solved_grid_for(env)
        steps = {
            "sweep": lambda: stage_sweep(run),
            "solve": lambda: stage_solve(run),
            "dataset": lambda: run.stage("dataset", dataset_key(run), lambda: stage_dataset(run)),
            "fidelity": lambda: stage_fidelity(run),
            # the device that trains and scores (CUDA where present, unless told): another
            # device trains other weights and scores in other last digits
            "train": lambda: run.stage("train", train_key(run), lambda: stage_train(run)),
            "evaluate": lambda: run.stage("evaluate", evaluate_key(run), lambda: stage_evaluate(run)),
            "guard": lambda: stage_guard(run),
            "monitor": lambda: stage_monitor(run),
            "incremental": lambda: stage_incremental(run),
            "report": lambda: run.stage("report", report_key(run), lambda: write_report(run)),
        }
        for name in STAGES[:STAGES.index(until) + 1]:
            run.outputs[name] = steps[name]()
            if after_stage is not None:
                after_stage(name)
        if only is not None and until == SLICE_UNTIL and spec.fidelity.starts:
            page = write_checked_page(run)
            log(f"checked so far: {len(page['checks'])} of the run's "
                f"{len(spec.all_environments())} environments"
                + (f" ({len(page['stale'])} on record for other inputs)" if page["stale"] else "")
                + (f", labels meeting the target in {len(page['labels_meet_target'])} of "
                   f"{len(page['labelled'])}" if page["labelled"] else "")
                + f"; {run.path(page['html'])} (and {page['md']})")
        return run


def report_key(run) -> str:
    """The report stage's key: everything the report prints, which is the run file as
    recorded (its configuration block), every stage's record before it whole (its key,
    files, figures and timings: `record_check`), and the source of all of reachwatch
    (`reach.fingerprint.LIBRARY`). The report costs seconds: a stage run again for the
    same bytes (new timings), a run-file edit no stage reads, or a resumed run whose
    report code changed writes it anew."""
    return digest(REPORT_FORMAT, dump_run_spec(run.spec),
                  {k: record_check(record) for k, record in run.records.items()},
                  modules_source_digest(*LIBRARY))


#: The lock file a run holds in its run directory while it runs (`run_folder_held`).
LOCK_NAME = ".reachwatch.lock"


@contextlib.contextmanager
def run_folder_held(out):
    """Holds an exclusive lock (``fcntl.flock``) on the run directory ``out`` for the
    block, or raises a ValueError in one line when another run holds it (another
    process, or another thread of this one): two runs on one folder would write the
    same files (a dataset's images truncated under the other's feet). The block runs
    unlocked where the folder cannot hold one (read-only: such a run writes nothing; a
    file system without ``flock``: said in one line). It guards the folder on this
    machine: two machines working on one ``--out`` URL each in a folder of their own are
    not held apart. The lock file stays when the block ends (removing it would race)."""
    fd = _locked(out)
    try:
        yield
    finally:
        if fd is not None:
            try:            # no pid left behind for the next refusal to name
                os.ftruncate(fd, 0)
            except OSError:
                pass        # opened to read: not ours to write
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def _locked(out):
    """`run_folder_held`'s lock: its file descriptor, None where the folder cannot hold
    one, or the one-line ValueError when another run holds it."""
    root, writable = Path(out), True
    try:
        root.mkdir(parents=True, exist_ok=True)
        fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except PermissionError as e:
        try:            # another user's lock file: flock holds on a file opened to read
            fd, writable = os.open(root / LOCK_NAME, os.O_RDONLY), False
        except FileNotFoundError:               # none, and none can be made: read-only
            return None
        except OSError:
            log.warning(f"{out}: cannot open its lock file ({e.strerror}); running without "
                        f"the lock that keeps a second run out")
            return None
    except OSError as e:
        # a read-only file system, or a file where the folder goes: the run writes
        # nothing there, and says so where it tries
        if e.errno not in (errno.EROFS, errno.ENOTDIR, errno.EEXIST):
            log.warning(f"{out}: cannot open its lock file ({e.strerror}); running without "
                        f"the lock that keeps a second run out")
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        try:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
        except OSError:
            holder = ""
        finally:
            os.close(fd)
        if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
            log.warning(f"{out}: cannot lock it ({e.strerror}); running without the lock "
                        f"that keeps a second run out")
            return None
        raise ValueError(f"{out} is in use by another reachwatch run"
                         f"{f' (pid {holder})' if holder.isdigit() else ''}: wait for it to "
                         f"end, or give another --out") from None
    if writable:                                # who holds it, for the other's message
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
        except OSError:
            pass
    return fd


def check_controller_builds(spec: RunSpec, log=log.info):
    """Build a user's controller (``scenario.controller.factory``) once before anything is
    written, so that a parameter its factory does not take (or lacks) is said in one line
    before the run directory or a sweep changes, not inside the first sweep; then fit the
    guard's strategies to the application and the controller (`fit_guard`)."""
    controller, built = spec.scenario.controller, None
    application = load_application(spec.application)
    if controller.factory:
        from reachwatch.diagrams import make_controller
        built = make_controller(application.resolved(spec.scenario).controller)
    elif not is_default_application(application):
        log(f"scenario.controller.factory is not set: a loop of '{application.name}' that "
            f"builds scenario.controller is steered by the built-in TaxiNet (name your "
            f"controller's factory to run another)")
    fit_guard(spec, built, log)


def fit_guard(spec: RunSpec, controller=None, log=log.info) -> None:
    """The guard's fallbacks the application or the ``controller`` (a built user's
    controller; None: the built-in one) cannot run, before anything is swept: the
    default ``guard.strategies`` lose them (said in one line), and one the run file names
    is refused in one line naming its key. The application's: a steering fallback
    without its hooks (`Application.guard_refusals`); the controller's: a fallback that
    dead-reckons from its estimate when it has no ``estimate`` output, or one of another
    size than the application carries (its ``true_estimate``'s)."""
    from reachwatch.diagrams.controller import estimate_size, has_estimate
    from reachwatch.systems import Fallback
    if not spec.guard_environments():
        return
    strategies = spec.guard.strategies
    application = load_application(spec.application)
    application.check_guard_speed(application.resolved(spec.scenario))
    refusals = application.guard_refusals(spec.scenario, strategies)
    carried = None                  # how many numbers the application's dead reckoning carries
    if application.true_estimate is not None:
        carried = np.shape(application.true_estimate(np.zeros((1, len(application.axes)))))[-1]
    for i, name in enumerate(strategies):
        if controller is None or Fallback.parse(name).steering != "dead_reckoning":
            continue
        if not has_estimate(controller):
            refusals.setdefault(i, f"dead-reckons from the controller's estimate, and the "
                                   f"controller '{controller_name(spec.scenario)}' has no "
                                   f"estimate output")
        elif carried is not None and estimate_size(controller) != carried:
            refusals.setdefault(i, f"dead-reckons from an estimate of {carried} numbers (the "
                                   f"application's true_estimate), and the controller "
                                   f"'{controller_name(spec.scenario)}' estimates "
                                   f"{estimate_size(controller)}")
    if not refusals:
        return
    if spec.default_strategies():
        spec.guard.strategies = [n for i, n in enumerate(strategies) if i not in refusals]
        log("guard.strategies: the default without "
            + "; ".join(f"{strategies[i]} (it {why})" for i, why in sorted(refusals.items())))
        return
    i = min(refusals)
    raise ValueError(f"guard.strategies[{i}]: '{strategies[i]}' {refusals[i]}; leave it out")


def check_slice(spec: RunSpec, only, until: str):
    """Raise a ValueError when ``only`` names no environment, or one the run lacks
    (listing the run's), or when ``until`` goes past `SLICE_UNTIL`."""
    names = [e.name for e in spec.all_environments()]
    unknown = [n for n in only if n not in names]
    if not only or unknown:
        what = ("no environment given" if not only else
                f"no environment named {', '.join(short(n, 60) for n in unknown[:3])}"
                f"{' ...' if len(unknown) > 3 else ''} in run '{spec.name}'")
        listed = ", ".join(names[:12]) + (f", ... ({len(names)} in all)" if len(names) > 12 else "")
        raise ValueError(f"--only: {what}; its environments are: {listed}")
    if STAGES.index(until) > STAGES.index(SLICE_UNTIL):
        raise ValueError(f"--only runs a slice up to {SLICE_UNTIL} at most (--until sweep, solve, "
                         f"dataset or {SLICE_UNTIL}): the stages after it pool every environment "
                         f"(the detector trains on all of them), got --until {until}")
