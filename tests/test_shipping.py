"""Files a task names travel with it (`reachwatch.diagrams.shipping`): a checkpoint and
a user's controller over two files are read from the copy that came with the task, so
the task runs after the driver's files are gone, and an edit sends new content."""

import shutil

import pytest

from reachwatch.diagrams import REFERENCE_TAXINET, load_checkpoint, load_scenario
from reachwatch.diagrams.controller import make_controller
from reachwatch.diagrams.shipping import MAX_SHIPPED_BYTES, Packer, pack, run_shipped, unpack
from reachwatch.systems.checks import is_file
from reachwatch.systems.files import local_copy
from lane_follower import FACTORY


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("REACHWATCH_CACHE", str(tmp_path / "worker_cache"))


def _controller_files(folder, offset):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "follower.py").write_text(FACTORY)
    (folder / "lane_vision.py").write_text(f"OFFSET = {offset}\n")
    (folder / "notes.txt").write_text("not code: not sent")
    return f"{folder / 'follower.py'}:make"


def _offset(scenario):
    from reachwatch.diagrams.controller import CONTROL_OUTPUT
    system = make_controller(scenario.controller)
    return float(system.GetOutputPort(CONTROL_OUTPUT).Eval(system.CreateDefaultContext())[0])


def _checkpoint_kind(scenario):
    assert is_file(scenario.controller.checkpoint)
    return load_checkpoint(scenario.controller.checkpoint, kind="taxinet")["kind"]


def test_a_task_runs_on_the_files_it_brought_after_the_drivers_are_gone(tmp_path):
    factory = _controller_files(tmp_path / "driver" / "mine", "0.25")
    checkpoint = tmp_path / "driver" / "taxinet.pt"
    shutil.copyfile(REFERENCE_TAXINET, checkpoint)
    scenario = load_scenario(data=f"controller: {{factory: '{factory}', "
                                  f"checkpoint: '{checkpoint}'}}\n")
    shipment = pack(scenario)
    named = {name for name, _, _ in shipment.names}
    assert named == {str(tmp_path / "driver" / "mine" / "follower.py"), str(checkpoint)}
    sent = {relative for folder in shipment.folders for relative, _ in folder.files}
    assert sent == {"follower.py", "lane_vision.py", "taxinet.pt"}     # no notes.txt
    shutil.rmtree(tmp_path / "driver")
    assert run_shipped(shipment, _offset, scenario) == 0.25
    assert run_shipped(shipment, _checkpoint_kind, scenario) == "taxinet"
    assert local_copy(str(checkpoint)) == str(checkpoint)      # outside the task: as named
    with pytest.raises(ValueError, match="file not found"):
        _offset(scenario)


def test_an_edited_helper_is_sent_again_and_a_tampered_copy_rewritten(tmp_path):
    factory = _controller_files(tmp_path / "mine", "0.25")
    scenario = load_scenario(data=f"controller: {{factory: '{factory}'}}\n")
    packer = Packer()
    first = packer.pack(scenario)
    assert packer.pack(scenario) == first
    (tmp_path / "mine" / "lane_vision.py").write_text("OFFSET = 0.5\n")
    second = packer.pack(scenario)
    assert second.digest != first.digest
    assert run_shipped(first, _offset, scenario) == 0.25
    assert run_shipped(second, _offset, scenario) == 0.5
    copies = tmp_path / "copies"
    unpack(first, copies)
    copy = copies / first.folders[0].digest / "lane_vision.py"
    copy.write_text("OFFSET = 9.0\n")              # a copy edited by hand
    fresh = tmp_path / "other_process"
    shutil.copytree(copies, fresh)
    import reachwatch.diagrams.shipping as shipping
    shipping._UNPACKED.clear()                     # as a new worker process finds it
    where = unpack(first, fresh)
    assert (fresh / first.folders[0].digest / "lane_vision.py").read_text() == "OFFSET = 0.25\n"
    assert set(where) == {str(tmp_path / "mine" / "follower.py")}


def test_a_same_size_edit_with_its_old_time_put_back_is_sent(tmp_path, monkeypatch):
    """The packer reads a file again when its change time moved, though its size and
    modification time are what they were (``cp -p``, ``touch -d``)."""
    import os

    import reachwatch.diagrams.shipping as shipping
    monkeypatch.setattr(shipping, "RACY_SECONDS", 0.0)
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"AAA")
    stat = checkpoint.stat()
    os.utime(checkpoint, ns=(stat.st_atime_ns, stat.st_mtime_ns - 10**10))  # older
    stat = checkpoint.stat()
    packer = Packer()
    first = packer.pack(str(checkpoint))
    checkpoint.write_bytes(b"BBB")
    os.utime(checkpoint, ns=(stat.st_atime_ns, stat.st_mtime_ns))           # put back
    assert (checkpoint.stat().st_mtime_ns, checkpoint.stat().st_size) == (
        stat.st_mtime_ns, stat.st_size)
    second = packer.pack(str(checkpoint))
    assert second.folders[0].files == (("model.pt", b"BBB"),) and second != first


def test_a_file_changed_just_now_is_read_again_at_every_task(tmp_path):
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"AAA")
    packer = Packer()
    packer.pack(str(checkpoint))
    checkpoint.write_bytes(b"BBB")          # within the same clock tick, the same size
    assert packer.pack(str(checkpoint)).folders[0].files == (("model.pt", b"BBB"),)


def test_plain_values_bring_nothing_and_too_much_is_one_line(tmp_path, monkeypatch):
    assert pack(1, "not a file", {"a": [2.0, "KMWH"]}) is None
    big = tmp_path / "big.pt"
    big.write_bytes(b"0" * 2048)
    import reachwatch.diagrams.shipping as shipping
    monkeypatch.setattr(shipping, "MAX_SHIPPED_BYTES", 1024)
    with pytest.raises(ValueError) as error:
        pack({"checkpoint": str(big)})
    assert "\n" not in str(error.value) and "big.pt" in str(error.value)
    assert MAX_SHIPPED_BYTES >= 1 << 20
