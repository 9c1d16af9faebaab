"""A controller over several files: its factory file imports a sibling helper. The
folder is importable where the scenario is loaded and in spawned workers, without
leaving the helper importable afterwards; the fingerprint covers every .py file in
the folder, so editing the helper sweeps again; a broken factory is one line."""

import os
import py_compile
import re
import sys

import numpy as np
import pytest

from reachwatch.diagrams import CONTROL_PORT, ControllerConfig, load_scenario
from reachwatch.diagrams.controller import make_controller, resolve_factory
from reachwatch.diagrams.user_code import factory_code_hash
from reachwatch.reach import InlineExecutor, default_executor, stop_executor
from reachwatch.taxi import paper_grid, sweep_closed_loop, taxi_sweep_key
from lane_follower import FACTORY


def _controller(tmp_path, offset="0.0"):
    folder = tmp_path / "mine"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "follower.py").write_text(FACTORY)
    (folder / "lane_vision.py").write_text(f"OFFSET = {offset}\n")
    return f"{folder / 'follower.py'}:make"


def _steering(controller):
    from reachwatch.diagrams.controller import CONTROL_OUTPUT
    context = controller.CreateDefaultContext()
    return float(controller.GetOutputPort(CONTROL_OUTPUT).Eval(context)[0])


def _steering_in_worker(factory):
    return _steering(make_controller(ControllerConfig(factory=factory)))


def test_a_two_file_controller_loads_here_and_in_a_worker_without_leaking(tmp_path):
    factory = _controller(tmp_path, "0.25")
    scenario = load_scenario(data=f"controller: {{factory: '{factory}'}}\n")
    assert _steering(make_controller(scenario.controller)) == 0.25
    assert "lane_vision" not in sys.modules            # not left importable for others
    with pytest.raises(ImportError):
        import lane_vision  # noqa: F401
    pool = default_executor(1)
    try:
        assert pool.submit(_steering_in_worker, factory).result() == 0.25
    finally:
        stop_executor(pool)


def test_two_folders_with_the_same_helper_name_keep_their_own(tmp_path):
    one, two = _controller(tmp_path / "a", "1.0"), _controller(tmp_path / "b", "2.0")
    assert _steering(make_controller(ControllerConfig(factory=one))) == 1.0
    assert _steering(make_controller(ControllerConfig(factory=two))) == 2.0


def test_a_controller_built_inside_another_folders_code_imports_its_own_helper(tmp_path):
    """An application's folder and a controller's each have a ``lane_vision.py``: the
    controller, first loaded while the application's code is importable (as a sweep
    worker builds the loop), imports its own, and the application's is shown again
    after."""
    from reachwatch.diagrams import user_code
    app = tmp_path / "app"
    app.mkdir()
    (app / "lane_vision.py").write_text("OFFSET = -5.0\n")
    (app / "application.py").write_text("import lane_vision\n\ndef make():\n"
                                        "    return lane_vision.OFFSET\n")
    module, make = user_code.resolve(f"{app / 'application.py'}:make", "application")
    factory = _controller(tmp_path / "ctrl", "0.5")
    with user_code.importable(module):
        assert make() == -5.0
        assert _steering(make_controller(ControllerConfig(factory=factory))) == 0.5
        import lane_vision
        assert lane_vision.OFFSET == -5.0


def test_pythons_own_modules_are_never_hidden_by_a_folders_file(tmp_path):
    """A folder with a ``json.py`` of its own: while its code is importable, the json
    module the process already has stays (what Python's modules import meanwhile is
    Python's); only another user folder's modules give way."""
    import json
    from reachwatch.diagrams import user_code
    folder = tmp_path / "shadow"
    folder.mkdir()
    (folder / "json.py").write_text("MINE = True\n")
    (folder / "factory.py").write_text("import json\n\ndef make():\n    return json\n")
    module, make = user_code.resolve(f"{folder / 'factory.py'}:make", "application")
    with user_code.importable(module):
        assert sys.modules["json"] is json and make() is json


