"""Fault cases a probe of the command line found: each is one line, exit 2, and writes
nothing."""

import sys

import pytest

from reachwatch.pipeline import cli
from reachwatch.pipeline.run import run_pipeline
from reachwatch.pipeline.spec import load_run_spec
from test_overlays import FACTORY
from tiny_run import TINY


def _one_line(capsys, argv) -> str:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_a_run_without_room_downtrack_is_one_line_on_the_command_line(tmp_path, capsys):
    """Before: `BoxExitError` was a RuntimeError, which the command line does not catch:
    a traceback."""
    text = TINY.replace("fidelity: {starts: 3, max_box_exits: 1.0}", "fidelity: {starts: 3}")
    path = tmp_path / "run.yaml"
    path.write_text(text)
    err = _one_line(capsys, ["run", "--scenario", str(path), "--out", str(tmp_path / "out")])
    assert "leaves no room downtrack" in err and "Set solved_py_max: 270" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, option", [
    (["run", "--scenario", "RUN", "--out", ""], "--out"),
    (["run", "--scenario", "", "--out", "OUT"], "--scenario"),
    (["run", "--scenario", "RUN", "--out", "OUT", "--sweep-cache", ""], "--sweep-cache"),
    (["simulate", "--scenario", "", "--out", "OUT"], "--scenario"),
])
def test_an_empty_path_is_refused(tmp_path, capsys, monkeypatch, argv, option):
    """Before: ``--out ''`` wrote the run into the current folder and ``--scenario ''``
    ran the built-in defaults."""
    (tmp_path / "run.yaml").write_text(TINY)
    monkeypatch.chdir(tmp_path)
    argv = [{"RUN": "run.yaml", "OUT": "out"}.get(a, a) for a in argv]
    err = _one_line(capsys, argv)
    assert f"{option} is empty" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.yaml"]


def test_a_factory_parameter_it_does_not_take_is_said_before_the_run_directory_changes(tmp_path):
    """Before: said inside the first sweep, after run.yaml had been overwritten with the
    failing run file and sweep folders made."""
    folder = tmp_path / "controller"
    folder.mkdir()
    (folder / "constant.py").write_text(FACTORY)
    factory = f"{folder / 'constant.py'}:make"
    text = TINY.replace("incremental:\n", "incremental:\n  enabled: false\n") + (
        f"scenario:\n  controller: {{factory: '{factory}', "
        f"parameters: {{steering: 0.0, gain: 2.0}}}}\n")
    with pytest.raises(ValueError, match="controller.parameters.gain is not a parameter it takes"):
        run_pipeline(load_run_spec(data=text), tmp_path / "out", until="sweep", progress=False,
                     log=lambda m: None)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("shape", [["0", "0", "0"], ["1", "3", "3"], ["3", "2", "3"]])
def test_grid_node_counts_are_bounded_alike_at_parse_time_and_in_the_run_file(tmp_path, capsys,
                                                                             shape):
    """Before: ``--shape 0 0 0`` was "in [1, 401]" and ``--shape 1 3 3`` "in [3, 401]"."""
    with pytest.raises(SystemExit) as done:
        cli.main(["sweep", "--shape", *shape, "--out", str(tmp_path / "out")])
    assert done.value.code == 2
    err = capsys.readouterr().err
    bad = next(s for s in shape if int(s) < 3)
    assert f"--shape: '{bad}' is not a whole number of grid nodes in [3, 401]" in err, err


def test_a_folder_or_a_run_file_given_as_a_scenario_is_named_so(tmp_path, capsys):
    """Before: a folder was "scenario file not found", and a run file given to `render`
    "scenario.name: unknown field of Scenario"."""
    err = _one_line(capsys, ["render", "--scenario", str(tmp_path), "--out", str(tmp_path / "o")])
    assert f"{tmp_path} is a folder, not a scenario file" in err
    (tmp_path / "run.yaml").write_text(TINY)
    err = _one_line(capsys, ["render", "--scenario", str(tmp_path / "run.yaml"),
                             "--out", str(tmp_path / "o")])
    assert "this looks like a run file" in err and "reachwatch run --scenario" in err
    assert not (tmp_path / "o").exists()


