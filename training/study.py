"""The paper's experiment end to end: BRTs of training and held-out environments,
BRT-labelled datasets, the detector, the baselines, Table 2 and its figures.

Every artifact lands in ``out`` (value functions, datasets, checkpoints) and is reused
when present, so a re-run skips finished work and an interrupted one resumes."""

import copy
import dataclasses as dc
import hashlib
import json
from pathlib import Path
from typing import List

import numpy as np

from reachwatch.diagrams import load_detector
from reachwatch.reach import (Grid, ValueFunction, resolved, solve_brt, sweep_closed_loop,
                              sweep_key, taxi_dynamics)
from reachwatch.systems import Environment
from reachwatch.systems.files import atomic_write_bytes, cache_root

from .baselines import prediction_error, prediction_error_labels
from .dataset import DatasetSpec, build_dataset, load_dataset
from .detector_train import DetectorTrainConfig, operating_threshold, train_detector
from .evaluation import Detector, csv_table, evaluate_environment, markdown_table
from .figures import plot_error_vs_margin, plot_overlay
from .metrics import best_threshold
from .taxinet_train import TaxiNetTrainConfig, train_taxinet_ensemble


@dc.dataclass
class StudyConfig:
    """Which environments, how fine, how much data."""
    train: List[Environment] = dc.field(default_factory=list)
    test: List[Environment] = dc.field(default_factory=list)
    grid_shape: List[int] = dc.field(default_factory=lambda: [21, 21, 21])
    horizon: float = 8.0
    dataset: DatasetSpec = dc.field(default_factory=DatasetSpec)
    detector: DetectorTrainConfig = dc.field(default_factory=DetectorTrainConfig)
    ensemble_seeds: List[int] = dc.field(default_factory=lambda: [1, 2, 3, 4, 5])
    ensemble_samples: int = 4000
    ensemble_epochs: int = 400


def value_function_for(scenario, grid, horizon, out, *, executor=None, cache=None):
    """The BRT of ``scenario``'s environment on ``grid`` (sweep cached, value saved)."""
    scenario = resolved(scenario)
    path = Path(out) / "brt" / f"value_{sweep_key(scenario, grid)}_{horizon:g}s.npz"
    if path.exists():
        return ValueFunction.load(path)
    table = sweep_closed_loop(scenario, grid, cache_dir=cache or cache_root() / "sweeps",
                              executor=executor)
    vf = solve_brt(grid, taxi_dynamics(scenario), table["p_controller.steering_angle"],
                   horizon=horizon, period=scenario.controller.period)
    vf.metadata["environment"] = scenario.environment.name
    vf.save(path)
    return vf


def run_study(base_scenario, config: StudyConfig, out, *, executor=None, progress=None):
    """Runs the study; returns the Table-2 rows (also written as ``table2.md/.csv``)."""
    out = Path(out)
    ensemble = sorted((out / "ensemble").glob("taxinet_seed*.pt"))
    if config.ensemble_seeds and len(ensemble) != len(config.ensemble_seeds):
        taxinet_config = TaxiNetTrainConfig(camera=base_scenario.camera,
                                            samples=config.ensemble_samples,
                                            epochs=config.ensemble_epochs)
        ensemble = train_taxinet_ensemble(taxinet_config, out / "ensemble",
                                          config.ensemble_seeds, progress=progress)
    data, brts = {}, {}
    for env in config.train + config.test:
        scenario = copy.deepcopy(base_scenario)
        scenario.environment = env
        grid = Grid.paper(env.half_width, tuple(config.grid_shape))
        brts[env.name] = value_function_for(scenario, grid, config.horizon, out,
                                            executor=executor)
        data[env.name] = load_dataset(build_dataset(out / "datasets", scenario, brts[env.name],
                                                    config.dataset, ensemble=ensemble))
    train_data = [data[e.name] for e in config.train]
    detectors = []
    tag = hashlib.sha256(json.dumps(dc.asdict(config.detector), sort_keys=True).encode()
                         ).hexdigest()[:10]      # a changed training config retrains
    path = out / f"detector_{tag}.pt"
    if not path.exists():
        train_detector(train_data, config.detector, path, progress=progress)
    model, det_config, meta = load_detector(path)
    threshold_brt = operating_threshold(model, train_data, config.detector)
    detectors.append(Detector("detector (BRT labels)", model, det_config, threshold_brt))
    # Baseline (a) as training labels: the error threshold that best matches the BRT
    # labels on the training environments, then the same detector trained on them.
    errors = np.concatenate([prediction_error(d.states, d.estimates) for d in train_data])
    threshold, _ = best_threshold(np.concatenate([d.labels for d in train_data]), errors)
    path = out / f"detector_prediction_error_labels_{tag}.pt"
    if not path.exists():
        train_detector(train_data, config.detector, path, progress=progress,
                       labels=[prediction_error_labels(d, threshold) for d in train_data])
    model, det_config, _ = load_detector(path)
    detectors.append(Detector(f"detector (prediction-error labels, error > {threshold:.3f})",
                              model, det_config, operating_threshold(
                                  model, train_data, config.detector,
                                  [prediction_error_labels(d, threshold) for d in train_data])))
    rows, figures = [], out / "figures"
    for env in config.test:
        env_rows, scores = evaluate_environment(data[env.name], detectors,
                                                device=config.detector.device)
        rows += env_rows
        d, vf = data[env.name], brts[env.name]
        predictions = {r["method"]: scores[r["method"]] >= r["threshold"] for r in env_rows}
        plot_error_vs_margin({m: (d.values, d.labels, p) for m, p in predictions.items()},
                             figures / f"error_vs_margin_{env.name}.png")
        for k, (method, p) in enumerate(predictions.items()):
            plot_overlay(vf, d.states, d.labels, p, py=175.0, half_width=env.half_width,
                         path=figures / f"overlay_{env.name}_{k}.png",
                         title=f"{env.name}: {method[:40]}")
    atomic_write_bytes(out / "table2.md", markdown_table(rows).encode())
    atomic_write_bytes(out / "table2.csv", csv_table(rows).encode())
    meta["operating_threshold"] = threshold_brt
    atomic_write_bytes(out / "detector_metadata.json", json.dumps(meta, indent=1).encode())
    return rows
