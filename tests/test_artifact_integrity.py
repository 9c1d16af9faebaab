"""A run's artifacts are used only as they were written: a dataset whose arrays changed
is built again (or refused), an edited checkpoint is trained again rather than
adopted, a downstream stage's key follows the content of what it reads, an edited
stage record is not trusted, and an edited sweep or outcome chunk is computed again."""

import json
import re
import shutil

import numpy as np
import pytest
import torch

from reachwatch.diagrams import file_hash, load_detector
from reachwatch.pipeline.run import run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.pipeline.stages import Run
from reachwatch.reach import InlineExecutor
from reachwatch.reach.outcomes import map_states
from reachwatch.taxi import sweep_closed_loop
from reachwatch.training.dataset import load_dataset
from tiny_run import TINY

# Up to evaluate, without the fidelity check: ~10 s.
TEXT = TINY.replace("fidelity: {starts: 3", "fidelity: {starts: 0")
TRAIN_ENV = "KMWH_9h_clear"


def _run(out, until):
    log = []
    run = run_pipeline(load_run_spec(data=TEXT), out, progress=False, log=log.append, until=until)
    return run, log


def _ran(log):
    return {re.match(r"\[(\S+)\]", m).group(1) for m in log if "] running" in m}


def _why(log, stage):
    return next(m for m in log if m.startswith(f"[{stage}] running"))


@pytest.fixture(scope="module")
def base(tmp_path_factory, seed_caches):
    """A tiny run up to evaluate, copied by each test that edits it."""
    out = seed_caches(tmp_path_factory.mktemp("base"))
    run, _ = _run(out, "evaluate")
    return out, run.outputs


