"""The dataset stage of ``reachwatch run``: the ensemble baseline's TaxiNets, then one
labelled dataset per train/test environment, each in a content-addressed folder (so
its folder is known before it is built, and a killed build resumes there)."""

import concurrent.futures as cf

from reachwatch.reach import InlineExecutor, ValueFunction
from reachwatch.reach.application import load_application
from reachwatch.training.dataset import build_dataset, dataset_folder, label_summary, load_dataset

from .spec import digest
from .stages import Run


def _ensemble(run: Run):
    paths = ensemble_paths(run)
    if not all(p.exists() for p in paths):
        spec = run.spec.ensemble
        run.application.train_ensemble(_ensemble_config(run), paths[0].parent, spec.seeds,
                                       progress=run.bar())
    return paths


def _ensemble_config(run: Run):
    """The application's training config of the ensemble's members (its fields key
    their folder: the taxi's is a `TaxiNetTrainConfig`)."""
    spec = run.spec.ensemble
    return run.application.ensemble_config(run.spec.scenario, samples=spec.samples,
                                           epochs=spec.epochs)


def ensemble_paths(run: Run) -> list:
    """The checkpoints of the ensemble baseline's members (trained or not yet); none
    without seeds (an application without an ensemble baseline is not asked)."""
    spec = run.spec.ensemble
    if not spec.seeds:
        return []
    folder = run.path(f"ensemble/{digest(_ensemble_config(run), spec.seeds)}")
    return [folder / f"taxinet_seed{s}.pt" for s in spec.seeds]


def _build(root, scenario, value_path, spec, ensemble, progress, box=None, application="",
           executor=None):
    """One dataset, built here with its image chunks and real-loop runs on ``executor``
    (their arrays come back here, where the dataset is written); a folder whose arrays
    are not the ones its manifest recorded is built again."""
    return str(build_dataset(root, scenario, ValueFunction.load(value_path), spec,
                             ensemble=ensemble, progress=progress, box=box, rebuild=True,
                             application=load_application(application), executor=executor))


def _label_box(run: Run, env):
    """The paper's box, where states are labelled, when the solved box is wider."""
    if run.solved_grid_for(env) == run.grid_for(env):
        return None
    grid = run.grid_for(env)
    return grid.lo.tolist(), grid.hi.tolist()


def dataset_folder_for(run: Run, env, value_path, ensemble) -> str:
    """The folder (relative to the run) the dataset stage builds ``env``'s dataset in,
    from its BRT (``value_path``) and the ensemble's checkpoints: content-addressed, so
    known before it is built."""
    folder = dataset_folder(run.path("datasets"), run.scenario_for(env),
                            ValueFunction.load(value_path), run.spec.dataset_spec_for(env),
                            ensemble=[str(p) for p in ensemble], box=_label_box(run, env),
                            application=run.application)
    return run.rel(folder)


def stage_dataset(run: Run) -> dict:
    """The ensemble baseline's TaxiNets, then one labelled dataset per train/test
    environment (`RunSpec.dataset_spec_for`): each written here, its image chunks and
    real-loop runs done on the run's executor. Inline, one environment after another;
    else each environment's build is a thread here, so that all feed the executor."""
    ensemble = _ensemble(run)
    envs = run.selected(run.spec.training_environments() + run.spec.held_out_environments())
    builds = (InlineExecutor() if isinstance(run.executor, InlineExecutor)
              else cf.ThreadPoolExecutor(max(1, len(envs)), thread_name_prefix="dataset"))
    try:
        futures = {e.name: builds.submit(
            _build, str(run.path("datasets")), run.scenario_for(e),
            str(run.path(run.outputs["solve"][e.name]["value"])), run.spec.dataset_spec_for(e),
            [str(p) for p in ensemble], run.progress, _label_box(run, e), run.spec.application,
            run.executor) for e in envs}
        bar = run.bar()              # hours at study scale: how many environments are done
        finished = cf.as_completed(futures.values())
        names, data = {future: name for name, future in futures.items()}, {}
        for future in (bar(finished, total=len(futures), desc="datasets", unit="environment")
                       if bar else finished):
            if future.exception() is None:   # a failed build raises below, once all are done
                data[names[future]] = load_dataset(future.result())
                run.log(f"[dataset_{names[future]}] labelled: "
                        f"{label_summary(data[names[future]].manifest)}")
    finally:     # (interrupted: a build thread ends when the executor is stopped)
        builds.shutdown(wait=False, cancel_futures=True)
    folders = {name: run.rel(f.result()) for name, f in futures.items()}
    data = {name: data[name] for name in futures}          # the environments' order
    return {"ensemble": [run.rel(p) for p in ensemble], "folders": folders,
            "positives": {name: float(d.labels.mean()) for name, d in data.items()},
            "labels": {name: {**d.manifest["labels"], "counts": d.manifest["label_counts"]}
                       for name, d in data.items()}}
