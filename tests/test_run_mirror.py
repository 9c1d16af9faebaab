"""A run directory at an fsspec URL: the run works in a local copy, puts what each
stage wrote to the URL (records last), and a run in an empty working directory
elsewhere fetches it and resumes: no stage runs again."""

import uuid

import fsspec
import pytest

from reachwatch.pipeline import run_mirror
from reachwatch.pipeline.cli import main
from reachwatch.pipeline.run_mirror import PUSHED, RunMirror
from reachwatch.systems.files import list_location, read_location
from tiny_run import TINY


@pytest.fixture
def url():
    """A fresh folder of fsspec's in-process memory filesystem, removed afterwards."""
    name = f"memory://run_mirror_{uuid.uuid4().hex}"
    yield name
    fs = fsspec.filesystem("memory")
    if fs.exists(name.split("://", 1)[1]):
        fs.rm(name.split("://", 1)[1], recursive=True)


def test_push_puts_what_changed_records_last_and_pull_fetches_it_elsewhere(
        tmp_path, url, monkeypatch):
    work = tmp_path / "work"
    (work / "stages").mkdir(parents=True)
    (work / "stages" / "sweep.json").write_text("{}")
    (work / "sweeps" / "k").mkdir(parents=True)
    (work / "sweeps" / "k" / "chunk_000000.npz").write_bytes(b"x" * 10)
    (work / "run.yaml").write_text("name: a\n")
    (work / ".half_written.tmp").write_text("never put")
    mirror = RunMirror(url, work)
    order = []
    put = run_mirror.put_location
    monkeypatch.setattr(run_mirror, "put_location",
                        lambda path, location: (order.append(location), put(path, location)))
    assert mirror.push() == 3
    assert order[0].endswith("sweeps/k/chunk_000000.npz")      # the records after it
    assert set(list_location(url)) == {"stages/sweep.json", "sweeps/k/chunk_000000.npz",
                                       "run.yaml"}
    assert mirror.push() == 0                                  # nothing changed
    (work / "stages" / "sweep.json").write_text('{"key": 1}')
    assert mirror.push() == 1 and read_location(f"{url}/stages/sweep.json") == b'{"key": 1}'

    elsewhere = RunMirror(url, tmp_path / "elsewhere")
    assert elsewhere.pull() == 3
    assert (tmp_path / "elsewhere" / "sweeps" / "k" / "chunk_000000.npz").read_bytes() == b"x" * 10
    assert elsewhere.push() == 0                               # fetched counts as put
    assert elsewhere.pull() == 2                               # the records, every time
    assert (tmp_path / "elsewhere" / PUSHED).is_file() and PUSHED not in list_location(url)
    # a record changed here and not put yet is newer than the URL's: not fetched over
    (tmp_path / "elsewhere" / "stages" / "sweep.json").write_text('{"key": 22}')
    assert elsewhere.pull() == 1
    assert (tmp_path / "elsewhere" / "stages" / "sweep.json").read_text() == '{"key": 22}'
    # a working directory used for another URL puts everything there
    assert RunMirror(url + "_other", work).push() == 3


def test_a_url_that_cannot_be_a_mirror_is_one_line(tmp_path):
    with pytest.raises(ValueError, match="not an fsspec URL"):
        RunMirror(str(tmp_path / "plain"), tmp_path / "work")


def test_a_run_at_a_url_resumes_in_another_working_directory(tmp_path, url, seed_caches):
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(TINY)
    first = seed_caches(tmp_path / "first")                  # its sweeps: rendered already
    argv = ["run", "--scenario", str(scenario), "--out", url, "--until", "solve",
            "--executor", "inline"]
    assert main(argv + ["--work-dir", str(first)]) == 0
    remote = list_location(url)
    records = {name: read_location(f"{url}/{name}") for name in remote
               if name.startswith("stages/")}
    assert "run.yaml" in remote and len(records) == 6        # sweep, solve x 3 environments
    assert any(name.startswith("sweeps/") for name in remote)
    second = tmp_path / "second"                             # another machine: nothing local
    assert main(argv + ["--work-dir", str(second)]) == 0
    assert {name: read_location(f"{url}/{name}") for name in records} == records  # none ran
    for name, data in records.items():
        assert (second / name).read_bytes() == data
