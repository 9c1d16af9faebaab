"""One run at a time in a run directory: a second `run_pipeline` on a folder another
process is running in is refused in one line before it writes anything (two runs would
write the same files: a dataset's images truncated under the other's feet)."""

import os
import subprocess
import sys

import pytest

from reachwatch.pipeline.run import run_folder_held, run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from tiny_run import TINY


HOLDER = """
import sys, time
from reachwatch.pipeline.run import run_folder_held
with run_folder_held(sys.argv[1]):
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
    with run_folder_held(out):                   # let go with its process: free again
        with pytest.raises(ValueError, match="is in use by another reachwatch run"):
            with run_folder_held(out):           # a second hold, this process's too: refused
                pass
    with run_folder_held(out):                   # and let go when the block ends
        pass


def test_a_lock_file_this_user_cannot_write_still_keeps_a_second_run_out(tmp_path,
                                                                         monkeypatch):
    """Another user's lock file (a shared, group-writable folder) opens only to read:
    the lock holds all the same, where the run went on unlocked without a word."""
    import errno
    import os
    from reachwatch.pipeline import run as run_module
    out = tmp_path / "shared"
    real_open = os.open

    def not_mine(path, flags, *args):
        if str(path).endswith(".reachwatch.lock") and flags & os.O_RDWR:
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_open(path, flags, *args)
    with run_folder_held(out):                   # its owner's run holds it
        monkeypatch.setattr(run_module.os, "open", not_mine)
        with pytest.raises(ValueError, match="is in use by another reachwatch run"):
            with run_folder_held(out):
                pass
    with run_folder_held(out):                   # free again: held, read-only
        with pytest.raises(ValueError, match="is in use by another reachwatch run"):
            with run_folder_held(out):
                pass


def test_a_file_system_without_flock_runs_unlocked_said_once(tmp_path, monkeypatch, caplog):
    import errno
    import fcntl

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")
    monkeypatch.setattr(fcntl, "flock", no_locks)
    ran = []
    with caplog.at_level("WARNING", logger="reachwatch"), run_folder_held(tmp_path / "nfs"):
        ran.append(True)
    assert ran and "cannot lock it (No locks available); running without the lock" in caplog.text


def test_a_folder_that_cannot_hold_a_lock_is_left_to_the_runs_own_checks(tmp_path):
    with run_folder_held(tmp_path / "new" / "below"):          # made, and held
        assert (tmp_path / "new" / "below" / ".reachwatch.lock").read_text() == str(os.getpid())
    (tmp_path / "plain").write_text("")
    with run_folder_held(tmp_path / "plain" / "below"):        # cannot be made: runs unlocked
        pass


def test_an_error_in_the_block_is_the_one_raised_and_the_lock_let_go(tmp_path):
    with pytest.raises(RuntimeError, match="the run's own") as raised:
        with run_folder_held(tmp_path):
            raise RuntimeError("the run's own")
    assert raised.value.__context__ is None
    with run_folder_held(tmp_path):
        pass
