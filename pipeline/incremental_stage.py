"""The incremental stage of ``reachwatch run``: the application's controller
fine-tuned on the anomalies mined from the training datasets (`Application.fine_tune`),
the held-out environment's BRT recomputed with it, before and after side by side, and
the loop from a start the fine-tuning saves."""

import json
import os
from pathlib import Path

from reachwatch.diagrams import file_hash
from reachwatch.reach import ValueFunction
from reachwatch.reach.application import Application, application_key
from reachwatch.reach.fingerprint import loop_code_digest, modules_source_digest
from reachwatch.systems.files import atomic_write_bytes

from .brt_stages import solve_env, sweep_env
from .online_stages import robust_starts
from .keys import digest
from .stages import Run


def incremental(run: Run) -> dict:
    """The incremental stage: the application's `fine_tune` of its controller on the
    training datasets' anomalies, then the BRT of ``incremental.environment`` again with
    the fine-tuned checkpoint, before and after side by side, and the loop from a start
    the fine-tuning saves (`Application.run_from`, `plot_runs`)."""
    spec, config, application = run.spec, run.spec.incremental, run.application
    env = config.environment
    progress = run.bar()
    base = application.resolved(run.scenario_for(env)).controller.checkpoint
    own = application_key(application)
    # the training environments' names: the datasets it fine-tunes on; the loop's code:
    # the built-in application's fine-tuning lives there (another's is in ``own``)
    name = digest(config, run.outputs["dataset"], file_hash(base) if base else "",
                  [e.name for e in spec.training_environments()], loop_code_digest(), own)
    path = run.path(f"incremental/{application.fine_tuned_name}_{name}.pt")
    seconds = None
    if not path.exists():
        # fine_tune writes beside the checkpoint's name, and the checkpoint takes its name
        # only once it and its metadata are both written: a checkpoint there is complete
        partial = path.with_name(f"{path.name}.partial")
        partial.parent.mkdir(parents=True, exist_ok=True)
        partial.unlink(missing_ok=True)
        train = spec.training_environments()
        meta = application.fine_tune(run.scenario_for(env), base,
                                     list(zip(train, run.datasets(train))), config, partial,
                                     progress=progress)
        if not partial.is_file():
            raise ValueError(f"incremental: the application '{application.name}''s fine_tune "
                             f"wrote no checkpoint at the path it was given ({partial})")
        seconds = meta.get("fine_tune_seconds")
        if type(application).fine_tuned_metadata is Application.fine_tuned_metadata:
            atomic_write_bytes(Path(f"{path}.json"), json.dumps(
                {k: v for k, v in meta.items() if k != "fine_tune_seconds"},
                default=str).encode())
        os.replace(partial, path)
    meta = {**application.fine_tuned_metadata(path), "fine_tune_seconds": seconds}
    after = {**sweep_env(run, env, checkpoint=path),
             **solve_env(run, env, checkpoint=path, label=" fine-tuned")}
    before_vf, after_vf = run.value_function(env.name), ValueFunction.load(run.path(after["value"]))
    grid = before_vf.grid
    saved = (before_vf.values.ravel() <= 0) & (after_vf.values.ravel() > 0)
    star = grid.states(robust_starts(saved, grid, 1))
    words = application.controller_words
    figure = application.plot_slices(
        {f"vanilla {words}": before_vf, f"fine-tuned {words}": after_vf},
        scenario=run.scenario_for(env), at=spec.slice_py,
        path=run.path(f"figures/incremental_{env.name}.png"),
        points=[("start (saved by fine-tuning)", star, "m*")] if len(star) else None)
    result = {"environment": env.name, "checkpoint": run.rel(path),
              "before": run.outputs["solve"][env.name]["brt_fraction"],
              "after": after["brt_fraction"], "after_record": after, "figure": run.rel(figure),
              "fine_tune": {k: meta.get(k) for k in ("mined_states", "replayed_states",
                                                      "mined_per_environment",
                                                      "mined_error_before", "mined_error_after",
                                                      "fine_tune_seconds")}}
    if len(star):
        runs = []
        for label, checkpoint in ((f"vanilla {words}", base), (f"fine-tuned {words}", path)):
            t, failed = application.run_from(run.scenario_for(env, checkpoint), star[0],
                                             spec.horizon)
            runs.append((t, failed, f"{label}{' (fails)' if failed else ''}"))
        shown = application.plot_runs(
            [(t, label) for t, _, label in runs], scenario=run.scenario_for(env),
            path=run.path(f"figures/incremental_run_{env.name}.png"),
            title=f"{env.name}: from the starred start")
        result["star"] = {"start": [float(v) for v in star[0]],
                          "vanilla_fails": runs[0][1], "fine_tuned_fails": runs[1][1],
                          "figure": run.rel(shown) if shown is not None else None}
    return result


#: The source in the incremental record's key: this module and the stages it calls.
INCREMENTAL_CODE = ("reachwatch.pipeline.incremental_stage", "reachwatch.pipeline.brt_stages",
                    "reachwatch.pipeline.online_stages")


def stage_incremental(run: Run) -> dict:
    config = run.spec.incremental
    if not config.enabled:
        return {}
    own = application_key(run.application)
    key = digest(config, run.content_key("dataset"),
                 run.content_key(f"solve_{config.environment.name}"),
                 [e.name for e in run.spec.training_environments()],
                 {"code": modules_source_digest(*INCREMENTAL_CODE)}, own)
    return run.stage("incremental", key, lambda: incremental(run))