def test_code_imported_from_outside_the_folder_is_keyed(tmp_path):
    """A factory file whose code imports modules of a user's source tree outside its
    folder (found through sys.path: here PYTHONPATH), at its top or inside the factory,
    is keyed by their content too, whatever the process imported first; Python's own
    and installed modules are not."""
    import subprocess
    shared = tmp_path / "shared"
    shared.mkdir()
    (shared / "tuning_at_top.py").write_text("GAIN = 1.0\n")
    (shared / "tuning_in_call.py").write_text("GAIN = 2.0\n")
    folder = tmp_path / "ctrl"
    folder.mkdir()
    (folder / "steer.py").write_text(
        "import json\nimport numpy\nimport tuning_at_top\n"
        "from lane_follower_factory import make as _make\n"
        "def make(config):\n    import tuning_in_call\n    return _make(config)\n")
    (folder / "lane_follower_factory.py").write_text(FACTORY)
    (folder / "lane_vision.py").write_text("OFFSET = 0.0\n")
    factory = f"{folder / 'steer.py'}:make"
    probe = ("from reachwatch.diagrams.user_code import _USER_CODE, factory_code_hash\n"
             f"print(factory_code_hash({factory!r}))\n"
             "print(sorted(next(iter(_USER_CODE.values())).outside()))\n")
    env = {**os.environ, "PYTHONPATH": str(shared)}

    def key():
        done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                              env=env, timeout=120)
        assert done.returncode == 0, done.stderr[-2000:]
        return done.stdout.splitlines()
    first = key()
    assert first[1] == "['tuning_at_top', 'tuning_in_call']"
    (shared / "tuning_in_call.py").write_text("GAIN = 3.0\n")
    second = key()
    assert second[0] != first[0]
    (shared / "tuning_in_call.py").write_text("GAIN = 2.0\n")
    assert key()[0] == first[0]
    # what those modules import in turn, and a namespace package (a folder without
    # __init__.py): before, neither was keyed
    (shared / "tuning_at_top.py").write_text("import table_of_gains\nGAIN = 1.0\n")
    (shared / "table_of_gains.py").write_text("ROWS = [1]\n")
    (shared / "gains_pkg").mkdir()
    (shared / "gains_pkg" / "values.py").write_text("K = 1\n")
    (shared / "tuning_in_call.py").write_text("from gains_pkg import values\nGAIN = 2.0\n")
    third = key()
    assert third[1] == "['gains_pkg', 'table_of_gains', 'tuning_at_top', 'tuning_in_call']"
    for edited, text in (("table_of_gains.py", "ROWS = [2]\n"), ("gains_pkg/values.py", "K = 2\n")):
        before = key()[0]
        (shared / edited).write_text(text)
        assert key()[0] != before, edited


def test_the_fingerprint_covers_the_helper_and_nothing_outside_the_folder(tmp_path):
    (tmp_path / "unrelated.py").write_text("X = 1\n")
    factory = _controller(tmp_path)
    before = factory_code_hash(factory)
    (tmp_path / "unrelated.py").write_text("X = 2\n")
    (tmp_path / "mine" / "__pycache__").mkdir()
    (tmp_path / "mine" / "__pycache__" / "junk.py").write_text("")
    (tmp_path / "mine" / ".hidden").mkdir()
    (tmp_path / "mine" / ".hidden" / "junk.py").write_text("")
    assert factory_code_hash(factory) == before
    (tmp_path / "mine" / "lane_vision.py").write_text("OFFSET = 2.0\n")
    assert factory_code_hash(factory) != before
    (tmp_path / "mine" / "lane_vision.py").write_text("OFFSET = 0.0\n")
    assert factory_code_hash(factory) == before
    (tmp_path / "mine" / "tools").mkdir()
    (tmp_path / "mine" / "tools" / "more.py").write_text("")   # importable as tools.more
    assert factory_code_hash(factory) != before


def _table(sweep):
    return np.asarray(sweep[CONTROL_PORT])