def test_evaluates_defaults_leave_the_check_room_downtrack():
    """Before: `reachwatch evaluate` took the run file's solved_py_max (250 m, the paper's
    box end), which the real-loop check refuses at the default 8 s horizon: the command
    with its defaults stopped at once. It now solves to 290 m, and says so."""
    from reachwatch.pipeline.commands import fill_run_file_defaults
    from reachwatch.pipeline.evaluate_commands import evaluate_spec
    from reachwatch.pipeline.fidelity_stages import BoxExitError, check_downtrack_room

    def spec(*extra):
        args = cli.build_parser().parse_args(["evaluate", "--out", "unused", *extra])
        fill_run_file_defaults(args)
        return evaluate_spec(args)
    default = spec()
    assert default.solved_py_max == 290.0 and default.fidelity.starts > 0
    check_downtrack_room(default)
    with pytest.raises(BoxExitError, match="solved_py_max 250 m leaves no room downtrack"):
        check_downtrack_room(spec("--solved-py-max", "250"))


def test_a_sweep_cache_url_of_no_known_protocol_is_refused_before_any_work(tmp_path, capsys,
                                                                           monkeypatch):
    """Before: the run file was written and three sweeps started before the first sweep
    said "Protocol not known"."""
    (tmp_path / "run.yaml").write_text(TINY)
    monkeypatch.chdir(tmp_path)
    err = _one_line(capsys, ["run", "--scenario", "run.yaml", "--out", "out",
                             "--sweep-cache", "bogus://x"])
    assert "--sweep-cache bogus://x: Protocol not known: bogus" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.yaml"]
    # a file where the folder goes: was said at the first sweep, after run.yaml was written
    err = _one_line(capsys, ["run", "--scenario", "run.yaml", "--out", "out",
                             "--sweep-cache", "run.yaml"])
    assert "--sweep-cache run.yaml is a file; name a folder" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.yaml"]


def test_an_actions_error_names_the_command_and_the_action(capsys):
    """Before: ``reachwatch taxinet: error:`` for an error of ``taxinet evaluate``."""
    err = _one_line(capsys, ["taxinet", "evaluate", "--runways", "ZZZZ"])
    assert err.startswith("reachwatch taxinet evaluate: error: --runways / --hours: "), err
    assert "unknown runway 'ZZZZ'" in err


USER_CODE = '''
def calc(args):
    {}["darkness"]          # a user's controller failing on a dark frame


def refuse(args):
    raise ValueError("too dark")


def leave(args):
    import sys
    sys.exit(0)             # a user's controller ending the process at some tick
'''


