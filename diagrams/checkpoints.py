"""Checkpoints: ``state_dict`` + model config + preprocessing config + metadata.

Saved with `torch.save`, loaded with ``torch.load(weights_only=True)``, so a file holds
only tensors and plain Python values. Written atomically.
"""

import dataclasses as dc
import errno
import io
import json
import math
import re
import zipfile
from pathlib import Path

import torch

from reachwatch.systems import (DetectorConfig, HistoryMonitorConfig, HistoryRiskEnsemble,
                                HistoryRiskModel, PreprocessConfig, TaxiNetConfig, build_detector,
                                build_taxinet, check_members)
from reachwatch.systems.checks import short
from reachwatch.systems.files import (atomic_write_bytes, check_keyed, file_hash,  # noqa: F401
                                      keyed_check_active, local_copy)  # (file_hash re-exported)

FORMAT = "reachwatch.checkpoint"
VERSION = 1
#: The reference TaxiNet shipped with the package (see `reachwatch taxinet train`).
REFERENCE_TAXINET = Path(__file__).parent / "weights" / "taxinet_tiny.pt"


class CheckpointError(ValueError):
    """A checkpoint file that is missing, corrupt, or not what was asked for."""


class UnreadableCheckpoint(CheckpointError):
    """A checkpoint file whose bytes torch cannot read: empty, truncated, or not a
    checkpoint at all (what may be written again; not one of another version or kind)."""


def save_checkpoint(path, *, kind: str, model: torch.nn.Module, model_config,
                    preprocess_config, metadata: dict) -> Path:
    """Write a checkpoint of ``kind`` (e.g. ``taxinet``) atomically; returns the path.
    A `HistoryRiskEnsemble`'s metadata gains its ``members`` (unless given)."""
    if isinstance(model, HistoryRiskEnsemble):
        metadata = {"members": len(model.members), **metadata}
    payload = {"format": FORMAT, "version": VERSION, "kind": kind,
               "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
               "model_config": dc.asdict(model_config),
               "preprocess": dc.asdict(preprocess_config) if preprocess_config else {},
               "metadata": _plain(metadata)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def _plain(metadata: dict) -> dict:
    """Metadata as plain JSON values, so ``weights_only`` loading accepts it."""
    try:
        return json.loads(json.dumps(metadata, default=lambda v: v.item() if hasattr(v, "item")
                                     else str(v)))
    except (TypeError, ValueError) as e:
        raise ValueError(f"checkpoint metadata must be JSON-like: {e}") from None


def load_checkpoint(path, *, kind) -> dict:
    """The raw checkpoint dict of ``kind`` (a name, or a tuple of accepted names);
    raises `CheckpointError` saying what is wrong (also in a task, when the file is not
    the one its driver keyed: `check_keyed`)."""
    named, path = path, Path(local_copy(path))      # the copy that came with the task
    if path.is_dir():
        raise CheckpointError(f"{path} is a folder, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise UnreadableCheckpoint(f"{path} is empty, not a checkpoint")
    if keyed_check_active():            # hashed only in a task that brought its keys
        try:
            check_keyed(named, file_hash(path, 64), f"the checkpoint {named}")
        except ValueError as e:
            raise CheckpointError(str(e)) from None
    if not zipfile.is_zipfile(path):    # torch.save's format; a truncated one loses its end
        raise UnreadableCheckpoint(f"{path} is not a readable checkpoint (corrupt, truncated "
                                   f"or not written by reachwatch): not a torch.save archive")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except OSError as e:
        if e.errno not in (None, errno.EINVAL):     # torch's error for a truncated file
            raise CheckpointError(f"{path}: cannot read it ({e.strerror or e})") from None
        raise UnreadableCheckpoint(f"{path} is not a readable checkpoint (corrupt, truncated "
                                   f"or not written by reachwatch): {type(e).__name__}: "
                                   f"{str(e)[:200]}") from None
    except Exception as e:  # torch raises several types for truncated/foreign files
        # its first line, less its advice on loading files one trusts
        first = ("it holds Python objects that a weights-only load refuses"
                 if "Weights only load failed" in str(e) else
                 re.sub(r"\x1b\[[0-9;]*m", "", (str(e).strip().splitlines() or [""])[0]))
        raise UnreadableCheckpoint(f"{path} is not a readable checkpoint (corrupt, truncated or "
                              f"not written by reachwatch): {type(e).__name__}: "
                              f"{first[:200]}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is a torch file but not a reachwatch checkpoint")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"{path} has checkpoint version {payload.get('version')}, "
                              f"this reachwatch reads version {VERSION}")
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if payload.get("kind") not in kinds:
        raise CheckpointError(f"{path} holds a '{payload.get('kind')}' model, not a "
                              f"{' or '.join(repr(k) for k in kinds)} model")
    missing = {"state_dict", "model_config", "preprocess", "metadata"} - set(payload)
    if missing:
        raise CheckpointError(f"{path} lacks {sorted(missing)}")
    _check_numbers(path, payload)
    return payload


def _check_numbers(path, payload):
    """Raise `CheckpointError` when a checkpoint's weights hold NaN or infinite values, or
    a history monitor's Platt ``calibration`` is not two finite numbers: such a model
    answers NaN, which never reaches a threshold, so a monitor would never warn."""
    weights = payload["state_dict"]
    if not isinstance(weights, dict) or not isinstance(payload["metadata"], dict):
        raise CheckpointError(f"{path}: its state_dict and metadata must be mappings")
    for name, value in weights.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() \
                and not bool(torch.isfinite(value).all()):
            raise CheckpointError(f"{path}: weight {short(name)} holds NaN or infinite "
                                  f"values; the checkpoint is corrupt (train it again)")
    calibration = payload["metadata"].get("calibration", (1.0, 0.0))
    if payload["kind"] == "history_monitor" and not (
            isinstance(calibration, (list, tuple)) and len(calibration) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in calibration)):
        raise CheckpointError(f"{path}: its calibration must be two finite numbers [a, b], "
                              f"got {short(calibration)}")
    if payload["kind"] == "history_monitor":
        members = payload["metadata"].get("members", 1)
        try:
            check_members(members)
        except ValueError as e:
            raise CheckpointError(f"{path}: its members: {e}") from None
        held = len({name.split(".")[1] for name in weights if name.startswith("members.")}) or 1
        if held != members:
            raise CheckpointError(f"{path}: its weights hold {held} member(s) of an ensemble, "
                                  f"its metadata says members: {members}")


