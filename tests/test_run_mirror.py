"""A run directory at an fsspec URL: the run works in a local copy, puts what each
stage wrote to the URL (records last), and a run in an empty working directory
elsewhere fetches it and resumes: no stage runs again. While a stage runs, its
finished chunks are put at an interval, so that a stage cut off half-way resumes
elsewhere from them."""

import threading
import time
import uuid

import fsspec
import numpy as np
import pytest

from reachwatch.pipeline import run_mirror
from reachwatch.pipeline.cli import main
from reachwatch.pipeline.run_mirror import PUSHED, RunMirror
from reachwatch.reach.chunk_files import FolderStore, is_chunk_file, split
from reachwatch.reach.chunks import run_chunks
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


def test_a_push_and_a_pull_show_the_bytes_they_move(tmp_path, url, capsys):
    """Gigabytes of datasets can move at the start and end of a run at a URL: with
    ``progress`` each shows a bar of its bytes, without it nothing."""
    work = tmp_path / "work"
    (work / "sweeps").mkdir(parents=True)
    (work / "sweeps" / "chunk_000000.npz").write_bytes(b"x" * 3000)
    (work / "run.yaml").write_text("name: a\n")
    assert RunMirror(url, work).push(progress=True) == 2
    shown = capsys.readouterr().err
    assert f"put to {url}" in shown and "2.94k" in shown.replace("K", "k")    # 3008 bytes
    assert RunMirror(url, tmp_path / "elsewhere").pull(progress=True) == 2
    assert f"fetched from {url}" in capsys.readouterr().err
    (work / "run.yaml").write_text("name: b\n")
    assert RunMirror(url, work).push() == 1 and capsys.readouterr().err == ""


def test_a_pull_interrupted_keeps_what_it_fetched_as_put(tmp_path, url, monkeypatch):
    """A pull stopped half-way (Ctrl-C, a lost connection) records the files it fetched
    as put, so the next push does not put them back as work of its own."""
    work = tmp_path / "work"
    (work / "sweeps").mkdir(parents=True)
    for i in range(4):
        (work / "sweeps" / f"chunk_{i:06d}.npz").write_bytes(b"x" * (i + 1))
    RunMirror(url, work).push()
    get, calls = run_mirror.get_location, []

    def flaky(location, target):
        calls.append(location)
        if len(calls) == 3:
            raise KeyboardInterrupt
        get(location, target)
    monkeypatch.setattr(run_mirror, "get_location", flaky)
    elsewhere = RunMirror(url, tmp_path / "elsewhere")
    with pytest.raises(KeyboardInterrupt):
        elsewhere.pull()
    monkeypatch.setattr(run_mirror, "get_location", get)
    assert elsewhere.push() == 0                 # the two fetched count as put


def test_a_url_that_cannot_be_a_mirror_is_one_line(tmp_path):
    with pytest.raises(ValueError, match="not an fsspec URL"):
        RunMirror(str(tmp_path / "plain"), tmp_path / "work")
    with pytest.raises(ValueError, match="^bogus://bucket/x: Protocol not known: bogus$"):
        RunMirror("bogus://bucket/x", tmp_path / "work")
    assert not (tmp_path / "work").exists()          # nothing made for it


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


def test_a_run_at_a_url_whose_working_directory_is_in_use_fetches_nothing(tmp_path, url,
                                                                           monkeypatch, capsys):
    from reachwatch.pipeline.run import run_folder_held
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(TINY)
    pulled = []
    monkeypatch.setattr(RunMirror, "pull", lambda self: pulled.append(True) or 0)
    work = tmp_path / "work"
    with run_folder_held(work):                              # another run works there
        assert main(["run", "--scenario", str(scenario), "--out", url, "--until", "sweep",
                     "--executor", "inline", "--work-dir", str(work)]) == 2
    assert "is in use by another reachwatch run" in capsys.readouterr().err
    assert not pulled and sorted(p.name for p in work.iterdir()) == [".reachwatch.lock"]


