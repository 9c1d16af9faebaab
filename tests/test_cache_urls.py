"""The chunk cache of sweeps and rollout batches may be an fsspec URL (``memory://``
here, ``s3://`` in a cluster): only the driver reads and writes it. A URL cache
computes once, is reused, recomputes a corrupted chunk, and is keyed and laid out like
a local folder; a local folder keeps its layout; a run keeps a URL sweep cache as it
is and writes no local sweeps folder."""

import functools
import uuid

import fsspec
import numpy as np
import pytest

from reachwatch.diagrams import load_scenario, make_state_feedback_diagram
from reachwatch.reach import InlineExecutor, Probe, sweep, sweep_key
from reachwatch.reach.chunk_files import chunk_path
from reachwatch.reach.outcomes import map_states
from reachwatch.reach.sweep import cached_table_digest
from reachwatch.systems.files import cache_join, cache_location
from reachwatch.taxi import paper_grid

FEEDBACK = Probe(plant="taxi_plant", control_port="p_controller.steering_angle",
                 extra_ports=("state_estimator.estimate",))
GRID = paper_grid(10.0, (4, 3, 3))          # 36 nodes: 6 chunks of 7 (the last of 1)
SWEEP = dict(probe=FEEDBACK, chunk_size=7, executor=InlineExecutor(), progress=False)


def _factory():
    return functools.partial(make_state_feedback_diagram, load_scenario(data=""))


def _square(states):
    return {"sq": states ** 2, "sum": states.sum(axis=1)}


@pytest.fixture
def memory_url():
    """A fresh folder of fsspec's in-process memory filesystem, removed afterwards."""
    url = f"memory://rw-test-{uuid.uuid4().hex[:12]}/cache"
    yield url
    fs = fsspec.filesystem("memory")
    root = url[len("memory://"):].split("/")[0]
    if fs.exists(f"/{root}"):
        fs.rm(f"/{root}", recursive=True)


def _corrupt(url):
    """Change a number of the chunk file ``url`` and keep its old checksum."""
    import io
    fs, path = fsspec.core.url_to_fs(url)
    with np.load(io.BytesIO(fs.cat_file(path))) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["port0"] = arrays["port0"] + 1.0
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    fs.pipe_file(path, buffer.getvalue())


def test_locations_keep_urls_as_strings_and_local_paths_as_paths(tmp_path):
    assert cache_location("memory://a/b") == "memory://a/b"
    assert cache_location(f"file://{tmp_path}") == tmp_path
    assert cache_location(str(tmp_path)) == tmp_path
    assert cache_join("s3://bucket/sweeps/", "k", "chunk_000000.npz") == \
        "s3://bucket/sweeps/k/chunk_000000.npz"
    assert cache_join(tmp_path, "k") == tmp_path / "k"
    assert chunk_path("memory://a/k", 3) == "memory://a/k/chunk_000003.npz"


def test_a_sweep_into_a_url_cache_is_reused_and_a_corrupted_chunk_recomputed(tmp_path, memory_url):
    first = sweep(_factory(), GRID, cache_dir=memory_url, **SWEEP)
    assert first.computed == GRID.size and first.key == sweep_key(_factory(), GRID, FEEDBACK)
    local = sweep(_factory(), GRID, cache_dir=tmp_path, **SWEEP)
    again = sweep(_factory(), GRID, cache_dir=memory_url, **SWEEP)
    assert again.computed == 0
    for port in FEEDBACK.ports:
        np.testing.assert_array_equal(again[port], first[port])
        np.testing.assert_array_equal(local[port], first[port])
    # the table's digest reads the same from either cache (the content is the same)
    digest = cached_table_digest(memory_url, first.key, GRID.size)
    assert digest is not None and digest == cached_table_digest(tmp_path, first.key, GRID.size)
    folder = cache_join(memory_url, first.key)
    _corrupt(chunk_path(folder, 2))
    assert cached_table_digest(memory_url, first.key, GRID.size) is None
    fsspec.core.url_to_fs(chunk_path(folder, 4))[0].pipe_file(
        fsspec.core.url_to_fs(chunk_path(folder, 4))[1], b"torn")
    repaired = sweep(_factory(), GRID, cache_dir=memory_url, **SWEEP)
    assert repaired.computed == 14                              # chunks 2 and 4, 7 nodes each
    for port in FEEDBACK.ports:
        np.testing.assert_array_equal(repaired[port], first[port])
    assert cached_table_digest(memory_url, first.key, GRID.size) == digest