def test_editing_the_helper_sweeps_again(tmp_path):
    scenario = load_scenario(data=f"controller: {{factory: '{_controller(tmp_path)}'}}\n")
    grid = paper_grid(scenario.environment.half_width, (3, 3, 3))
    kwargs = dict(cache_dir=tmp_path / "sweeps", executor=InlineExecutor(), progress=False)
    first = sweep_closed_loop(scenario, grid, **kwargs)
    assert first.computed == 27 and np.all(_table(first) == 0.0)
    assert sweep_closed_loop(scenario, grid, **kwargs).computed == 0       # all cached
    key = taxi_sweep_key(scenario, grid)
    # Same size and time as a cached .pyc of the old file, which would pass for it.
    helper = tmp_path / "mine" / "lane_vision.py"
    py_compile.compile(str(helper), doraise=True)
    stat = helper.stat()
    helper.write_text("OFFSET = 0.1\n")
    os.utime(helper, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert taxi_sweep_key(scenario, grid) != key
    again = sweep_closed_loop(scenario, grid, **kwargs)
    assert again.computed == 27 and np.all(_table(again) == 0.1)


@pytest.mark.parametrize("helper, message", [
    (None, "ModuleNotFoundError: No module named 'lane_vision' at "),
    ("OFFSET = (\n", "SyntaxError: "),
    ("OFFSET = 1 / 0\n", "ZeroDivisionError: division by zero at "),
])
def test_a_broken_folder_is_one_line_naming_the_factory(tmp_path, capsys, helper, message):
    from reachwatch.pipeline import cli
    factory = _controller(tmp_path)
    (tmp_path / "mine" / "lane_vision.py").unlink()
    if helper is not None:
        (tmp_path / "mine" / "lane_vision.py").write_text(helper)
    with pytest.raises(ValueError, match=re.escape(f"controller.factory '{factory}': importing "
                                                   f"it failed: {message}")):
        resolve_factory(factory)
    path = tmp_path / "s.yaml"
    path.write_text(f"controller: {{factory: '{factory}'}}\n")
    # a command that builds the controller (rendering alone does not import it)
    assert cli.main(["simulate", "--scenario", str(path), "--out", str(tmp_path / "o"),
                     "--no-meshcat"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_missing_file_or_function_is_one_line(tmp_path):
    factory = _controller(tmp_path)
    with pytest.raises(ValueError, match="has no function 'missing'"):
        resolve_factory(factory.replace(":make", ":missing"))
    with pytest.raises(ValueError, match="controller.factory: file not found: "):
        resolve_factory(factory.replace("follower.py", "nowhere.py"))


def test_a_huge_folder_is_refused(tmp_path, monkeypatch):
    from reachwatch.diagrams import user_code
    monkeypatch.setattr(user_code, "MAX_SOURCE_ENTRIES", 5)
    factory = _controller(tmp_path)
    for i in range(6):
        (tmp_path / "mine" / f"data_{i}.txt").write_text("")
    with pytest.raises(ValueError, match="holds more than 5 files; put the controller's files "
                                         "in a folder of their own"):
        factory_code_hash(factory)


def test_a_users_package_is_fingerprinted_whole_and_never_run_stale(tmp_path, monkeypatch):
    package = tmp_path / "src" / "rw_test_pkg"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    relative = FACTORY.replace("import lane_vision", "from . import lane_vision")
    (package / "follower.py").write_text(relative.replace("from lane_vision", "from .lane_vision"))
    (package / "lane_vision.py").write_text("OFFSET = 0.5\n")
    monkeypatch.syspath_prepend(str(tmp_path / "src"))       # workers get the same sys.path
    factory = "rw_test_pkg.follower:make"
    pool = default_executor(1)
    try:
        before = factory_code_hash(factory)
        assert _steering(make_controller(ControllerConfig(factory=factory))) == 0.5
        (package / "lane_vision.py").write_text("OFFSET = 1.5\n")
        with pytest.raises(ValueError, match="changed since this process imported them; start a "
                                             "new process"):
            factory_code_hash(factory)
        assert pool.submit(factory_code_hash, factory).result() not in ("", before)
        assert pool.submit(_steering_in_worker, factory).result() == 1.5
    finally:
        stop_executor(pool)
        for name in [n for n in sys.modules if n.partition(".")[0] == "rw_test_pkg"]:
            del sys.modules[name]
    assert factory_code_hash("json:dumps") == factory_code_hash("json:dumps") != ""


def test_a_factory_imported_from_a_helper_still_sees_its_folder(tmp_path):
    factory = _controller(tmp_path, "0.75")
    (tmp_path / "mine" / "entry.py").write_text("from follower import make  # noqa: F401\n")
    entry = factory.replace("follower.py", "entry.py")
    assert _steering(make_controller(ControllerConfig(factory=entry))) == 0.75
    assert factory_code_hash(entry) == factory_code_hash(factory)      # the same folder


def test_a_worker_refuses_a_controller_edited_after_the_driver_keyed_it(tmp_path):
    """The driver keys a sweep with the controller's code; a worker that loads the
    folder after an edit (a replacement worker, a Dask task's shipment) would run other
    code under that key: one line instead. The code the driver keyed loads."""
    import concurrent.futures as cf
    import functools
    from reachwatch.reach import RespawningPool
    from reachwatch.reach.fingerprint import loop_code_digest
    factory = _controller(tmp_path / "keyed", offset="0.25")
    factory_code_hash(factory)                      # the driver keys it: loaded here
    pool = RespawningPool(functools.partial(cf.ThreadPoolExecutor, 1), code=loop_code_digest())
    try:
        assert pool.submit(_steering_in_worker, factory).result() == pytest.approx(
            _steering_in_worker(factory))
        (tmp_path / "keyed" / "mine" / "lane_vision.py").write_text("OFFSET = 0.5\n")
        with pytest.raises(ValueError, match=r"^controller.factory '\S+follower.py:make': the "
                                             r"code in \S+mine changed after this run keyed "
                                             r"its results with it; start the run again"):
            pool.submit(_steering_in_worker, factory).result()
    finally:
        stop_executor(pool)


def test_a_worker_refuses_a_checkpoint_rewritten_after_the_driver_keyed_it(tmp_path):
    """The same for a checkpoint the driver keyed by its content (a retraining that
    writes the same path while a sweep runs); a file the driver did not key is not
    checked."""
    import concurrent.futures as cf
    import functools
    import torch
    from reachwatch.diagrams import CheckpointError
    from reachwatch.diagrams.checkpoints import load_checkpoint
    from reachwatch.reach import RespawningPool
    from reachwatch.reach.fingerprint import fingerprint, loop_code_digest
    path = tmp_path / "model.pt"
    path.write_bytes(b"the weights keyed")
    fingerprint(ControllerConfig(checkpoint=str(path)))     # the driver keys it
    pool = RespawningPool(functools.partial(cf.ThreadPoolExecutor, 1), code=loop_code_digest())
    try:
        with pytest.raises(CheckpointError, match="not a readable checkpoint"):   # as keyed
            pool.submit(load_checkpoint, str(path), kind="taxinet").result()
        path.write_bytes(b"other weights")
        for spelled in (str(path), os.path.relpath(path)):    # one file, however named
            with pytest.raises(CheckpointError, match=r"^the checkpoint \S*model.pt changed "
                                                      r"after this run keyed its results"):
                pool.submit(load_checkpoint, spelled, kind="taxinet").result()
        other = tmp_path / "other.pt"
        torch.save({"x": 1}, other)
        with pytest.raises(CheckpointError, match="not a reachwatch checkpoint"):
            pool.submit(load_checkpoint, str(other), kind="taxinet").result()
    finally:
        stop_executor(pool)


def test_a_data_file_the_factory_reads_unkeyed_is_warned_of_once(tmp_path):
    """Before: a factory that read a data file from its folder (weights, a table) was
    keyed by its .py files alone, so a sweep after an edit to that file came from the
    cache without a word. Now building the controller warns, naming the file and
    `controller.checkpoint`; a file read at import counts too; the declared checkpoint
    (named through a link here) does not, nor do the neighbours it imports, a file it
    writes, one it failed to open or one of a virtual environment; each is said once."""
    factory = _controller(tmp_path, "0.5")
    folder = tmp_path / "mine"
    (folder / "gain.txt").write_text("2.0\n")
    (folder / "weights.npy").write_bytes(b"")
    (folder / "table.csv").write_text("1\n")
    (folder / ".venv").mkdir()
    (folder / ".venv" / "pyvenv.cfg").write_text("")
    linked = tmp_path / "linked"                      # the checkpoint named through a link
    linked.symlink_to(folder)
    (folder / "follower.py").write_text(
        'from pathlib import Path\n'
        'TABLE = Path(__file__).with_name("table.csv").read_text()\n' + FACTORY.replace(
            "def make(config):\n",
            "def make(config):\n"
            "    with open(Path(__file__).with_name('gain.txt')) as f:\n"
            "        float(f.read())\n"
            "    if config.checkpoint:\n"
            "        open(config.checkpoint, 'rb').close()\n"
            "    open(Path(__file__).with_name('written.log'), 'w').close()\n"
            "    open(Path(__file__).parent / '.venv' / 'pyvenv.cfg').close()\n"
            "    try:\n"
            "        open(Path(__file__).with_name('missing.json'))\n"
            "    except FileNotFoundError:\n"
            "        pass\n"))
    config = ControllerConfig(factory=factory, checkpoint=str(linked / "weights.npy"))
    with pytest.warns(UserWarning) as caught:
        make_controller(config)
    said = sorted(str(w.message) for w in caught if w.category is UserWarning)
    assert len(said) == 2, said
    assert said[0].startswith(f"controller.factory '{factory}' read gain.txt from its folder: "
                              f"not its code, so no key covers it")
    assert said[1].startswith(f"controller.factory '{factory}' read table.csv from its folder")
    assert all("name the controller's data files in controller.data_files" in m for m in said)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_controller(config)                       # said once


def test_a_linked_folder_of_the_factorys_code_is_keyed(tmp_path):
    """A helper package linked into the factory's folder is imported through the link;
    before, the walk did not follow it, so an edit to it was answered from the caches.
    A link back up the tree is walked once."""
    from reachwatch.diagrams.user_code import source_digest
    shared = tmp_path / "shared" / "helpers"
    shared.mkdir(parents=True)
    (shared / "__init__.py").write_text("")
    (shared / "gains.py").write_text("K = 1\n")
    folder = tmp_path / "ctrl"
    folder.mkdir()
    (folder / "steer.py").write_text("from helpers import gains\n")
    (folder / "helpers").symlink_to(shared)
    (shared / "loop").symlink_to(tmp_path / "shared")          # a cycle through the link
    data = tmp_path / "big_data"                               # a link to data: not walked
    (data / "tables").mkdir(parents=True)
    (data / "tables" / "table.py").write_text("ROWS = 1\n")
    (folder / "data").symlink_to(data)
    spaced = tmp_path / "shared" / "spaced"       # a namespace package through a link: walked
    spaced.mkdir()
    (spaced / "util.py").write_text("U = 1\n")
    (folder / "spaced").symlink_to(spaced)
    with_namespace = source_digest(folder)
    (spaced / "util.py").write_text("U = 2\n")
    assert source_digest(folder) != with_namespace
    before = source_digest(folder)
    (shared / "gains.py").write_text("K = 2\n")
    assert source_digest(folder) != before
    before = source_digest(folder)
    (data / "tables" / "table.py").write_text("ROWS = 2\n")
    assert source_digest(folder) == before


def test_controller_data_files_are_keyed_by_content_and_not_warned_of(tmp_path):
    """A controller reading a second data file (a table of gains beside its weights):
    before, only controller.checkpoint was keyed, so one of the two could not be."""
    import warnings
    from reachwatch.reach.fingerprint import canonical
    factory = _controller(tmp_path, "0.5")
    folder = tmp_path / "mine"
    (folder / "gains.yaml").write_text("k: 1\n")
    (folder / "follower.py").write_text(FACTORY.replace(
        "def make(config):\n",
        "def make(config):\n"
        "    for path in config.data_files:\n"
        "        open(path).close()\n"))
    config = ControllerConfig(factory=factory, data_files=[str(folder / "gains.yaml")])
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # keyed: no warning
        make_controller(config)
    key = canonical(config)
    (folder / "gains.yaml").write_text("k: 2\n")
    assert canonical(config) != key
    # on a cluster's worker the factory is handed the copy that came with the task
    from reachwatch.systems.files import shipped_copies
    copy = tmp_path / "shipped_gains.yaml"
    copy.write_text("k: 2\n")
    (folder / "follower.py").write_text(FACTORY.replace(
        "def make(config):\n",
        "OPENED = []\n\n\ndef make(config):\n"
        "    OPENED.extend(config.data_files)\n"))
    fresh = ControllerConfig(factory=f"{folder / 'follower.py'}:make",
                             data_files=[str(folder / "gains.yaml")])
    from reachwatch.diagrams import user_code
    with shipped_copies({str(folder / "gains.yaml"): str(copy)}):
        make_controller(fresh)
    module, _ = user_code.resolve(fresh.factory)
    assert module.OPENED == [str(copy)]
    with pytest.raises(ValueError, match=r"controller.data_files\[0\]: file not found"):
        ControllerConfig(factory=factory, data_files=[str(folder / "no.yaml")]).validate()
    with pytest.raises(ValueError, match="controller.data_files: only a controller.factory"):
        ControllerConfig(data_files=[str(folder / "gains.yaml")]).validate()


def test_a_moved_controller_folder_keeps_its_key_and_another_file_in_it_does_not(tmp_path):
    """The key holds the factory file's name and its folder's code by content, not its
    path: before, the taxi's resolved (absolute) path was in every sweep key, so a moved
    or cloned project swept again."""
    import shutil
    from reachwatch.reach.fingerprint import canonical
    factory = _controller(tmp_path / "here", "0.5")
    moved = tmp_path / "there" / "mine"
    shutil.copytree(tmp_path / "here" / "mine", moved)
    (moved / "other.py").write_text("from follower import make\n")
    (tmp_path / "here" / "mine" / "other.py").write_text("from follower import make\n")
    key = canonical(ControllerConfig(factory=factory))
    assert canonical(ControllerConfig(factory=f"{moved / 'follower.py'}:make")) == key
    assert canonical(ControllerConfig(factory=f"{moved / 'other.py'}:make")) != key
