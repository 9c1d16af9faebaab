"""One run at a time in a run directory: a second `run_pipeline` on a folder another
process is running in is refused in one line before it writes anything (two runs would
write the same files: a dataset's images truncated under the other's feet)."""

import subprocess
import sys

import pytest

from reachwatch.pipeline.run import hold_run_folder, release_run_folder, run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from tiny_run import TINY


HOLDER = """
import sys, time
from reachwatch.pipeline.run import hold_run_folder
hold_run_folder(sys.argv[1])
print("held", flush=True)
time.sleep(60)
"""


def test_a_second_run_on_a_folder_in_use_is_refused_and_writes_nothing(tmp_path):
    out = tmp_path / "study"
    other = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE,
                             text=True)                  # the other run, holding the folder
    try:
        assert other.stdout.readline().strip() == "held"
        with pytest.raises(ValueError, match=rf"{out} is in use by another reachwatch run "
                                             rf"\(pid {other.pid}\): wait for it to end"):
            run_pipeline(load_run_spec(data=TINY), out, progress=False, log=lambda m: None,
                         until="sweep")
        assert sorted(p.name for p in out.iterdir()) == [".reachwatch.lock"]
    finally:
        other.kill()
        other.wait()
    held = hold_run_folder(out)                  # let go with its process: free again
    assert held is not None
    try:                                         # a second hold, this process's too: refused
        with pytest.raises(ValueError, match="is in use by another reachwatch run"):
            hold_run_folder(out)
    finally:
        release_run_folder(held)


def test_a_file_system_without_flock_runs_unlocked_said_once(tmp_path, monkeypatch, caplog):
    import errno
    import fcntl

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")
    monkeypatch.setattr(fcntl, "flock", no_locks)
    with caplog.at_level("WARNING", logger="reachwatch"):
        assert hold_run_folder(tmp_path / "nfs") is None
    assert "cannot lock it (No locks available); running without the lock" in caplog.text


def test_a_folder_that_cannot_hold_a_lock_is_left_to_the_runs_own_checks(tmp_path):
    fresh = hold_run_folder(tmp_path / "new" / "below")       # made, and held
    assert fresh is not None
    release_run_folder(fresh)
    (tmp_path / "plain").write_text("")
    assert hold_run_folder(tmp_path / "plain" / "below") is None
