"""The dataset stage of ``reachwatch run``: the ensemble baseline's TaxiNets, then one
labelled dataset per train/test environment, each in a content-addressed folder (so
its folder is known before it is built, and a killed build resumes there)."""

import functools

from reachwatch.reach import ValueFunction
from reachwatch.reach.application import application_key, load_application
from reachwatch.reach.fingerprint import fingerprint, modules_source_digest
from reachwatch.training.dataset import DATASET_CODE
from reachwatch.training.dataset import FORMAT as DATASET_FORMAT
from reachwatch.training.dataset import build_dataset, dataset_folder, label_summary, load_dataset

from .keys import digest
from .stages import Run
from .together import each_environment


def _ensemble(run: Run):
    paths = ensemble_paths(run)
    if not all(p.exists() for p in paths):
        spec = run.spec.ensemble
        paths[0].parent.mkdir(parents=True, exist_ok=True)
        run.application.train_ensemble(_ensemble_config(run), paths, list(spec.seeds),
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
    without seeds (an application without an ensemble baseline is not asked). Their
    folder is keyed by the training config, the seeds, the software and render stack
    (`reach.fingerprint.fingerprint`: members trained on another machine's renders, or
    by another torch, are not reused) and the application's code (`application_key`:
    its `train_ensemble` trains them)."""
    spec = run.spec.ensemble
    if not spec.seeds:
        return []
    own = application_key(run.application)
    key = fingerprint(_ensemble_config(run), list(spec.seeds), own)[:16]
    folder = run.path(f"ensemble/{key}")
    return [folder / f"member_seed{s}.pt" for s in spec.seeds]


def _build(root, scenario, value_path, spec, ensemble, progress, box, application: str,
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


def dataset_key(run: Run) -> str:
    """The dataset stage's key: each solved BRT by path and content, each environment's
    dataset spec by name (which environments get a dataset, and the labels each gets:
    ``held_out_labels`` for the held-out ones, so that swapped roles label again), the
    ensemble baseline's settings, the camera, and the dataset code."""
    spec = run.spec
    return digest(
        {n: r["value"] for n, r in run.outputs["solve"].items()},
        {n: run.content_key(f"solve_{n}") for n in run.outputs["solve"]},
        {e.name: spec.dataset_spec_for(e).key()
         for e in spec.training_environments() + spec.held_out_environments()},
        spec.ensemble, spec.scenario.camera,
        {"format": DATASET_FORMAT, "code": modules_source_digest(
            *DATASET_CODE, "reachwatch.pipeline.dataset_stages")})


def stage_dataset(run: Run) -> dict:
    """The ensemble baseline's TaxiNets, then one labelled dataset per train/test
    environment (`RunSpec.dataset_spec_for`): each written here, its image chunks and
    real-loop runs done on the run's executor, every environment's at once
    (`each_environment`; inline, one environment after another)."""
    ensemble = _ensemble(run)
    envs = run.selected(run.spec.training_environments() + run.spec.held_out_environments())
    bar = run.bar()              # hours at study scale: how many environments are done

    def build(run: Run, env):
        folder = _build(str(run.path("datasets")), run.scenario_for(env),
                        str(run.path(run.outputs["solve"][env.name]["value"])),
                        run.spec.dataset_spec_for(env), [str(p) for p in ensemble],
                        run.progress, _label_box(run, env), run.spec.application, run.executor)
        data = load_dataset(folder)
        run.log(f"[dataset_{env.name}] labelled: {label_summary(data.manifest)}")
        return folder, data
    built = each_environment(run, envs, build, what="dataset of environment",
                             bar=bar and functools.partial(bar, None, desc="datasets",
                                                           unit="environment"))
    data = {name: d for name, (_, d) in built.items()}
    return {"ensemble": [run.rel(p) for p in ensemble],
            "folders": {name: run.rel(folder) for name, (folder, _) in built.items()},
            "positives": {name: float(d.labels.mean()) for name, d in data.items()},
            "labels": {name: {**d.manifest["labels"], "counts": d.manifest["label_counts"]}
                       for name, d in data.items()}}