def _copy(base, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(base[0], out)
    return out


def test_a_dataset_whose_labels_were_flipped_is_built_again_not_reused(base, tmp_path):
    out = _copy(base, tmp_path)
    folder = out / base[1]["dataset"]["folders"][TRAIN_ENV]
    labels = np.load(folder / "labels.npy")
    flipped = np.load(folder / "labels.npy", mmap_mode="r+")
    flipped[:] = 1 - flipped
    flipped.flush()
    del flipped
    # Loading it is refused, in one line naming the file.
    with pytest.raises(ValueError, match=r"labels\.npy changed since the dataset was built") as e:
        load_dataset(folder)
    assert "\n" not in str(e.value)
    # The run notices, builds the dataset again and trains on the labels it was built with.
    run, log = _run(out, "train")
    assert "labels.npy changed content" in _why(log, "dataset")
    np.testing.assert_array_equal(np.load(folder / "labels.npy"), labels)
    np.testing.assert_array_equal(load_dataset(folder, verify=True).labels, labels)
    assert run.outputs["dataset"]["positives"] == base[1]["dataset"]["positives"]
    # ... and the record now matches the files: nothing runs again
    _, log = _run(out, "train")
    assert _ran(log) == set()
    # Without the stage's record, the dataset's manifest finds the edit itself.
    flipped = np.load(folder / "labels.npy", mmap_mode="r+")
    flipped[:] = 1 - flipped
    flipped.flush()
    del flipped
    (out / "stages/dataset.json").unlink()
    _run(out, "dataset")
    np.testing.assert_array_equal(np.load(folder / "labels.npy"), labels)


def test_zeroed_detector_weights_are_trained_again_and_what_reads_them_follows(
        base, tmp_path, monkeypatch):
    out = _copy(base, tmp_path)
    # Training again gives other bytes (as on another machine or torch version).
    from reachwatch.pipeline import detector_stages as stages
    train = stages.train_detector

    def other_bytes(data, config, path, **kw):
        result = train(data, config, path, **kw)
        checkpoint = torch.load(path, weights_only=False)
        checkpoint["state_dict"] = {k: v + 1e-3 if v.is_floating_point() else v
                                    for k, v in checkpoint["state_dict"].items()}
        torch.save(checkpoint, path)
        return result
    monkeypatch.setattr(stages, "train_detector", other_bytes)
    path = out / base[1]["train"]["detector"]
    checkpoint = torch.load(path, weights_only=False)
    checkpoint["state_dict"] = {k: torch.zeros_like(v) for k, v in checkpoint["state_dict"].items()}
    torch.save(checkpoint, path)
    edited = path.read_bytes()
    run, log = _run(out, "evaluate")
    assert "[train] running: its output" in _why(log, "train")
    # Trained again, not the edited file adopted.
    assert path.read_bytes() != edited
    record = json.loads((out / "stages/train.json").read_text())
    assert record["files"][base[1]["train"]["detector"]]["hash"] == file_hash(path)
    model, _, _ = load_detector(path)
    assert any(p.abs().sum() > 0 for p in model.parameters())
    # evaluate's key follows the content of train's files (not only train's key, which
    # is unchanged): Table 2 describes the detector now on disk.
    original = json.loads((base[0] / "stages/train.json").read_text())
    assert record["key"] == original["key"] and record["files"] != original["files"]
    assert "[evaluate] running: its inputs changed" in _why(log, "evaluate")
    _, log = _run(out, "evaluate")
    assert _ran(log) == set()


def test_a_downstream_key_follows_the_bytes_its_upstream_wrote(tmp_path):
    run = Run(load_run_spec(data=TEXT), tmp_path, progress=False, log=lambda m: None)

    def write(data):
        def fn():
            (tmp_path / "made").mkdir(exist_ok=True)
            (tmp_path / "made/out.bin").write_bytes(data)
            return {"file": "made/out.bin"}
        return fn

    run.stage("up", "k", write(b"one"))
    first = run.content_key("up")
    (tmp_path / "made/out.bin").write_bytes(b"two")      # edited: the stage runs again
    run.stage("up", "k", write(b"three"))                # ... and writes other bytes
    assert run.records["up"]["key"] == "k" and run.content_key("up") != first
    run.stage("up", "k", write(b"four"))                 # up to date: not run
    assert (tmp_path / "made/out.bin").read_bytes() == b"three"


def test_a_temporary_file_a_killed_write_left_is_not_an_output(tmp_path):
    """A hidden file in an output folder (`systems.files`' temporary name, left by a
    write killed before its rename) is not recorded: its removal would else make the
    stage run again, and its bytes would be hashed with the outputs."""
    run = Run(load_run_spec(data=TEXT), tmp_path, progress=False, log=lambda m: None)

    def build():
        (tmp_path / "made/sub").mkdir(parents=True, exist_ok=True)
        (tmp_path / "made/sub/out.bin").write_bytes(b"built")
        (tmp_path / "made/sub/.chunk_000001.npz.x1y2.tmp").write_bytes(b"half a chunk")
        return {"folder": "made/sub"}
    run.stage("s", "k", build)
    assert list(run.records["s"]["files"]) == ["made/sub/out.bin"]
    (tmp_path / "made/sub/.chunk_000001.npz.x1y2.tmp").unlink()
    ran = []
    run.stage("s", "k", lambda: ran.append(1) or {"folder": "made/sub"})
    assert ran == []                                        # up to date: not run again


def test_an_edited_output_is_removed_before_its_stage_runs_again(tmp_path):
    run = Run(load_run_spec(data=TEXT), tmp_path, progress=False, log=lambda m: None)
    target = tmp_path / "made.bin"

    def build():               # reuses a file found at its output path, as train does
        if not target.exists():
            target.write_bytes(b"built")
        return {"file": "made.bin"}

    run.stage("s", "k", build)
    target.write_bytes(b"edited")
    run.stage("s", "k", build)
    assert target.read_bytes() == b"built"


def test_a_hand_edited_record_is_not_trusted(base, tmp_path):
    out = _copy(base, tmp_path)
    record_path = out / f"stages/solve_{TRAIN_ENV}.json"
    record = json.loads(record_path.read_text())
    true_fraction = record["outputs"]["brt_fraction"]
    record["outputs"]["brt_fraction"] = 0.987
    record_path.write_text(json.dumps(record, indent=1))
    run, log = _run(out, "solve")
    assert "is corrupt (edited after its stage wrote it" in _why(log, f"solve_{TRAIN_ENV}")
    assert run.outputs["solve"][TRAIN_ENV]["brt_fraction"] == true_fraction
    assert json.loads(record_path.read_text())["outputs"]["brt_fraction"] == true_fraction
    # A record from before records carried a check is reused, and gets one.
    other = out / "stages/sweep_KSFO_17h_clear.json"
    legacy = json.loads(other.read_text())
    del legacy["check"]
    other.write_text(json.dumps(legacy, indent=1))
    _, log = _run(out, "sweep")
    assert _ran(log) == set() and "check" in json.loads(other.read_text())


def test_a_sweep_chunk_whose_numbers_were_edited_is_computed_again(tmp_path):
    run = Run(load_run_spec(data=TEXT), tmp_path / "run", progress=False, log=lambda m: None)
    env = run.spec.training_environments()[0]
    scenario, grid = run.scenario_for(env), run.solved_grid_for(env)
    sweep = lambda: sweep_closed_loop(scenario, grid, cache_dir=tmp_path / "sweeps",  # noqa: E731
                                      executor=InlineExecutor(), chunk_size=25, progress=False)
    first = sweep()
    assert first.computed == grid.size
    chunk = next((tmp_path / "sweeps").glob("*/chunk_000001.npz"))
    with np.load(chunk) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["port0"] = arrays["port0"] + 1.0            # same shape, other numbers
    np.savez(chunk, **arrays)
    again = sweep()
    assert again.computed == 25
    for port in first.tables:
        np.testing.assert_array_equal(again[port], first[port])
    assert sweep().computed == 0


def _square(states):
    return {"y": states ** 2}


def test_an_outcome_chunk_whose_numbers_were_edited_is_run_again(tmp_path):
    states = np.arange(12, dtype=float).reshape(6, 2)
    fields, key, computed = map_states(_square, states, cache_dir=tmp_path, chunk_size=2,
                                       progress=False)
    assert computed == 6
    chunk = tmp_path / key / "chunk_000001.npz"
    with np.load(chunk) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["y"] = arrays["y"] * 0
    np.savez(chunk, **arrays)
    again, _, computed = map_states(_square, states, cache_dir=tmp_path, chunk_size=2,
                                    progress=False)
    assert computed == 2
    np.testing.assert_array_equal(again["y"], states ** 2)
    assert set(again) == {"y"}


def _quarters(states):
    """Whole quarters come back as ints (as a rollout's ``-1``, never failed, might)."""
    q = states[:, 0] / 4
    return {"q": q if np.any(q % 1) else q.astype(int)}


def _names_by_chunk(states):
    return {"a" if states[0, 0] == 0 else "b": states[:, 0]}


def _widths_by_chunk(states):
    return {"y": np.zeros((len(states), 1 if states[0, 0] == 0 else 2))}


def test_map_states_keeps_every_chunks_numbers_and_refuses_unlike_chunks(tmp_path):
    """A later chunk's floats are not cut to the first chunk's ints; chunks that return
    other names or shapes are one error, not a field left unfilled."""
    states = np.array([[0.0, 0], [4, 0], [1, 0], [3, 0]])
    fields, _, _ = map_states(_quarters, states, cache_dir=tmp_path, chunk_size=2,
                              progress=False)
    np.testing.assert_array_equal(fields["q"], [0, 1, 0.25, 0.75])
    assert fields["q"].dtype == np.float64
    with pytest.raises(ValueError, match=r"^chunk 1 of .* holds the arrays \['b'\], the first "
                                         r"chunk \['a'\]: the function must return the same"):
        map_states(_names_by_chunk, states, cache_dir=tmp_path, chunk_size=2, progress=False)
    with pytest.raises(ValueError, match=r"^chunk 1 of .*: 'y' has shape \(2,\) a state, the "
                                         r"first chunk's \(1,\)"):
        map_states(_widths_by_chunk, states, cache_dir=tmp_path, chunk_size=2, progress=False)


def _rewrite_chunk(path, change):
    """Rewrite a chunk file with ``change(arrays)`` and a checksum that matches (a table
    made elsewhere, or edited by a tool that knows the format)."""
    from reachwatch.reach.chunk_files import CHECKSUM, store_chunk_file
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k != CHECKSUM}
    change(arrays)
    store_chunk_file(path, arrays)


