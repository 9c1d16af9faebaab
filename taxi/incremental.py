"""Incremental training (the paper's last experiment): fine-tune TaxiNet on the
anomalous states mined from the BRT-labelled training datasets, replaying
nominal-condition frames so it does not forget the condition it was trained on.

Mined states are those labelled anomalous (``V <= 0``) that still lie on the runway
(``|px| < B``): off-runway states have already failed and teach nothing about
staying on. Their frames are re-rendered at the camera resolution TaxiNet reads
(datasets store them at the detector's smaller size)."""

import time
from typing import List

import numpy as np
import torch

from reachwatch.diagrams import StateRenderer, load_checkpoint, load_taxinet, save_checkpoint
from reachwatch.systems import CameraConfig, Environment, TaxiNetConfig
from reachwatch.systems.models import preprocess_batched

from .taxinet_data import render_states, sample_states, targets
from .taxinet_train import estimation_errors, fit_regressor


def mine_anomalies(datasets, limit: int, rng: np.random.Generator) -> List[tuple]:
    """``[(Environment, states (n, 3))]`` from ``[(Environment, LabelledData)]``: the
    anomalous on-runway states of each, at most ``limit`` in all (equal shares)."""
    share = -(-limit // max(len(datasets), 1))
    mined = []
    for env, d in datasets:
        index = np.flatnonzero((d.labels == 1) & (np.abs(d.states[:, 0]) < env.half_width))
        if len(index) > share:
            index = np.sort(rng.choice(index, share, replace=False))
        mined.append((env, np.asarray(d.states[index])))
    return mined


def fine_tune_taxinet(checkpoint, mined, config, camera: CameraConfig,
                      out_path, *, progress=None) -> dict:
    """Fine-tune the TaxiNet in ``checkpoint`` on ``mined`` states (from
    `mine_anomalies`) plus ``config.replay`` nominal frames; write ``out_path``
    and return its metadata (counts, errors on the mined states before/after).
    ``config``: the run file's ``incremental`` section
    (`reachwatch.pipeline.spec.IncrementalConfig`), read for ``replay``, ``epochs``,
    ``batch_size``, ``learning_rate`` and ``seed``."""
    started = time.time()
    model, preprocess_config, meta = load_taxinet(checkpoint)
    model_config = TaxiNetConfig(**load_checkpoint(checkpoint, kind="taxinet")["model_config"])
    images, states = [], []
    for env, s in mined:
        if len(s):
            renderer = StateRenderer(environment=env, camera=camera)
            images.append(render_states(renderer, s))
            states.append(s)
    if not states:
        raise ValueError("incremental training: no anomalous on-runway states were mined "
                         "from the training datasets (more samples or a finer grid?)")
    mined_x = preprocess_batched(np.concatenate(images), preprocess_config)
    mined_y = torch.from_numpy(targets(np.concatenate(states)))
    rng = np.random.default_rng(config.seed)
    replay_states = sample_states(config.replay, rng)
    replay_x = preprocess_batched(render_states(StateRenderer(environment=Environment(), camera=camera), replay_states),
                                  preprocess_config) if config.replay else mined_x[:0]
    replay_y = torch.from_numpy(targets(replay_states)) if config.replay else mined_y[:0]
    before = estimation_errors(model, mined_x, mined_y)
    torch.manual_seed(config.seed)
    losses = fit_regressor(model, torch.cat([mined_x, replay_x]), torch.cat([mined_y, replay_y]),
                           epochs=config.epochs, batch_size=config.batch_size,
                           learning_rate=config.learning_rate, seed=config.seed,
                           scale=model_config.output_scale,
                           progress=(lambda it: progress(it, desc="fine-tune")) if progress
                           else None)
    metadata = {**meta, "fine_tuned_from": str(checkpoint),
                "mined_states": int(len(mined_y)), "replayed_states": int(config.replay),
                "mined_per_environment": {e.name: int(len(s)) for e, s in mined},
                "fine_tune_epochs": config.epochs, "final_train_loss": losses[-1],
                "mined_error_before": before,
                "mined_error_after": estimation_errors(model, mined_x, mined_y)}
    metadata.pop("train_seconds", None)     # the base checkpoint's, if it recorded one
    save_checkpoint(out_path, kind="taxinet", model=model, model_config=model_config,
                    preprocess_config=preprocess_config, metadata=metadata)
    # Wall time is returned, not saved: identical training gives an identical file.
    return {**metadata, "fine_tune_seconds": round(time.time() - started, 1)}