def test_a_file_written_again_at_the_url_at_its_size_is_fetched_again(tmp_path, url,
                                                                     monkeypatch):
    """Machine A puts a half-filled array and later pulls again; meanwhile B filled it
    and put it at the same size. A fetches B's (its listing's version changed), where it
    kept its own stale copy (same size); a file unchanged at the URL is not fetched."""
    a, b = RunMirror(url, tmp_path / "a"), RunMirror(url, tmp_path / "b")
    (a.local / "data").mkdir()
    (a.local / "data" / "images.npy").write_bytes(b"half" + bytes(4))
    (a.local / "data" / "labels.npy").write_bytes(b"labels")
    assert a.push() == 2
    assert b.pull() == 2
    time.sleep(0.01)                                 # a later creation time at the URL
    (b.local / "data" / "images.npy").write_bytes(b"whole!!!")
    assert b.push() == 1
    assert a.pull() == 1                             # images.npy, not labels.npy
    assert (a.local / "data" / "images.npy").read_bytes() == b"whole!!!"
    assert a.pull() == 0 and a.push() == 0           # nothing new either way
    # a put whose listing failed: its versions unknown, fetched again at the next pull
    (a.local / "data" / "labels.npy").write_bytes(b"LABELS")
    listing = run_mirror.list_location

    def failing(location, versions=False):
        if versions:
            raise OSError("listing refused")
        return listing(location)
    with monkeypatch.context() as patched:
        patched.setattr(run_mirror, "list_location", failing)
        assert a.push() == 1
    assert a.pull() == 1 and a.pull() == 0


def _rows(chunk, ran, fail_at=None):
    """A chunk's task: its rows' indices squared; ``ran`` lists the chunks it ran."""
    if chunk.index == fail_at:
        raise RuntimeError("the machine is lost")
    ran.append(chunk.index)
    return {"squares": np.arange(chunk.start, chunk.stop) ** 2}


def _wait_for(condition, seconds=20.0):
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "not within the wait"
        time.sleep(0.01)


def test_a_stage_cut_off_half_way_resumes_elsewhere_from_the_chunks_put_while_it_ran(
        tmp_path, url):
    work, chunks = tmp_path / "work", split(8, 2)
    mirror, ran = RunMirror(url, work), []
    store = FolderStore(work / "monitor_cache" / "runs" / "key")
    with mirror.pushing_every(0.01):
        manifest = work / "datasets" / "d" / "manifest.json"      # describes other files
        manifest.parent.mkdir(parents=True)
        manifest.write_text("{}")
        with pytest.raises(RuntimeError, match="the machine is lost"):
            run_chunks(lambda chunk: _rows(chunk, ran, fail_at=2), chunks, store,
                       args=lambda chunk: (chunk,))
        _wait_for(lambda: len(list_location(url)) == 2)
    assert ran == [0, 1]
    assert sorted(list_location(url)) == ["monitor_cache/runs/key/chunk_000000.npz",
                                          "monitor_cache/runs/key/chunk_000001.npz"]

    elsewhere = RunMirror(url, tmp_path / "elsewhere")      # the first machine is gone
    assert elsewhere.pull() == 2
    ran.clear()
    store = FolderStore(tmp_path / "elsewhere" / "monitor_cache" / "runs" / "key", keep=True)
    run_chunks(lambda chunk: _rows(chunk, ran), chunks, store, args=lambda chunk: (chunk,))
    assert ran == [2, 3]
    assert np.array_equal(np.concatenate([store.read(c)["squares"] for c in chunks]),
                          np.arange(8) ** 2)


def test_no_push_every_interval_puts_nothing_before_the_stage_ends(tmp_path, url):
    work = tmp_path / "work"
    with RunMirror(url, work).pushing_every(0):
        FolderStore(work / "k").store(split(2, 2)[0], {"a": np.zeros(2)})
        time.sleep(0.05)
    assert list_location(url) == {}


def test_chunk_files_are_the_ones_chunk_path_names():
    assert is_chunk_file("chunk_000000.npz") and is_chunk_file("chunk_1234567.npz")
    assert not any(is_chunk_file(name) for name in (
        "manifest.json", "images.npy", ".chunk_000000.npz.x1.tmp", "chunk_000000.npz.tmp",
        "chunk_0.npz"))


def test_a_file_removed_before_its_put_is_left_to_the_next_push(tmp_path, url, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "a.npz").write_bytes(b"a")
    (work / "b.npz").write_bytes(b"b")
    mirror, put = RunMirror(url, work), run_mirror.put_location

    def removed_first(path, location):
        if path.name == "a.npz":
            path.unlink()                        # the stage removed it after the listing
        return put(path, location)
    monkeypatch.setattr(run_mirror, "put_location", removed_first)
    assert mirror.push() == 1 and set(list_location(url)) == {"b.npz"}

    def refused(path, location):                 # the URL's side, with the file here
        raise FileNotFoundError(f"no bucket for {location}")
    monkeypatch.setattr(run_mirror, "put_location", refused)
    (work / "c.npz").write_bytes(b"c")
    with pytest.raises(FileNotFoundError, match="no bucket"):
        mirror.push()


