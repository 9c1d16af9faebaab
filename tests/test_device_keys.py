"""A result computed on another kind of device (CUDA where present, unless told) is
another result: the BRT's solve and the detector's weights are keyed by it, so a run
moved between a machine with a GPU and one without computes them again instead of
reusing them."""

import torch

from reachwatch.pipeline.brt_stages import solve_stage_key
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.detector_stages import detector_weights
from reachwatch.pipeline.stages import Run
from reachwatch.systems.checks import device_kind, torch_device
from reachwatch.training.detector_train import DetectorTrainConfig
from tiny_run import TINY


def test_the_default_device_is_cuda_where_present(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert device_kind("") == device_kind(None) == "cpu" and torch_device("cpu").type == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert device_kind("") == "cuda" and device_kind("cpu") == "cpu"
    assert device_kind("cuda:1") == "cuda"


def test_the_detectors_weights_and_the_solve_are_keyed_by_the_device_kind(tiny_run, monkeypatch):
    folder, _ = tiny_run
    run = Run(load_run_spec(data=TINY), folder, progress=False, log=lambda m: None)
    env = run.spec.training_environments()[0]
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cpu = solve_stage_key(run, env), detector_weights(DetectorTrainConfig())
    told = detector_weights(DetectorTrainConfig(device="cpu"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    gpu = solve_stage_key(run, env), detector_weights(DetectorTrainConfig())
    assert cpu[0] != gpu[0] and cpu[1] != gpu[1]
    assert cpu[1]["device"] == "cpu" and gpu[1]["device"] == "cuda"
    assert detector_weights(DetectorTrainConfig(device="cpu")) == told      # told: kept


def test_the_solve_key_covers_its_settings(tiny_run, seed_caches, tmp_path):
    """Each setting the solve reads is in its key (a refine, robust or map-selection
    setting dropped from it would reuse the other setting's BRT)."""
    folder = seed_caches(tmp_path / "run")
    keys = set()
    for extra in ("", "refine: {levels: 1}\n", "refine: {levels: 1, band: 3.0}\n",
                  "horizon: 3.0\n", "periods_per_step: 20\n"):
        text = TINY.replace("horizon: 4.0\n", "") + ("" if "horizon" in extra else
                                                     "horizon: 4.0\n") + extra
        run = Run(load_run_spec(data=text), folder, progress=False, log=lambda m: None)
        keys.add(solve_stage_key(run, run.spec.training_environments()[0]))
    assert len(keys) == 5