def _user_module(tmp_path):
    import importlib.util
    path = tmp_path / "my_controller.py"
    path.write_text(USER_CODE)
    spec = importlib.util.spec_from_file_location("my_controller", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return path, module


def test_an_error_raised_in_the_users_code_names_its_file_and_line(tmp_path, capsys,
                                                                   monkeypatch):
    """Before: a KeyError in a controller's calc was a 40-line traceback (exit 1), and a
    ValueError one line that did not say where. Now one line with the user's file and
    line; -v keeps the traceback, and reachwatch's own errors keep theirs."""
    from reachwatch.pipeline import commands
    path, module = _user_module(tmp_path)
    monkeypatch.setattr(commands, "render", module.calc)
    argv = ["render", "--out", str(tmp_path / "out")]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert (f"reachwatch render: error: KeyError: 'darkness', raised at {path.resolve()}:3 "
            f"(in calc); -v shows the traceback") in err
    with pytest.raises(KeyError, match="darkness"):
        cli.main(["-v", *argv])
    monkeypatch.setattr(commands, "render", module.refuse)
    err = _one_line(capsys, argv)
    assert f"error: too dark (raised at {path.resolve()}:7, in refuse)" in err

    # raised in reachwatch's own code (here: `user_frame` given a Namespace): a bug of
    # ours, whose traceback stays
    monkeypatch.setattr(commands, "render", cli.user_frame)      # given a Namespace
    with pytest.raises(AttributeError, match="'Namespace' object has no attribute '__traceback__'"):
        cli.main(["render", "--out", str(tmp_path / "out")])


def test_sys_exit_in_the_users_code_is_an_error_naming_where_not_a_silent_success(
        tmp_path, capsys, monkeypatch):
    """Before: the command ended at once with status 0, unfinished, without a word.
    reachwatch's own exits (argparse's) are left as they are."""
    from reachwatch.pipeline import commands
    path, module = _user_module(tmp_path)
    monkeypatch.setattr(commands, "render", module.leave)
    assert cli.main(["render", "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert (f"reachwatch render: error: the user's code called sys.exit(0) at "
            f"{path.resolve()}:12 (in leave), so the command stopped unfinished; finished "
            f"work is kept") in err
    monkeypatch.setattr(commands, "render", sys.exit)     # no frame of the user's
    with pytest.raises(SystemExit):
        cli.main(["render", "--out", str(tmp_path / "out")])


def test_a_worker_process_error_is_traced_to_the_users_code(tmp_path):
    """Raised in a worker process, the frames come back as the cause's text
    (`concurrent.futures.process._RemoteTraceback`), inside the frames here: the
    user's innermost one there is found; an error reachwatch raised while handling the
    user's is reachwatch's (its traceback stays), and so is one raised inside reachwatch
    when the user's code called it."""
    from concurrent.futures.process import _RemoteTraceback

    from reachwatch.diagrams import user_code, user_errors
    path, module = _user_module(tmp_path)
    ours = user_code.__file__

    def remote(*frames, handled=()):
        def block(fs):
            return "Traceback (most recent call last):\n" + "".join(
                f'  File "{f}", line {n}, in {name}\n    code\n' for f, n, name in fs)
        text = block(handled) + "KeyError: 'darkness'\n\nDuring handling of the above " \
            "exception, another exception occurred:\n\n" if handled else ""
        return _RemoteTraceback(f'\n"""\n{text}{block(frames)}Error\n"""')

    def raised_here_by(remote_cause):
        try:                     # a local frame of the user's module outside the worker's
            module.calc(None)
        except KeyError as e:
            e.__cause__ = remote_cause
            return e

    error = raised_here_by(remote((ours, 10, "main"), (str(path), 7, "refuse")))
    assert user_errors.user_frame(error) == (str(path.resolve()), 7, "refuse")
    error = raised_here_by(remote((ours, 10, "main"), (ours, 20, "check"),
                                  handled=[(str(path), 3, "calc")]))
    assert user_errors.user_frame(error) is None      # reachwatch's, raised while handling
    error = raised_here_by(remote((str(path), 7, "refuse"), (ours, 20, "check")))
    assert user_errors.user_frame(error) is None      # raised in reachwatch, called by the user
    assert user_errors.user_frame(raised_here_by(None)) == (str(path.resolve()), 3, "calc")


def test_a_swept_table_the_solve_would_refuse_is_written_with_a_warning(tmp_path, capsys):
    """Before: `reachwatch sweep` wrote a table of steering past +-pi/2 rad (degrees, say)
    without a word, and only `brt` refused it. Now the table is still written (it is
    what the controller did), and the warning names the first state and says `brt` will
    refuse it."""
    folder = tmp_path / "controller"
    folder.mkdir()
    (folder / "constant.py").write_text(FACTORY)
    scenario = tmp_path / "s.yaml"
    scenario.write_text(f"camera: {{width: 64, height: 36}}\n"
                        f"controller: {{factory: '{folder / 'constant.py'}:make', "
                        f"parameters: {{steering: 10.0}}}}\n")
    argv = ["sweep", "--scenario", str(scenario), "--shape", "3", "3", "3", "--executor",
            "inline", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out")]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert len(list((tmp_path / "out").glob("sweep_*.npz"))) == 1
    assert ("warning: KMWH_9h_clear: controller.steering_angle: the swept control is outside "
            "the plant's controls (-1.5708 < u0 < 1.5708) at 27 of 27 grid states, the first ["
            ) in captured.err, captured.err
    assert "`reachwatch brt` refuses this table" in captured.err
