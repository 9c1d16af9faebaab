"""Train TaxiNet on the nominal condition (KMWH, 9 h, clear, as the authors' was)."""

import dataclasses as dc
import time

import numpy as np
import torch
from torch import nn

from reachwatch.diagrams import StateRenderer, save_checkpoint
from reachwatch.systems import (CameraConfig, Environment, PreprocessConfig, TaxiNetConfig,
                                build_taxinet)
from reachwatch.systems.models import preprocess_batched

from .taxinet_data import render_states, sample_states, targets


@dc.dataclass
class TaxiNetTrainConfig:
    """Everything that determines a trained TaxiNet (same config + seed = same weights)."""
    environment: Environment = dc.field(default_factory=Environment)   # KMWH 9 h clear
    camera: CameraConfig = dc.field(default_factory=CameraConfig)
    model: TaxiNetConfig = dc.field(default_factory=TaxiNetConfig)
    preprocess: PreprocessConfig = dc.field(default_factory=PreprocessConfig)
    samples: int = 8000
    validation_fraction: float = 0.1
    epochs: int = 200
    batch_size: int = 256
    learning_rate: float = 1e-3
    seed: int = 0


def fit_regressor(model, inputs, outputs, *, epochs, batch_size, learning_rate, seed,
                  scale, progress=None):
    """MSE + Adam (amsgrad) on ``outputs / scale``; returns per-epoch train losses."""
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=learning_rate, amsgrad=True)
    loss_fn, losses = nn.MSELoss(), []
    scale = torch.as_tensor(scale, dtype=torch.float32)
    epochs_iter = progress(range(epochs)) if progress else range(epochs)
    for _ in epochs_iter:
        model.train()
        order = torch.randperm(len(inputs), generator=generator)
        total = 0.0
        for start in range(0, len(inputs), batch_size):
            idx = order[start:start + batch_size]
            optimizer.zero_grad()
            loss = loss_fn(model(inputs[idx]) / scale, outputs[idx] / scale)
            loss.backward()
            optimizer.step()
            total += loss.item() * len(idx)
        losses.append(total / len(inputs))
    return losses


@torch.no_grad()
def estimation_errors(model, inputs, outputs) -> dict:
    """Mean and 95th-percentile absolute errors in px (m) and theta (deg)."""
    model.eval()
    err = (model(inputs) - outputs).abs().numpy()
    return {"px_mean_m": float(err[:, 0].mean()), "px_p95_m": float(np.percentile(err[:, 0], 95)),
            "theta_mean_deg": float(err[:, 1].mean()),
            "theta_p95_deg": float(np.percentile(err[:, 1], 95))}


def render_training_set(config: TaxiNetTrainConfig, progress=None):
    """Network inputs and targets of ``config.samples`` nominal-condition states."""
    rng = np.random.default_rng(config.seed)
    states = sample_states(config.samples, rng)
    renderer = StateRenderer(environment=config.environment, camera=config.camera)
    images = render_states(renderer, states,
                           progress=(lambda it: progress(it, desc="render")) if progress else None)
    return preprocess_batched(images, config.preprocess.validate()), torch.from_numpy(targets(states))


def fit_taxinet(config: TaxiNetTrainConfig, x, y, out_path, *, seed=None, progress=None,
                started=None) -> dict:
    """Train one TaxiNet on prepared ``x, y`` (first ``validation_fraction`` held out)
    with ``seed`` (default ``config.seed``); writes the checkpoint, returns metadata."""
    started = started or time.time()
    seed = config.seed if seed is None else seed
    torch.manual_seed(seed)
    n_val = int(round(config.validation_fraction * len(x)))
    model = build_taxinet(config.model, config.preprocess)
    losses = fit_regressor(model, x[n_val:], y[n_val:], epochs=config.epochs,
                           batch_size=config.batch_size, learning_rate=config.learning_rate,
                           seed=seed, scale=config.model.output_scale,
                           progress=(lambda it: progress(it, desc="train")) if progress else None)
    metadata = {
        "image_size": [config.camera.height, config.camera.width],
        "environment": config.environment.name, "samples": config.samples,
        "epochs": config.epochs, "seed": seed, "data_seed": config.seed,
        "final_train_loss": losses[-1],
        "validation": estimation_errors(model, x[:n_val], y[:n_val]) if n_val else {},
        "torch": str(torch.__version__),
    }
    save_checkpoint(out_path, kind="taxinet", model=model, model_config=config.model,
                    preprocess_config=config.preprocess, metadata=metadata)
    # Wall time is returned, not saved: identical training gives an identical file.
    return {**metadata, "train_seconds": round(time.time() - started, 1)}


def train_taxinet(config: TaxiNetTrainConfig, out_path, progress=None) -> dict:
    """Render a labelled set, train, and write a checkpoint; returns its metadata."""
    started = time.time()
    x, y = render_training_set(config, progress)
    return fit_taxinet(config, x, y, out_path, progress=progress, started=started)


def train_taxinet_ensemble(config: TaxiNetTrainConfig, paths, seeds, progress=None):
    """The ensemble baseline: TaxiNets differing only in their training seed (same
    rendered data), the one of ``seeds[i]`` written to ``paths[i]``."""
    if len(paths) != len(seeds):
        raise ValueError(f"train_taxinet_ensemble: {len(paths)} paths for {len(seeds)} seeds")
    x, y = render_training_set(config, progress)
    for path, seed in zip(paths, seeds):
        fit_taxinet(config, x, y, path, seed=seed, progress=progress)
