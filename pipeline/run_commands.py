"""``reachwatch run``'s arguments; the command itself is `reachwatch.pipeline.run`'s
``run_command``, imported when it runs (so that building the parser needs no torch)."""

from .overlays import add_overlay_arguments

#: ``reachwatch.pipeline.run``'s ``STAGES`` and ``SLICE_UNTIL``, here for the parser's
#: ``--until`` (a test keeps them the same).
STAGES = ("sweep", "solve", "dataset", "fidelity", "train", "evaluate", "guard", "monitor",
          "incremental", "report")
SLICE_UNTIL = "fidelity"


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
    p.add_argument("--executor", default="local", help="local (one worker per core) | "
                   "local:N | inline | dask://HOST:PORT (a Dask scheduler; its workers get "
                   "the files each task names with it and return results, so they need "
                   "neither the run directory nor this machine's paths)")
    p.add_argument("--until", choices=STAGES, help=f"last stage to run (default: report, "
                   f"or {SLICE_UNTIL} with --only)")
    p.add_argument("--sweep-cache", help="folder or fsspec URL (memory://, s3://... "
                   "with s3fs) of sweep chunks shared between runs (keyed by content; "
                   "default OUT/sweeps)")
    p.add_argument("--only", nargs="+", metavar="ENV", help="run a slice: these environments "
                   "alone (names as the report gives them, e.g. KSFO_21h_overcast), up to "
                   f"--until {SLICE_UNTIL} at most; their records are the whole run's")
    p.set_defaults(func=run_command)


def run_command(args):
    from .run import run_command
    return run_command(args)