def test_a_sweep_table_edited_with_a_valid_checksum_is_solved_again(base, tmp_path):
    """The solve's key follows the content of the sweep table it reads, not only the
    sweep's key: an edited table (its checksum rewritten) solves again instead of the
    BRT of the old one being adopted; a chunk deleted since is swept again first, so
    the same table keeps its BRT."""
    out = _copy(base, tmp_path)
    chunk = out / "sweeps" / base[1][f"sweep_{TRAIN_ENV}"]["sweep"] / "chunk_000000.npz"
    original = base[1]["solve"][TRAIN_ENV]["brt_fraction"]

    def hard_left(arrays):
        arrays["port0"] = np.full_like(arrays["port0"], 0.6)
    _rewrite_chunk(chunk, hard_left)
    run, log = _run(out, "solve")
    assert _ran(log) == {f"solve_{TRAIN_ENV}"}
    assert "its inputs changed" in _why(log, f"solve_{TRAIN_ENV}")
    assert run.outputs["solve"][TRAIN_ENV]["brt_fraction"] != original
    _, log = _run(out, "solve")
    assert _ran(log) == set()
    chunk.unlink()                        # swept again: the original table, its BRT
    run, log = _run(out, "solve")
    assert run.outputs["solve"][TRAIN_ENV]["brt_fraction"] == original
    assert chunk.is_file()
    _, log = _run(out, "solve")
    assert _ran(log) == set()


