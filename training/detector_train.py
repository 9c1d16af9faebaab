"""Train the anomaly detector on BRT-labelled datasets (cross-entropy, Adam 3e-4)."""

import dataclasses as dc
import logging
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from reachwatch.diagrams import load_detector, save_checkpoint
from reachwatch.diagrams.checkpoints import UnreadableCheckpoint
from reachwatch.systems import DetectorConfig, build_detector, detector_input
from reachwatch.systems.bounds import bounded, check_bounds, seed_field
from reachwatch.systems.checks import check_torch_device, clip, is_file, short, torch_device

from .metrics import HELD_OUT_RULES, binary_metrics, held_out_threshold, recall_threshold


@dc.dataclass
class DetectorTrainConfig:
    """Everything that determines a trained detector (same config + data = same weights)."""
    detector: DetectorConfig = dc.field(default_factory=DetectorConfig)
    epochs: int = bounded(6, 1, 100_000, whole=True)
    batch_size: int = bounded(64, 1, 65_536, whole=True)
    learning_rate: float = bounded(3e-4, 0.0, 10.0, low_open=True)
    #: Share of the training images kept back to choose the threshold. Samples on one
    #: real run (a dataset's read-along states, ``runs``) are near-copies of each
    #: other, so a run goes to one side whole.
    validation_fraction: float = bounded(0.2, 0.0, 1.0, high_open=True,
                                         note="> 0 with target_recall")
    seed: int = seed_field()
    threshold: float = bounded(0.5, 0.0, 1.0)
    #: > 0: operate at the highest threshold whose recall on the validation split is at
    #: least this (safety first: a missed anomaly costs more than a false alarm).
    target_recall: float = bounded(0.95, 0.0, 1.0)
    #: > 0 (with target_recall): choose the threshold on environments the detector has
    #: not seen. The training datasets are split into this many contiguous groups in
    #: their listed order (as many as datasets: leave-one-environment-out); a detector
    #: trained without each group scores it, and `held_out_threshold` picks the
    #: threshold by ``threshold_rule`` (every_group | pooled). Costs one extra training
    #: per group; the deployed detector is still trained on every dataset.
    threshold_folds: int = bounded(0, 0, whole=True,
                                   note="0, or 2 to the number of training environments")
    threshold_rule: str = "every_group"
    pretrained_path: str = ""
    #: Random per-image colour gains, brightness and contrast in training, so lighting
    #: the training environments lack (e.g. a warm low sun) does not shift the scores.
    augment: bool = True
    #: Weight the loss so each class counts as much as the other (weights from the
    #: training split's class shares). Anomalies are 10-25 % of a dataset, so an
    #: unweighted loss leans towards calling images safe.
    class_balance: bool = False
    device: str = ""                        # "" = CUDA when present, else CPU

    @property
    def judged_recall(self) -> float:
        """The recall the evaluation judges against: ``target_recall``, or the paper's
        95 % when the detector runs at a fixed ``threshold`` (``target_recall`` 0)."""
        return self.target_recall or 0.95

    def validate(self, where="detector"):
        """Raise ValueError naming the first bad field (as ``where.field``); return self."""
        self.detector.validate(f"{where}.detector")
        check_bounds(self, f"{where}.")
        if self.target_recall > 0 and self.validation_fraction == 0:
            raise ValueError(f"{where}.target_recall {self.target_recall} needs a validation "
                             f"split: set {where}.validation_fraction > 0")
        folds = self.threshold_folds
        if folds == 1:
            raise ValueError(f"{where}.threshold_folds must be 0 (validation split) or a whole "
                             f"number >= 2 of environment groups, got {folds!r}")
        if folds and not self.target_recall:
            raise ValueError(f"{where}.threshold_folds {folds} chooses a threshold for "
                             f"target_recall; set {where}.target_recall > 0")
        if self.threshold_rule not in HELD_OUT_RULES:
            raise ValueError(f"{where}.threshold_rule must be one of {HELD_OUT_RULES}, got "
                             f"{short(self.threshold_rule)}")
        for name in ("augment", "class_balance"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{where}.{name} must be true or false, got "
                                 f"{getattr(self, name)!r}")
        if self.pretrained_path and self.detector.arch != "efficientnet_b0":
            raise ValueError(f"{where}.pretrained_path: pretrained weights apply to "
                             f"detector.arch efficientnet_b0 only, got {short(self.detector.arch)}")
        if self.pretrained_path and not is_file(self.pretrained_path):
            raise ValueError(f"{where}.pretrained_path: file not found: "
                             f"{clip(self.pretrained_path, 200)}")
        check_torch_device(f"{where}.device", self.device)
        return self


