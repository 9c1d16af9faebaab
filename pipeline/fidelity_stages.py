"""The fidelity stage of ``reachwatch run``: every environment's BRT, swept table and
labels checked against the real Drake loop (rendering at every tick) from seeded
uniform random starts (the application's: on the runway for the taxi), with 95 %
Wilson intervals.

The split says where an error comes from: the swept table as a model of the real
loop (table rollouts vs real), the solver against its own table (BRT vs table
rollouts), and the runs that leave the solved box (where the table is clamped)."""

import time

import numpy as np

from reachwatch.reach import compare_verdicts, min_target_along_rollouts
from reachwatch.reach.application import load_application
from reachwatch.reach.fingerprint import modules_source_digest
from reachwatch.training.dataset import DATASET_CODE, load_dataset
from reachwatch.training.labels import SOURCE_PATH, label_verdicts

from .keys import digest
from .spec import RunSpec
from .stages import Run
from .together import each_environment


class BoxExitError(ValueError):
    """The real loop leaves the solved box too often for BRT labels to mean anything: the
    run file's settings do not fit together (the command line says so in one line)."""


def check_downtrack_room(spec: RunSpec):
    """Raise `BoxExitError` before the sweeps when the fidelity check is bound to refuse
    the run's BRT labels for lack of room in the solved box (the application's
    ``box_exit_share`` above ``fidelity.max_box_exits``), instead of after them."""
    check = spec.fidelity
    if check.starts == 0 or spec.dataset.labels.source != "brt":
        return
    exits = load_application(spec.application).box_exit_share(
        spec.scenario, spec.horizon, theta_deg=float(spec.solved_theta_deg),
        py_max=float(spec.solved_py_max))
    if exits is not None and exits["share"] > check.max_box_exits:
        raise BoxExitError(
            f"{exits['problem']}, more than fidelity.max_box_exits "
            f"({100 * check.max_box_exits:.0f} %), so the check would refuse the BRT labels "
            f"after every sweep had run. {exits['fix']}, label with dataset.labels.source: "
            f"hybrid or rollout, or raise fidelity.max_box_exits to accept it")


def fidelity_env(run: Run, env) -> dict:
    """Real-loop outcomes from ``run.spec.fidelity.starts`` starts (``more_starts``
    where those find the BRT or the labels wrong) and the BRT, the table rollouts and
    (for train/test environments) the labels compared with them."""
    spec, check, application = run.spec, run.spec.fidelity, run.application
    scenario, grid = run.scenario_for(env), run.grid_for(env)
    vf = run.value_function(env.name)
    labels = run.outputs.get("dataset", {}).get("labels", {}).get(env.name)
    band = spec.dataset_spec_for(env).labels.band

    def real(states):
        # box exits are counted against the solved box (wider than the paper's if asked)
        return application.real_outcomes(
            scenario, states, grid=run.solved_grid_for(env), duration=spec.horizon,
            cache_dir=run.path("outcomes"), executor=run.executor,
            progress=run.progress).fields

    def any_wrong(states, failed):
        wrong = vf.in_brt(states) != failed
        if labels:
            wrong |= label_verdicts(labels, band, vf.at(states), failed) != failed
        return bool(wrong.any())

    started = time.time()
    starts = application.starts(scenario, grid, check.starts, check.seed)
    outcomes = real(starts)
    # The labels' audit (other runs) found the map wrong: its figure needs the longer
    # check whatever the first runs say, and choosing so does not bias the check.
    distrusted = bool(labels) and (labels.get("audit") or {}).get("map_trusted") is False
    because = None
    if check.more_starts:
        because = ("audit" if distrusted else
                   "check" if any_wrong(starts, outcomes["failed"].astype(bool)) else None)
    extended = because is not None
    if extended:      # the same draw, longer: its first rows are the runs above
        more = application.starts(scenario, grid, check.more_starts, check.seed)[check.starts:]
        extra = real(more)
        starts = np.concatenate([starts, more])
        outcomes = {k: np.concatenate([outcomes[k], extra[k]]) for k in outcomes}
    seconds = time.time() - started
    real_failed = outcomes["failed"].astype(bool)
    predicted = vf.in_brt(starts)
    solved_grid, steering = run.steering_table(env)
    lowest, table_left = min_target_along_rollouts(
        solved_grid, application.dynamics(scenario), steering, starts, horizon=spec.horizon,
        hold=scenario.controller.period, box_axes=application.open_axes)
    table_fails = lowest <= 0
    out = {"starts": int(len(starts)), "seed": int(check.seed),
           "brt": compare_verdicts(predicted, real_failed, outcomes["left_box"]).as_dict(),
           "table_rollouts": compare_verdicts(table_fails, real_failed, table_left).as_dict(),
           "brt_vs_table_rollouts": float(np.mean(predicted == table_fails)),
           "real_max_abs_theta_deg": heading_percentiles(outcomes, len(starts)),
           "frames": int(np.sum(outcomes["ticks"])), "seconds": round(seconds, 1)}
    if check.more_starts:
        out["extended"] = extended
        if extended:
            out["extended_because"] = because
    if labels:
        verdicts = label_verdicts(labels, band, vf.at(starts), real_failed)
        audit = labels.get("audit") or {}
        out["labels"] = {"source": labels["source"], "map_trusted": audit.get("map_trusted"),
                         "band": audit.get("band", band) if audit else None,
                         "audit_runs": audit.get("samples"),
                         "labelled_by": labels.get("labelled_by"),
                         **compare_verdicts(verdicts, real_failed, outcomes["left_box"]).as_dict()}
        if labels.get("counts", {}).get("path"):       # trajectory labels, or paths: N
            out["path_labels"] = check_path_labels(run, env, len(starts))
    return out


