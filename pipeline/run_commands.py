"""``reachwatch run``'s arguments and the command, a front end of
`reachwatch.pipeline.run.run_pipeline`, imported when it runs (so that building the
parser needs no torch)."""

from .executor_option import add_executor_argument
from .overlays import add_overlay_arguments

#: ``reachwatch.pipeline.run``'s ``STAGES`` and ``SLICE_UNTIL``, here for the parser's
#: ``--until`` (a test keeps them the same).
STAGES = ("sweep", "solve", "dataset", "fidelity", "train", "evaluate", "guard", "monitor",
          "incremental", "report")
SLICE_UNTIL = "fidelity"

#: ``--push-every``'s default, seconds: a machine lost mid-stage loses at most this
#: much of its chunks.
PUSH_EVERY = 300.0

#: ``--push-every``'s largest value, seconds (a day): longer is never, which is 0.
MAX_PUSH_EVERY = 86400.0


def add_parsers(sub):
    p = sub.add_parser("run", help="the whole study from a run file: sweeps, BRTs, labelled "
                       "datasets, detector, Table 2, guarded loop, incremental training, "
                       "report (re-runs skip finished stages; killed runs resume)")
    p.add_argument("--scenario", required=True, help="run file (e.g. scenarios/demo.yaml)")
    add_overlay_arguments(p, "run")
    p.add_argument("--out", required=True, help="run directory (reused), or an fsspec URL "
                   "(s3://bucket/study with s3fs, file:///..., memory://...): the run works "
                   "in a local copy (--work-dir), fetched from it first and put to it after "
                   "every stage")
    p.add_argument("--work-dir", help="with --out URL: the local working copy (default "
                   "$REACHWATCH_CACHE/runs/<digest of the URL>)")
    p.add_argument("--push-every", type=float, default=PUSH_EVERY, metavar="SECONDS",
                   help="with --out URL: also put the chunks a stage has finished every "
                   "SECONDS while it runs, so that a stage cut off half-way resumes on "
                   f"another machine from them (1 to {MAX_PUSH_EVERY:g}; default "
                   f"{PUSH_EVERY:g}; 0: only after each stage)")
    add_executor_argument(p)
    p.add_argument("--until", choices=STAGES, help=f"last stage to run (default: report, "
                   f"or {SLICE_UNTIL} with --only)")
    p.add_argument("--sweep-cache", help="folder or fsspec URL (memory://, s3://... "
                   "with s3fs) of sweep chunks shared between runs (keyed by content; "
                   "default OUT/sweeps)")
    p.add_argument("--only", nargs="+", metavar="ENV", help="run a slice: these environments "
                   "alone (names as the report gives them, e.g. KSFO_21h_overcast), up to "
                   f"--until {SLICE_UNTIL} at most; their records are the whole run's")
    p.set_defaults(func=run_command)


def _still_writing(error: BaseException):
    """The jobs an interrupt found still writing (`reach.chunk_jobs.run_together`'s
    ``jobs_still_writing``), on ``error`` or on one it was raised while handling (an
    executor that failed to stop, say); None when none."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        writing = getattr(error, "jobs_still_writing", None)
        if writing:
            return writing
        error = error.__cause__ or error.__context__
    return None


def run_command(args):
    """``reachwatch run``: the run file (with its overlays) to the stages up to
    ``--until``, in ``--out`` (a folder, or an fsspec URL through a `RunMirror`)."""
    import contextlib
    import time
    from pathlib import Path

    from reachwatch.systems.files import is_url, make_folder

    from .commands import scenario_from_args
    from .console import log, progress_enabled
    from .executors import open_executor
    from .run import run_folder_held, run_pipeline
    from .run_mirror import RunMirror
    from .spec import RunSpec
    if not (args.push_every == 0 or 1 <= args.push_every <= MAX_PUSH_EVERY):
        raise ValueError(f"--push-every must be 0 or 1 to {MAX_PUSH_EVERY:g} seconds, got "
                         f"{args.push_every:g}")
    spec = scenario_from_args(args, schema=RunSpec, root="run", controller=True)
    until = args.until or (SLICE_UNTIL if args.only else "report")
    if args.sweep_cache and is_url(args.sweep_cache):     # checked before any work, as --out
        try:
            make_folder(args.sweep_cache)
        except (ValueError, OSError) as e:
            raise ValueError(f"--sweep-cache {e}") from None
    elif args.sweep_cache and Path(args.sweep_cache).exists() and \
            not Path(args.sweep_cache).is_dir():
        raise ValueError(f"--sweep-cache {args.sweep_cache} is a file; name a folder")
    started = time.time()

    def stamp(message):
        log.info(f"{time.time() - started:7.1f} s  {message}")

    mirror = RunMirror(args.out, getattr(args, "work_dir", None)) if is_url(args.out) else None
    # a URL's working directory is held before anything is fetched into it or put from it
    with run_folder_held(mirror.local) if mirror is not None else contextlib.nullcontext():
        out = args.out
        if mirror is not None:
            fetched = mirror.pull(progress=progress_enabled())
            stamp(f"{args.out}: working in {mirror.local}; fetched {fetched} files")
            out = mirror.local

        def push(stage):
            if mirror is not None:
                put = mirror.push(progress=progress_enabled())
                stamp(f"[{stage}] {put} files put to {mirror.url}")

        try:
            pushing = (mirror.pushing_every(args.push_every, stamp, log.warning)
                       if mirror is not None else contextlib.nullcontext())
            with open_executor(args.executor) as executor, pushing:
                run = run_pipeline(spec, out, executor=executor, until=until,
                                   sweep_cache=args.sweep_cache, only=args.only,
                                   progress=progress_enabled(), log=stamp, after_stage=push,
                                   folder_held=mirror is not None)
        except BaseException as error:  # what finished before an error or interrupt is put too
            writing = _still_writing(error)
            if writing:             # their files may change while they are put: a mixed copy
                log.warning(f"not put to {args.out}: {len(writing)} jobs were still writing "
                            f"when interrupted ({', '.join(writing[:3])}); run the command "
                            f"again, which resumes here and puts the folder")
                raise
            try:
                push("end")
            except Exception as e:     # the run's own error is the one to see
                log.warning(f"could not put the working directory to {args.out}: "
                            f"{type(e).__name__}: {e}")
            raise
        push("end")
        log.info(f"run '{spec.name}' up to {until} finished in {time.time() - started:.0f} s")
        if "report" in run.outputs and run.outputs["report"]:
            log.info(f"report: {run.path(run.outputs['report']['html'])} "
                     f"(and {run.path(run.outputs['report']['md'])})"
                     + (f", put to {mirror.url}" if mirror is not None else ""))
