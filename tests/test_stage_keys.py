"""What the learning stages' keys hold besides their settings: which environments
train (the same datasets with the roles swapped train another detector), the content
of pretrained weights (not only their path), and the code that computes each stage (an
edit there runs the stage again). Read against the session's tiny run, nothing run."""

import dataclasses as dc
import json

import pytest

from reachwatch.pipeline import brt_stages, dataset_stages, detector_stages, fidelity_stages
from reachwatch.pipeline.brt_stages import solve_stage_key
from reachwatch.pipeline.dataset_stages import dataset_key
from reachwatch.pipeline.detector_stages import detector_weights, evaluate_key, train_key
from reachwatch.pipeline.fidelity_stages import fidelity_stage_key
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.stages import Run
from reachwatch.training.detector_train import DetectorTrainConfig
from tiny_run import TINY

SWAPPED = (TINY.replace("train: [{runway: KMWH, hour: 9.0, sky: clear}]",
                        "train: [{runway: KSFO, hour: 17.0, sky: clear}]")
           .replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                    "test: [{runway: KMWH, hour: 9.0, sky: clear}]"))
HELD_OUT_LABELS = "held_out_labels: {source: rollout, max_rollouts: 6}\n"


def read_back(text, folder) -> Run:
    """A `Run` of run file ``text`` over ``folder`` with its stage records read back,
    as a resumed run holds them when its later stages' keys are computed."""
    run = Run(load_run_spec(data=text), folder, progress=False, log=lambda m: None)
    for path in (folder / "stages").glob("*.json"):
        record = json.loads(path.read_text())
        run.records[record["stage"]], run.outputs[record["stage"]] = record, record["outputs"]
    run.outputs["solve"] = {e.name: run.outputs[f"solve_{e.name}"]
                            for e in run.spec.all_environments()}
    return run


def test_swapped_roles_train_again_on_the_same_datasets(tiny_run):
    folder, _ = tiny_run
    run, swapped = read_back(TINY, folder), read_back(SWAPPED, folder)
    assert [e.name for e in run.spec.training_environments()] != \
        [e.name for e in swapped.spec.training_environments()]
    # each environment's dataset is the same whatever its role: nothing is labelled again
    assert dataset_key(run) == dataset_key(swapped)
    assert train_key(run) != train_key(swapped)


def test_held_out_labels_follow_the_roles(tiny_run):
    """With ``held_out_labels`` the held-out environment's dataset is labelled apart:
    swapping the roles changes which dataset gets which labels."""
    folder, _ = tiny_run
    run, swapped = read_back(TINY + HELD_OUT_LABELS, folder), \
        read_back(SWAPPED + HELD_OUT_LABELS, folder)
    assert dataset_key(run) != dataset_key(swapped)
    assert dataset_key(run) != dataset_key(read_back(TINY, folder))


def test_pretrained_weights_are_keyed_by_their_content(tmp_path):
    path = tmp_path / "weights.pth"
    path.write_bytes(b"first weights")
    config = DetectorTrainConfig(pretrained_path=str(path))
    before = detector_weights(config)
    path.write_bytes(b"other weights, the same path")
    after = detector_weights(config)
    assert before != after and before["pretrained_path"] == after["pretrained_path"]
    assert "pretrained_content" not in detector_weights(dc.replace(config, pretrained_path=""))


@pytest.mark.parametrize("module, key", [
    (detector_stages, lambda run: train_key(run)),
    (detector_stages, lambda run: evaluate_key(run)),
    (detector_stages, lambda run: json.dumps(detector_weights(run.spec.detector))),
    (dataset_stages, lambda run: dataset_key(run)),
    (brt_stages, lambda run: solve_stage_key(run, run.spec.training_environments()[0])),
    (fidelity_stages, lambda run: fidelity_stage_key(
        run, run.records[f"solve_{run.spec.training_environments()[0].name}"], None)),
], ids=["train", "evaluate", "weights", "dataset", "solve", "fidelity"])
def test_a_stages_key_holds_its_code(tiny_run, monkeypatch, module, key):
    """Another source digest of the stage's code (as an edit there gives) is another key."""
    folder, _ = tiny_run
    run = read_back(TINY, folder)
    before = key(run)
    real = module.modules_source_digest
    monkeypatch.setattr(module, "modules_source_digest",
                        lambda *names: real(*names) + "edited")
    assert key(run) != before


def test_a_record_of_a_newer_reachwatch_is_refused_not_overwritten(tiny_run, tmp_path):
    """A run directory a newer reachwatch wrote (a record format above this one's) is
    refused in one line, not run again over it; an older one's records run again."""
    import shutil
    from reachwatch.pipeline.stages import RECORD_FORMAT
    folder, _ = tiny_run
    copy = tmp_path / "run"
    shutil.copytree(folder / "stages", copy / "stages")
    record_path = copy / "stages" / "dataset.json"
    record = json.loads(record_path.read_text())
    run = Run(load_run_spec(data=TINY), copy, progress=False, log=lambda m: None)
    from reachwatch.pipeline.stages import record_check
    newer = {**record, "format": RECORD_FORMAT + 1}
    record_path.write_text(json.dumps({**newer, "check": record_check(newer)}))
    with pytest.raises(ValueError, match=r"dataset.json was written by a newer reachwatch "
                                         r"\(record format"):
        run.stage("dataset", record["key"], lambda: pytest.fail("ran over a newer record"))
    # whatever its check: a newer version may compute it otherwise (the message says to
    # delete the record where it is damaged)
    record_path.write_text(json.dumps(newer))
    with pytest.raises(ValueError, match=r"or delete the record to run its stage again"):
        run._read_record(record_path)
    record_path.write_text(json.dumps({**record, "format": RECORD_FORMAT - 1}))
    assert run._read_record(record_path)[1] == f"record {record_path} has format " \
                                                f"{RECORD_FORMAT - 1}"