def test_a_brt_solved_again_with_other_bytes_is_checked_again(base, tmp_path, monkeypatch):
    """The fidelity check's key follows the content of the BRT it checks (the solve's
    files), not only the solve's key: a value function solved again (its old file
    edited) that comes out with other bytes, as on another machine, is checked again."""
    out = _copy(base, tmp_path)
    text = TEXT.replace("fidelity: {starts: 0", "fidelity: {starts: 1")
    run = lambda: run_pipeline(load_run_spec(data=text), out, progress=False,  # noqa: E731
                               log=log.append, until="fidelity")
    log = []
    run()
    assert f"fidelity_{TRAIN_ENV}" in _ran(log)
    from reachwatch.pipeline import brt_stages
    from reachwatch.reach import ValueFunction
    solve = brt_stages.solve_env

    def other_bytes(run, env, **kw):
        result = solve(run, env, **kw)
        vf = ValueFunction.load(run.path(result["value"]))
        vf.metadata["solved_on"] = "another machine"            # same values, other bytes
        vf.save(run.path(result["value"]))
        return result
    monkeypatch.setattr(brt_stages, "solve_env", other_bytes)
    value = out / base[1]["solve"][TRAIN_ENV]["value"]
    value.write_bytes(value.read_bytes() + b"edited")
    log.clear()
    run()
    assert f"solve_{TRAIN_ENV}" in _ran(log)
    assert "its inputs changed" in _why(log, f"fidelity_{TRAIN_ENV}")
    assert "fidelity_KSFO_17h_clear" not in _ran(log)
    log.clear()
    run()
    assert _ran(log) == set()


def _history_checkpoint(path, *, nan_weight=False, calibration=(1.0, 0.0)):
    from reachwatch.diagrams import save_checkpoint
    from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel
    config = HistoryMonitorConfig(height=16, width=24, frames=2)
    model = HistoryRiskModel(config)
    if nan_weight:
        with torch.no_grad():
            next(iter(model.parameters()))[0] = float("nan")
    return save_checkpoint(path, kind="history_monitor", model=model, model_config=config,
                           preprocess_config=None,
                           metadata={"threshold": 0.5, "calibration": calibration})


@pytest.mark.parametrize("nan_weight, calibration, message", [
    (True, (1.0, 0.0), r"weight 'encoder\.0\.weight' holds NaN or infinite values"),
    (False, (float("nan"), 0.0), r"its calibration must be two finite numbers \[a, b\], got \[nan, 0\.0\]"),
    (False, "ab", r"its calibration must be two finite numbers \[a, b\], got 'ab'"),
])
def test_a_monitor_checkpoint_that_would_answer_nan_is_refused(tmp_path, nan_weight,
                                                                calibration, message):
    """NaN weights or calibration make a monitor answer NaN, which never reaches its
    threshold: it would never warn. Refused where any checkpoint is read, so also by the
    cheap check commands make before their work (`checkpoint_kind`)."""
    from reachwatch.diagrams.checkpoints import (CheckpointError, checkpoint_kind,
                                                 load_history_monitor)
    good = _history_checkpoint(tmp_path / "good.pt")
    assert checkpoint_kind(good) == "history_monitor" and load_history_monitor(good)
    bad = _history_checkpoint(tmp_path / "bad.pt", nan_weight=nan_weight, calibration=calibration)
    for read in (load_history_monitor, checkpoint_kind):
        with pytest.raises(CheckpointError, match=message) as e:
            read(bad)
        assert "\n" not in str(e.value) and len(str(e.value)) < 300


def test_a_key_holds_every_number_of_an_array_not_its_abbreviated_text():
    """`digest` (the key of stages and studies) of a run file whose application keeps
    numpy values: two arrays of more than 1,000 numbers that differ only inside the
    part numpy's text elides get different keys; equal ones, equal keys."""
    import numpy as np
    from reachwatch.pipeline.keys import digest
    a = np.zeros(2000)
    b = a.copy()
    b[1000] = 1.0
    assert str(a) == str(b)                        # what the key read before
    assert digest({"x": a}) != digest({"x": b})
    assert digest({"x": a}) == digest({"x": a.copy()})
    assert digest({"x": a}) != digest({"x": a.astype(np.float32)})
    assert digest({"x": np.float64(0.5)}) == digest({"x": 0.5})
    assert digest({"x": np.array([None, 1], dtype=object)}) != digest(
        {"x": np.array([None, 2], dtype=object)})
    assert digest({"x": np.zeros((2, 0))}) != digest({"x": np.zeros((0, 2))})   # empty
    assert digest({"x": np.array(["2026-12-07"], dtype="datetime64[D]")}) != digest(
        {"x": np.array(["2026-12-08"], dtype="datetime64[D]")})
    masked = np.ma.masked_array([0.0, 1.0], mask=[False, True])
    assert digest({"x": masked}) != digest({"x": np.ma.masked_array([0.0, 1.0])})