def heading_percentiles(outcomes: dict, runs: int) -> list:
    """The 50th, 90th and 100th percentiles (deg, one decimal) of the real runs' largest
    heading ``max_abs_theta`` (rad, along `Application.heading_axis`); NaN where a
    plant's own `real_outcomes` leaves it out or has none."""
    heading = outcomes.get("max_abs_theta", np.full(runs, np.nan))
    return np.percentile(np.rad2deg(heading), [50, 90, 100]).round(1).tolist()


def check_path_labels(run: Run, env, count: int) -> dict:
    """The labels read along runs (``trajectory`` labels, or ``paths``), checked where
    they could be wrong: ``count`` of the dataset's states that runs passed through
    (drawn with ``fidelity.seed``; as many as the environment's check has starts), each
    run again from scratch for the horizon and compared with its label.
    `Fidelity.as_dict` with the ``frames`` those runs rendered, or ``{}`` when the
    dataset has no such states."""
    check = run.spec.fidelity
    data = load_dataset(run.path(run.outputs["dataset"]["folders"][env.name]))
    along = np.flatnonzero(data.sources == SOURCE_PATH)
    if len(along) == 0:
        return {}
    rows = np.sort(np.random.default_rng(check.seed).choice(
        along, size=min(count, len(along)), replace=False))
    states = np.asarray(data.states[rows], float)
    outcomes = run.application.real_outcomes(
        run.scenario_for(env), states, grid=run.solved_grid_for(env), duration=run.spec.horizon,
        cache_dir=run.path("outcomes"), executor=run.executor, progress=run.progress)
    return {**compare_verdicts(np.asarray(data.labels[rows]) == 1, outcomes.failed,
                               outcomes["left_box"]).as_dict(),
            "frames": int(np.sum(outcomes["ticks"]))}


#: The source in a fidelity record's key: this module and the dataset code it reads
#: labels with (a test walks its imports of training/).
FIDELITY_CODE = ("reachwatch.pipeline.fidelity_stages", *DATASET_CODE)


def fidelity_stage_key(run: Run, solve: dict, folder) -> str:
    """The key of an environment's fidelity record: the content of what it checks, its
    solve record's (key, and the hash of every file it names: the value function and
    table) and its dataset's arrays (the ``.npy`` files of ``folder``, None without a
    dataset; its manifest names the run directory), the check's settings, and
    `FIDELITY_CODE`. A BRT or dataset made again with other bytes is checked again.
    (The real-loop runs it compares with are cached under the loop's own key.)"""
    arrays = folder and {k: v for k, v in run.output_files(folder).items() if k.endswith(".npy")}
    return digest(solve["key"], solve["files"], run.spec.fidelity.key(), folder, arrays,
                  {"code": modules_source_digest(*FIDELITY_CODE)})


def stage_fidelity(run: Run) -> dict:
    """`fidelity_env` for every environment the run needs (one record each), all
    their real-loop runs together on the run's executor (`each_environment`; inline,
    one after another); raises `BoxExitError` when BRT labels are used where more than
    ``fidelity.max_box_exits`` of the real runs leave the solved box."""
    check = run.spec.fidelity
    if check.starts == 0:
        return {}
    out = each_environment(run, run.environments(), _fidelity_record,
                           what="fidelity check of environment", unit="run")
    check_box_exits(out, check.max_box_exits)
    return out


def _fidelity_record(run: Run, env) -> dict:
    folder = run.outputs.get("dataset", {}).get("folders", {}).get(env.name)
    key = fidelity_stage_key(run, run.records[f"solve_{env.name}"], folder)
    return run.stage(f"fidelity_{env.name}", key, lambda: fidelity_env(run, env))


def check_box_exits(results: dict, max_box_exits: float):
    """Raise `BoxExitError` naming every environment of ``results`` (`fidelity_env`
    outputs by name) labelled by the BRT alone where more than ``max_box_exits`` of
    the real runs left the solved box."""
    crowded = {name: r["brt"]["box_exits_rate"] for name, r in results.items()
               if r.get("labels", {}).get("source") == "brt"
               and r["brt"]["box_exits_rate"] > max_box_exits}
    if crowded:
        raise BoxExitError(
            "the real loop leaves the solved box (along an open axis of the state) within "
            "the horizon in " +
            ", ".join(f"{n}: {100 * r:.0f} % of runs" for n, r in crowded.items()) +
            f" (fidelity.max_box_exits {100 * max_box_exits:.0f} %): there the swept "
            f"table is clamped to its edge and BRT labels are guesses. Label with "
            f"dataset.labels.source: hybrid or rollout, widen the grid, or raise "
            f"fidelity.max_box_exits to accept it (the report then shows it)")