@pytest.mark.parametrize("seconds", ["-1", "0.5", "inf", "nan"])
def test_a_push_every_interval_out_of_bounds_is_one_line(tmp_path, capsys, seconds):
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(TINY)
    assert main(["run", "--scenario", str(scenario), "--out", str(tmp_path / "out"),
                 "--push-every", seconds]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"reachwatch run: error: --push-every must be 0 or 1 to 86400 seconds, "
                   f"got {float(seconds):g}")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("seconds", [-1.0, float("inf")])
def test_a_push_interval_it_cannot_wait_is_refused(tmp_path, url, seconds):
    with pytest.raises(ValueError, match="a push interval must be 0 to"):
        with RunMirror(url, tmp_path / "work").pushing_every(seconds):
            pass


def test_a_push_that_fails_is_warned_once_and_tried_again(tmp_path, url, monkeypatch):
    work = tmp_path / "work"
    FolderStore(work / "k").store(split(2, 2)[0], {"a": np.zeros(2)})
    tries, warned, put = [], [], run_mirror.put_location

    def refused_three_times(path, location):
        tries.append(location)
        if len(tries) <= 3:
            raise PermissionError("no credentials")
        return put(path, location)
    monkeypatch.setattr(run_mirror, "put_location", refused_three_times)
    with RunMirror(url, work).pushing_every(0.01, warn=warned.append):
        _wait_for(lambda: len(list_location(url)) == 1)
    assert len(tries) == 4
    assert warned == [f"could not put the finished chunks to {url} (PermissionError: no "
                      f"credentials); trying again every 0.01 s"]


def test_a_push_told_to_stop_leaves_the_rest_to_the_next(tmp_path, url):
    work = tmp_path / "work"
    for chunk in split(4, 1):
        FolderStore(work / "k").store(chunk, {"a": np.zeros(1)})
    stop, mirror = threading.Event(), RunMirror(url, work)
    stop.set()
    assert mirror.push(stop=stop) == 0 and list_location(url) == {}
    assert mirror.push() == 4


@pytest.mark.parametrize("writing", [["dataset of environment KSFO_17h_clear"], None])
def test_an_interrupt_with_jobs_still_writing_puts_nothing(tmp_path, url, monkeypatch,
                                                           capsys, writing):
    """Interrupted while a stage's jobs had not stopped (`run_together`'s
    ``jobs_still_writing``): nothing is put, since their files may change while they
    go (a dataset's manifest put naming rows its copy lacks); said in one line. An
    interrupt whose jobs all stopped puts what the run wrote."""
    from reachwatch.pipeline import run as run_module
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(TINY)

    def interrupted(spec, out, **kwargs):
        (out / "written.txt").write_text("a stage's file")
        error = KeyboardInterrupt()
        error.jobs_still_writing = writing
        raise error
    monkeypatch.setattr(run_module, "run_pipeline", interrupted)
    assert main(["run", "--scenario", str(scenario), "--out", url, "--executor", "inline",
                 "--work-dir", str(tmp_path / "work"), "--push-every", "0"]) == 130
    put = "written.txt" in list_location(url)
    err = capsys.readouterr().err
    if writing:
        assert not put and f"not put to {url}: 1 jobs were still writing" in err
    else:
        assert put and "not put" not in err


def test_jobs_still_writing_are_seen_through_an_error_raised_while_stopping(tmp_path, url,
                                                                           monkeypatch):
    """The executor failing to stop after such an interrupt raises its own error: the
    jobs still writing are seen through it, and nothing is put."""
    from reachwatch.pipeline import run as run_module
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(TINY)

    def interrupted(spec, out, **kwargs):
        (out / "written.txt").write_text("a stage's file")
        error = KeyboardInterrupt()
        error.jobs_still_writing = ["dataset of environment KSFO_17h_clear"]
        try:
            raise error
        except KeyboardInterrupt:
            raise RuntimeError("the pool would not stop")
    monkeypatch.setattr(run_module, "run_pipeline", interrupted)
    assert main(["run", "--scenario", str(scenario), "--out", url, "--executor", "inline",
                 "--work-dir", str(tmp_path / "work"), "--push-every", "0"]) != 0
    assert "written.txt" not in list_location(url)