def test_a_url_cache_and_a_local_one_hold_the_same_files(tmp_path, memory_url):
    key = "feedback"
    sweep(_factory(), GRID, cache_dir=tmp_path / "local", key=key, **SWEEP)
    sweep(_factory(), GRID, cache_dir=f"file://{tmp_path}/url", key=key, **SWEEP)
    sweep(_factory(), GRID, cache_dir=memory_url, key=key, **SWEEP)
    names = ["fingerprint.json"] + [f"chunk_{i:06d}.npz" for i in range(6)]
    assert sorted(p.name for p in (tmp_path / "local" / key).iterdir()) == sorted(names)
    assert not [p for p in (tmp_path / "local" / key).iterdir() if p.name.startswith(".")]
    assert sorted(p.name for p in (tmp_path / "url" / key).iterdir()) == sorted(names)
    fs, path = fsspec.core.url_to_fs(cache_join(memory_url, key))
    assert sorted(p.rsplit("/", 1)[1] for p in fs.ls(path, detail=False)) == sorted(names)
    assert fs.cat_file(f"{path}/fingerprint.json") == \
        (tmp_path / "local" / key / "fingerprint.json").read_bytes()
    # a key naming a URL cache filled from another factory is refused, as locally
    with pytest.raises(ValueError, match="filled from another"):
        sweep(_factory(), GRID, cache_dir=memory_url, key=key,
              **{**SWEEP, "probe": Probe(plant="taxi_plant", control_port=FEEDBACK.control_port)})
    # one whose fingerprint cannot be read is refused too: its tables cannot be checked
    (tmp_path / "local" / key / "fingerprint.json").write_text("{torn")
    with pytest.raises(ValueError, match=r"^sweep key 'feedback': the cache's fingerprint.json "
                                         r".* is not readable, so its tables cannot be checked"):
        sweep(_factory(), GRID, cache_dir=tmp_path / "local", key=key, **SWEEP)


def test_map_states_into_a_url_cache_is_reused_and_a_corrupted_chunk_recomputed(memory_url):
    states = np.arange(20.0).reshape(10, 2)
    fields, key, computed = map_states(_square, states, cache_dir=memory_url, chunk_size=4,
                                       progress=False)
    assert computed == 10
    np.testing.assert_array_equal(fields["sq"], states ** 2)
    again, key2, computed2 = map_states(_square, states, cache_dir=memory_url, chunk_size=4,
                                        progress=False)
    assert key2 == key and computed2 == 0
    np.testing.assert_array_equal(again["sum"], fields["sum"])
    fs, path = fsspec.core.url_to_fs(chunk_path(cache_join(memory_url, key), 1))
    fs.pipe_file(path, fs.cat_file(path)[:-9])                  # a torn write
    repaired, _, computed3 = map_states(_square, states, cache_dir=memory_url, chunk_size=4,
                                        progress=False)
    assert computed3 == 4
    np.testing.assert_array_equal(repaired["sq"], fields["sq"])


def test_a_run_with_a_url_sweep_cache_writes_no_local_sweeps_folder(tmp_path, memory_url):
    from reachwatch.pipeline.run import run_pipeline
    from reachwatch.pipeline.spec import load_run_spec
    from tiny_run import TINY
    spec = load_run_spec(data=TINY)
    only = [spec.all_environments()[0].name]                # one environment's sweep suffices
    run = run_pipeline(spec, tmp_path, until="sweep", progress=False, only=only,
                       log=lambda *_: None, sweep_cache=memory_url)
    assert run.sweep_cache == memory_url
    assert not (tmp_path / "sweeps").exists()
    assert not [p for p in tmp_path.rglob("*.npz")]
    fs, path = fsspec.core.url_to_fs(memory_url)
    keys = {r["sweep"] for r in run.outputs["sweep"].values()}
    assert len(keys) == 1 and {p.rsplit("/", 1)[1] for p in fs.ls(path, detail=False)} == keys


def test_a_url_whose_protocol_is_unknown_or_not_installed_is_one_line():
    import importlib.util
    from reachwatch.systems.files import make_folder
    with pytest.raises(ValueError, match=r"^nosuchproto://x/y: Protocol not known: nosuchproto$"):
        make_folder("nosuchproto://x/y")
    if importlib.util.find_spec("s3fs") is None:
        with pytest.raises(ValueError, match=r"^s3://bucket/x: .*s3fs.* \(its fsspec "
                                             r"implementation is not installed\)$"):
            make_folder("s3://bucket/x")


def test_a_closure_under_a_given_key_never_runs_another_sweeps_diagram():
    """A factory that cannot be fingerprinted keeps its threads' diagrams under the
    given key and a suffix of this call's own: a second sweep under the same key, from
    another closure, builds its own; a fingerprinted factory's diagrams are shared."""
    from reachwatch.reach.sweep import probe_key
    scenario = load_scenario(data="")
    closure = lambda: make_state_feedback_diagram(scenario)         # noqa: E731
    first, second = probe_key(closure, FEEDBACK, "mine"), probe_key(closure, FEEDBACK, "mine")
    assert first.startswith("mine_") and second.startswith("mine_") and first != second
    shared = functools.partial(make_state_feedback_diagram, scenario)
    assert probe_key(shared, FEEDBACK, "mine") == probe_key(shared, FEEDBACK) != first


def test_a_task_checks_a_relative_path_against_the_drivers_working_directory(tmp_path,
                                                                             monkeypatch):
    """A task names files as its driver does, relative paths included; a worker whose
    working directory is another (a Dask worker's) resolves them against the driver's,
    so that a checkpoint edited after the driver keyed it is still refused there."""
    from reachwatch.systems.files import (check_keyed, keyed_by_driver, keyed_digests,
                                          remember_keyed)
    (tmp_path / "driver").mkdir()
    (tmp_path / "worker").mkdir()
    monkeypatch.chdir(tmp_path / "driver")
    remember_keyed("models/relative_check.pt", "keyed-digest")
    keyed = keyed_digests()
    monkeypatch.chdir(tmp_path / "worker")
    with keyed_by_driver(keyed):
        check_keyed("models/relative_check.pt", "keyed-digest", "the checkpoint")
        with pytest.raises(ValueError, match="^the checkpoint changed after this run keyed"):
            check_keyed("models/relative_check.pt", "edited-digest", "the checkpoint")
