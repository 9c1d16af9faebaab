"""A dataset's arrays are reserved on disk when they are made: a full disk is an
OSError naming the file, not a SIGBUS in the middle of a rendered chunk."""

import errno
import os

import numpy as np
import pytest

from reachwatch.training.dataset_files import reserved_memmap


def test_the_arrays_bytes_are_reserved_at_once(tmp_path):
    path = tmp_path / "images.npy"
    array = reserved_memmap(path, np.uint8, (64, 48, 80, 3))
    assert array.shape == (64, 48, 80, 3)
    stat = os.stat(path)
    assert stat.st_blocks * 512 >= stat.st_size          # allocated, not sparse
    array[3] = 7
    array.flush()
    assert np.load(path, mmap_mode="r")[3].max() == 7


def test_no_room_is_one_oserror_naming_the_file(tmp_path, monkeypatch):
    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError, match=r"No space left on device: cannot reserve .* MiB for "
                                      r"the dataset array: '.*images\.npy'"):
        reserved_memmap(tmp_path / "images.npy", np.uint8, (64, 48, 80, 3))
    assert not (tmp_path / "images.npy").exists()          # what was reserved given back


def test_a_failed_atomic_write_names_its_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    from reachwatch.systems.files import atomic_write_bytes
    path = atomic_write_bytes(tmp_path / "record.json", b"old")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError) as e:
        atomic_write_bytes(path, b"new")
    assert e.value.filename == str(path) and e.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == [
        "record.json"]


@pytest.mark.parametrize("manifest", ['{"format": "reachwatch.dataset/4"}', "[1, 2]",
                                      '{"format": "x", "samples": "40", "estimate_size": 2, '
                                      '"chunks_done": [], "spec": {}, "labels": {}}'])
def test_a_damaged_manifest_is_one_line_naming_the_dataset(tmp_path, manifest):
    from reachwatch.training.dataset_files import read_manifest
    (tmp_path / "manifest.json").write_text(manifest)
    with pytest.raises(ValueError, match=rf"^{tmp_path} is not a readable reachwatch dataset "
                                         rf"\(its manifest has .*\); delete it to rebuild"):
        read_manifest(tmp_path)


def test_a_datasets_small_arrays_are_saved_whole_and_a_full_disk_names_them(tmp_path,
                                                                             monkeypatch):
    """Before: np.save's OSError on a full disk named no file ("error: No space left on
    device"), and left a half-written one."""
    from reachwatch.training.dataset_files import save_array
    states = np.arange(12.0).reshape(4, 3)
    save_array(tmp_path / "states.npy", states)
    np.testing.assert_array_equal(np.load(tmp_path / "states.npy"), states)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError) as e:
        save_array(tmp_path / "labels.npy", np.zeros(4, np.uint8))
    assert e.value.filename == str(tmp_path / "labels.npy")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["states.npy"]