def _config(cls, data, path, what):
    try:
        return cls(**data)
    except TypeError as e:
        raise CheckpointError(f"{path}: {what} does not match this reachwatch: {e}") from None


def _load_model(path, kind, config_cls, build, preprocess_cls=None):
    """``(model, config, preprocess_config, metadata)``; ``build(config,
    preprocess_config, metadata)`` makes the untrained model the weights load into."""
    payload = load_checkpoint(path, kind=kind)
    config = _config(config_cls, payload["model_config"], path, "model_config")
    preprocess_config = (_config(preprocess_cls, payload["preprocess"], path, "preprocess")
                         if preprocess_cls else None)
    model = build(config, preprocess_config, payload["metadata"])
    try:
        model.load_state_dict(payload["state_dict"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not fit the {kind} its "
                              f"config describes: {str(e)[:300]}") from None
    return model.eval(), config, preprocess_config, payload["metadata"]


def load_taxinet(path=REFERENCE_TAXINET):
    """``(model, preprocess_config, metadata)`` from a TaxiNet checkpoint (eval mode)."""
    model, _, preprocess_config, metadata = _load_model(
        path, "taxinet", TaxiNetConfig, lambda c, p, _: build_taxinet(c, p), PreprocessConfig)
    return model, preprocess_config, metadata


def load_detector(path):
    """``(model, detector_config, metadata)`` from an anomaly-detector checkpoint."""
    model, config, _, metadata = _load_model(path, "detector", DetectorConfig,
                                             lambda c, _, __: build_detector(c))
    return model, config, metadata


#: The checkpoint kinds a guarded loop's ``monitor.detector`` may name.
MONITOR_KINDS = ("detector", "history_monitor")


def checkpoint_kind(path, kinds=MONITOR_KINDS) -> str:
    """The kind of the checkpoint at ``path`` (one of ``kinds``, else `CheckpointError`)."""
    return load_checkpoint(path, kind=kinds)["kind"]


def checkpoint_metadata(path, kinds=MONITOR_KINDS) -> dict:
    """The metadata of the checkpoint at ``path`` (one of ``kinds``), e.g. the
    ``threshold`` and ``flag_rule`` a monitor's was chosen with."""
    return load_checkpoint(path, kind=kinds)["metadata"]


def load_history_monitor(path):
    """``(model, config, metadata)`` from a history-monitor checkpoint (eval mode); the
    metadata holds its ``threshold``, Platt ``calibration`` ``[a, b]`` and, for an
    ensemble, its ``members`` (the model is then a `HistoryRiskEnsemble`, else a
    `HistoryRiskModel`)."""
    def build(config, _, metadata):
        members = metadata.get("members", 1)
        return HistoryRiskModel(config) if members == 1 else HistoryRiskEnsemble(config, members)
    model, config, _, metadata = _load_model(path, "history_monitor", _history_config, build)
    return model, config, metadata


def _history_config(**fields) -> HistoryMonitorConfig:
    """A history monitor's config as its checkpoint holds it; one written before
    ``input_norm`` existed was trained ``fixed`` (not today's default), and one written
    before ``pool`` averaged the last feature map whole ([1, 1])."""
    return HistoryMonitorConfig(**{"input_norm": "fixed", "pool": [1, 1], **fields})
