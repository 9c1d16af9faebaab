"""A stage's per-environment work, every environment at once on the run's executor
(`reachwatch.reach.chunk_jobs.run_together`): the sweep, dataset and fidelity stages feed
all their environments' chunks to one window sized to the executor, so a cluster
larger than one environment's chunks is kept busy and no environment's tail leaves
workers idle. Inline, one environment after another, as before."""

import copy
import functools

from reachwatch.reach.chunk_jobs import ordered_log, run_together, together

from .stages import Run


def _view(run: Run, log) -> Run:
    """``run`` as one environment's thread sees it: the same run directory, executor
    and settings, its own dicts of outputs and records (merged back in the
    environments' order) and a log whose lines come in that order."""
    view = copy.copy(run)
    view.outputs, view.records, view.log = dict(run.outputs), dict(run.records), log
    return view


def every_environment_bar(unit: str, desc: str, *, shown: bool):
    """The ``rows_bar`` of `run_together` for environments run at once (a tqdm bar of
    ``unit`` rows, ``desc``), or None when progress is not ``shown``."""
    if not shown:
        return None
    from tqdm import tqdm
    return functools.partial(tqdm, unit=unit, desc=desc)


def each_environment(run: Run, envs, fn, *, what: str, bar=None, unit: str = None) -> dict:
    """``{env.name: fn(run, env)}`` for ``envs``, in their order. On a pool each ``fn``
    runs in a thread of its own, all environments' chunks together on the run's
    executor; the records its `Run.stage` calls keep (``run.outputs`` and
    ``run.records``) and the lines it logs come in the environments' order, as
    inline. An error in one environment stops the others' queued chunks (their
    finished chunks and stage records are kept) and is raised with ``"{what}
    {name}: "`` before its message. ``bar``: a tqdm-like factory counting the
    environments done. ``unit`` (what a row of the stage's chunks is: ``"state"``,
    ``"run"``): with the run's progress shown, a bar of the rows of every environment
    below theirs, whose rate and time left are the machine's where each environment's
    bar reads its share."""
    envs = list(envs)
    rows_bar = every_environment_bar(unit, f"{unit}s of every environment",
                                     shown=bool(unit) and run.progress)
    if not together(run.executor, len(envs)):
        return dict(zip([e.name for e in envs], run_together(
            [(e.name, lambda e=e: fn(run, e)) for e in envs], run.executor, what=what,
            bar=bar)))
    log = ordered_log(run.log)
    views = [_view(run, log) for _ in envs]
    try:
        results = run_together([(e.name, lambda e=e, v=v: fn(v, e)) for e, v in zip(envs, views)],
                               run.executor, what=what, bar=bar, rows_bar=rows_bar)
    finally:              # what each environment's stages recorded, in their order
        for view in views:
            for mine, theirs in ((run.outputs, view.outputs), (run.records, view.records)):
                for name, value in theirs.items():
                    if mine.get(name) is not value:
                        mine[name] = value
    return dict(zip([e.name for e in envs], results))