#: The `DetectorTrainConfig` fields that change neither the weights nor the checkpoint
#: file (``threshold`` and ``target_recall`` are in its metadata; these are not).
THRESHOLD_CHOICE = ("threshold_folds", "threshold_rule")


def colour_jitter(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Per-image random channel gains (0.7-1.3), brightness (0.5-1.3) and contrast
    (0.7-1.3) on normalised inputs (mean = std = 0.5 convention)."""
    n = x.shape[0]
    u = lambda lo, hi, *shape: lo + (hi - lo) * torch.rand(n, *shape, 1, 1,  # noqa: E731
                                                             generator=generator)
    img = x * 0.5 + 0.5
    img = img * u(0.7, 1.3, 3) * u(0.5, 1.3, 1)
    mean = img.mean(dim=(1, 2, 3), keepdim=True)
    img = (img - mean) * u(0.7, 1.3, 1) + mean
    return (img.clamp(0.0, 1.0) - 0.5) / 0.5


def _batches(datasets, index, batch_size, config, device, generator=None):
    """Yield (inputs, dataset-local rows) for global ``index`` rows, in order; with a
    ``generator``, colour-jittered."""
    offsets = np.cumsum([0] + [len(d.labels) for d in datasets])
    for start in range(0, len(index), batch_size):
        rows = index[start:start + batch_size]
        which = np.searchsorted(offsets, rows, side="right") - 1
        images = np.stack([datasets[w].images[r - offsets[w]] for w, r in zip(which, rows)])
        x = detector_input(torch.from_numpy(images), config)
        if generator is not None:
            x = colour_jitter(x, generator)
        yield x.to(device), rows


@torch.no_grad()
def detector_scores(model, config: DetectorConfig, images, *, batch_size=128, device="") -> np.ndarray:
    """Anomaly probabilities for uint8 ``(N, H, W, 3)`` images (memmaps welcome)."""
    device = torch_device(device)
    model = model.to(device).eval()
    out = []
    for start in range(0, len(images), batch_size):
        x = detector_input(torch.from_numpy(np.asarray(images[start:start + batch_size])), config)
        out.append(torch.softmax(model(x.to(device)), dim=1)[:, 1].cpu().double().numpy())
    return np.concatenate(out) if out else np.zeros(0)


def run_groups(datasets):
    """One id per sample of the concatenated ``datasets``: samples on one real run
    (`LabelledData.runs`) share theirs, every other sample has its own. None when no
    dataset has runs."""
    if all(getattr(d, "runs", None) is None for d in datasets):
        return None
    ids, offset, next_run = [], 0, 0
    total = sum(len(d.labels) for d in datasets)
    for d in datasets:
        n = len(d.labels)
        own = offset + np.arange(n)                   # a sample alone: its global row
        runs = getattr(d, "runs", None)
        if runs is None:
            ids.append(own)
        else:
            runs = np.asarray(runs, np.int64)
            on_run = runs >= 0
            ids.append(np.where(on_run, total + next_run + runs, own))
            next_run += int(runs.max(initial=-1)) + 1
        offset += n
    return np.concatenate(ids)


def _split(n, config, rng, groups=None):
    """Validation and training rows: a random ``validation_fraction`` of ``n`` rows,
    or with ``groups`` (`run_groups`) whole groups in random order until that many rows
    (the split of datasets without runs is unchanged)."""
    n_val = int(round(config.validation_fraction * n))
    if groups is None:
        order = rng.permutation(n)
        return np.sort(order[:n_val]), order[n_val:]
    _, group_of = np.unique(groups, return_inverse=True)
    sizes = np.bincount(group_of)
    order = rng.permutation(len(sizes))
    taken = order[:int(np.searchsorted(np.cumsum(sizes[order]), n_val)) + 1] if n_val else order[:0]
    in_val = np.isin(group_of, taken)
    return np.flatnonzero(in_val), np.flatnonzero(~in_val)


def operating_threshold(model, datasets, config: DetectorTrainConfig, labels=None) -> float:
    """The decision threshold: ``config.threshold``, or with ``target_recall > 0`` the
    highest threshold reaching that recall on the training run's validation split
    (re-drawn from the same seed)."""
    if not config.target_recall:
        return config.threshold
    y = np.concatenate(labels if labels is not None else [d.labels for d in datasets])
    val, _ = _split(len(y), config, np.random.default_rng(config.seed), run_groups(datasets))
    offsets = np.cumsum([0] + [len(d.labels) for d in datasets])
    which = np.searchsorted(offsets, val, side="right") - 1
    images = np.stack([datasets[w].images[r - offsets[w]] for w, r in zip(which, val)])
    scores = detector_scores(model, config.detector, images, device=config.device)
    threshold = recall_threshold(y[val], scores, config.target_recall)
    return config.threshold if threshold is None else threshold


def class_weights(labels, config: DetectorTrainConfig):
    """The loss weights of classes 0 and 1: None (equal) unless ``config.class_balance``,
    then ``0.5 / share`` of each class among ``labels``, so both classes carry half the
    loss. A class missing from ``labels`` keeps weight 1."""
    if not config.class_balance:
        return None
    labels = torch.as_tensor(labels)
    share = torch.stack([(labels == c).double().mean() for c in (0, 1)])
    weights = torch.where(share > 0, 0.5 / share.clamp(min=1e-12),
                          torch.ones(2, dtype=torch.float64))
    return weights.float()


def train_detector(datasets, config: DetectorTrainConfig, out_path, *, labels=None,
                   progress=None) -> dict:
    """Train on the concatenated ``datasets`` (`LabelledData`), with their BRT labels or
    the given per-dataset ``labels`` (for baselines); writes a checkpoint."""
    started = time.time()
    config.validate()
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    device = torch_device(config.device)
    y_all = np.concatenate(labels if labels is not None else [d.labels for d in datasets])
    y_all = torch.as_tensor(y_all.astype(np.int64))
    val, train = _split(len(y_all), config, rng, run_groups(datasets))
    jitter = torch.Generator().manual_seed(config.seed) if config.augment else None
    model = build_detector(config.detector, config.pretrained_path).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    weights = class_weights(y_all[train], config)
    loss_fn = nn.CrossEntropyLoss(weight=None if weights is None else weights.to(device))
    losses = []
    epochs = progress(range(config.epochs), desc="train detector") if progress else range(config.epochs)
    for _ in epochs:
        model.train()
        shuffled = train[rng.permutation(len(train))]
        total = 0.0
        for x, rows in _batches(datasets, shuffled, config.batch_size, config.detector, device,
                                jitter):
            optimizer.zero_grad()
            loss = loss_fn(model(x), y_all[rows].to(device))
            loss.backward()
            optimizer.step()
            total += loss.item() * len(rows)
        losses.append(total / max(1, len(train)))
    model.eval()
    threshold = operating_threshold(model, datasets, config, labels)
    metadata = {"image_size": datasets[0].manifest["camera_size"],
                "input_size": [config.detector.height, config.detector.width],
                "threshold": threshold, "target_recall": config.target_recall,
                "environments": [d.manifest["environment"] for d in datasets],
                "samples": int(len(y_all)), "positives": int(y_all.sum()),
                "epochs": config.epochs, "seed": config.seed, "train_losses": losses,
                "class_weights": None if weights is None else weights.tolist(),
                "pretrained": bool(config.pretrained_path)}
    if len(val):
        scores = []
        with torch.no_grad():
            for x, _ in _batches(datasets, val, 128, config.detector, device):
                scores.append(torch.softmax(model(x), 1)[:, 1].cpu().numpy())
        scores = np.concatenate(scores)
        metadata["validation"] = binary_metrics(y_all[val].numpy(), scores >= threshold,
                                                scores).row()
    save_checkpoint(out_path, kind="detector", model=model.cpu(), model_config=config.detector,
                    preprocess_config=None, metadata=metadata)
    # Wall time is returned, not saved: identical training gives an identical file.
    return {**metadata, "train_seconds": round(time.time() - started, 1)}


def environment_groups(n: int, folds: int):
    """``folds`` contiguous groups of dataset indices ``0..n-1`` in order (sizes differ by
    at most one), e.g. the paper's 12 environments listed runway by runway, in 3 groups,
    leave one runway out."""
    if not 2 <= folds <= n:
        raise ValueError(f"threshold_folds must be between 2 and the number of training "
                         f"datasets ({n}), got {folds}")
    return [list(map(int, g)) for g in np.array_split(np.arange(n), folds)]


def held_out_operating_threshold(datasets, config: DetectorTrainConfig, checkpoint_for, *,
                                 labels=None, progress=None):
    """The threshold from detectors that never saw the environments they score (see
    ``DetectorTrainConfig.threshold_folds``): for each group, a detector trained on the
    other datasets (checkpoint ``checkpoint_for(names_left_out)``, trained when missing,
    so an interrupted choice resumes) scores the group's datasets. ``labels`` (one array
    per dataset, as in `train_detector`) replace the datasets' own, e.g. for the
    prediction-error baseline. Returns `HeldOutThreshold` with one group per left-out
    dataset group."""
    config.validate()
    if labels is not None and len(labels) != len(datasets):
        raise ValueError(f"{len(datasets)} datasets need {len(datasets)} label arrays, got "
                         f"{len(labels)}")
    labels_of = (lambda i: datasets[i].labels) if labels is None else (lambda i: labels[i])
    groups = environment_groups(len(datasets), config.threshold_folds)
    scored = {}
    for group in groups:
        names = [datasets[i].manifest["environment"] for i in group]
        path = checkpoint_for(names)
        kept = [i for i in range(len(datasets)) if i not in group]
        model, detector_config, _ = trained_detector(path, lambda: train_detector(
            [datasets[i] for i in kept], config, path, progress=progress,
            labels=None if labels is None else [labels[i] for i in kept]))
        group_labels = np.concatenate([labels_of(i) for i in group])
        scores = np.concatenate([detector_scores(model, detector_config, datasets[i].images,
                                                 device=config.device) for i in group])
        scored["+".join(names)] = (group_labels, scores)
    return held_out_threshold(scored, config.target_recall, rule=config.threshold_rule)


def trained_detector(path, train):
    """`load_detector` of the checkpoint at ``path``, trained first by ``train()`` when
    there is none, or when torch cannot read the one there (empty, truncated: a run
    killed as it wrote it before atomic writes, a damaged disk): trained again, said in
    one line, instead of stopping the run. One of another version or kind, or with
    weights that are not finite, is refused as `load_detector` says (not deleted)."""
    path = Path(path)
    if path.exists():
        try:
            return load_detector(path)
        except UnreadableCheckpoint as e:
            logging.getLogger("reachwatch").warning(f"{e}; training it again")
            path.unlink()
    train()
    return load_detector(path)
