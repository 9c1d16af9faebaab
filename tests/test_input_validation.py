"""Bad input refused where the scenario or run file is loaded: names that become file
names, non-finite and out-of-range numbers, YAML alias bombs and huge files, short
one-line errors (exit 2 from the command line), and nothing written for them."""

import re
from pathlib import Path

import pytest

from reachwatch.diagrams import REFERENCE_TAXINET, ControllerConfig, ScenarioError, load_scenario
from reachwatch.diagrams.controller import make_controller
from reachwatch.pipeline import cli
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.systems import Environment, RunwaySpec
from reachwatch.training.labels import LabelSpec
from tiny_run import TINY

NAME_ERROR = "runway_spec.name must be 1 to 64 of the characters"


def _runway(spec: str) -> str:
    return f"environment: {{runway: MINE, runway_spec: {spec}}}\n"


@pytest.mark.parametrize("name", ["../../../../escaped", "a/b", ".hidden", "..", "", "x" * 65,
                                  "KMWH 9", "tab\there", "é"])
def test_runway_names_that_are_not_safe_file_names_are_refused(name):
    with pytest.raises(ScenarioError, match=re.escape(NAME_ERROR)):
        load_scenario(data=_runway(f"{{name: {name!r}}}"))
    text = TINY.replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                        f"test: [{{runway: KSFO, runway_spec: {{name: {name!r}}}}}]")
    with pytest.raises(ScenarioError, match=re.escape(NAME_ERROR)):
        load_run_spec(data=text)
    for good in ("MINE", "my-runway_2.b", "A" * 64):
        load_scenario(data=_runway(f"{{name: {good}}}"))


def test_render_with_an_escaping_runway_name_writes_nothing(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text(_runway("{name: '../../escaped'}"))
    out = tmp_path / "a" / "b" / "out"
    assert cli.main(["render", "--scenario", str(scenario), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert NAME_ERROR in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["s.yaml"]


def test_environment_names_write_the_hour_faithfully():
    assert Environment("KMWH", 9.0).name == "KMWH_9h_clear"            # names kept as they were
    assert Environment("KSFO", 17.5, "overcast").name == "KSFO_17p5h_overcast"
    assert Environment("KMWH", 23.9999999).name == "KMWH_23p9999999h_clear"
    hours = (23.9999999, 23.99999999, 9.0000001, 9.0)
    assert len({Environment("KMWH", h).name for h in hours}) == len(hours)


@pytest.mark.parametrize("text, message", [
    ("camera: {right: .nan}", "camera.right must be a finite number in [-100, 100] m, got nan"),
    ("camera: {up: .inf}", "camera.up must be a finite number in [-100, 100] m, got inf"),
    ("camera: {forward: 1.0e6}", "camera.forward must be a finite number in [-100, 100] m"),
    ("camera: {far: 1.0e9}", "camera.far must be a finite number in (0, 100000] m"),
    ("initial_state: {px: .nan}", "initial_state.px must be a finite number in [-10000, 10000] m"),
    (_runway("{heading_deg: .nan}"), "environment.runway_spec.heading_deg must be a finite number in [-360, 360] deg"),
    (_runway("{buildings: -3}"), "buildings must be a whole number in [0, 50], got -3"),
    (_runway("{buildings: 100000}"), "buildings must be a whole number in [0, 50]"),
    (_runway("{half_width: 1.0e9}"), "half_width must be a finite number in (0, 200] m"),
    (_runway("{half_width: 1e9}"), "half_width must be a finite number in (0, 200] m"),
    (_runway("{half_width: .inf}"), "half_width must be a finite number in (0, 200] m"),
    (_runway("{length: 1.0e12}"), "length must be a finite number in (300, 20000] m"),
    (_runway("{lights: {spacing: 0.000001}}"), "lights.spacing must be a finite number in [5, 20000] m"),
    (_runway("{markings: {dash_length: 0.000001}}"),
     "markings.dash_length must be a finite number in [1, 20000] m"),
    (_runway("{markings: {threshold_stripes: 1000000}}"), "markings.threshold_stripes must be"),
    (_runway("{taxiway_lines: [{radius: 1.0e9}]}"), "taxiway_lines[0].radius must be a finite number"),
    (_runway("{surface: {texture_seed: -1}}"), "surface.texture_seed must be a whole number in [0,"),
    ("seed: -1", "seed must be a whole number in [0, 2147483647], got -1"),
    ("duration: 1.0e12", "duration must be a finite number in (0, 3600] s"),
    ("controller: {px_gain: .nan}", "controller.px_gain must be a finite number in [-1000, 1000] deg/m, got nan"),
    ("controller: {theta_gain: -.inf}", "controller.theta_gain must be a finite number"),
    ("controller: {px_gain: 1.0e300}", "controller.px_gain must be a finite number in [-1000, 1000]"),
    (f"controller: {{checkpoint: {'c' * 5000}}}", "controller.checkpoint: file not found: ccc"),
    (f"monitor: {{detector: {'d' * 5000}}}", "monitor.detector: file not found: ddd"),
    (f"controller: {{factory: '{'f' * 5000}.py:make'}}", "controller.factory: file not found: fff"),
    ("controller: {speed: 1.0e9}", "controller.speed must be a finite number in [0, 100] m/s"),
    ("monitor: {brake_deceleration: .nan}", "monitor.brake_deceleration must be a finite number in (0, 100] m/s^2"),
    ("camera: {width: 100000000000000}", "scenario.camera.width: 100000000000000 is out of range"),
    ("monitor: {flag_window: 100000000}", "monitor.flag_window must be a whole number in [1, 1000] ticks"),
])
def test_scenario_numbers_must_be_finite_and_in_range(text, message):
    with pytest.raises(ScenarioError, match=re.escape(message)):
        load_scenario(data=text)


@pytest.mark.parametrize("edit, message", [
    (("noise_starts: 0}", "noise_starts: 0, mission_limit: -1}"), "guard.mission_limit must be a finite number in [1, 100] horizons"),
    (("noise_starts: 0}", "noise_starts: 0, mission_limit: .nan}"), "guard.mission_limit must be a finite number in [1, 100] horizons"),
    (("noise_starts: 0}", "noise_starts: 0, mission_limit: 1.0e6}"), "guard.mission_limit must be a finite number in [1, 100] horizons"),
    (("noise_starts: 0}", "noise_starts: 0, check_seed: -1}"), "guard.check_seed must be a whole number in [0, 2147483647], got -1"),
    (("seeds: [1, 2]", "seeds: [1, -2]"), "ensemble.seeds[1] must be a whole number in [0, 2147483647], got -2"),
    (("epochs: 1\n", "epochs: 1\n  learning_rate: .nan\n"), "detector.learning_rate must be a finite"),
    (("epochs: 1\n", "epochs: 1\n  seed: -1\n"), "detector.seed must be a whole number in [0, 2147483647], got -1"),
    (("device: cpu", "device: gpu"), "detector.device must be a torch device such as cpu"),
    (("device: cpu", "device: cpu\n  pretrained_path: missing.pt"),
     "detector.pretrained_path: pretrained weights apply to detector.arch efficientnet_b0 only"),
    (("detector: {height: 24, width: 40, channels: [4, 8]}",
      "detector: {arch: efficientnet_b0, height: 24, width: 40}\n  pretrained_path: missing.pt"),
     "detector.pretrained_path: file not found: missing.pt"),
    (("replay: 20", "replay: 20\n  learning_rate: .nan"), "incremental.learning_rate must be a finite"),
    (("name: tiny", "name: tiny\nscenario: {controller: {px_gain: .nan}}"),
     "controller.px_gain must be a finite number"),
    (("grid: [5, 3, 5]", "grid: [5, 3, 50000]"), "grid[2] must be a whole number in [3, 401], got 50000"),
    (("horizon: 4.0", "horizon: 1.0e6"), "horizon must be a finite number in (0, 120] s"),
    (("horizon: 4.0", "horizon: 4.0\nmap_selection: {starts: 100000000000}"),
     "run.map_selection.starts: 100000000000 is out of range"),
    (("horizon: 4.0", "horizon: 4.0\nmap_selection: {starts: 100000000}"),
     "map_selection.starts must be a whole number in [0, 1000000]"),
    (("horizon: 4.0", "horizon: 4.0\nrefine: {levels: 40}"), "refine.levels must be a whole number in [0, 5]"),
    (("horizon: 4.0", "horizon: 4.0\nperiods_per_step: 100000000"), "periods_per_step must be a whole number in [1, 10000]"),
    (("horizon: 4.0", "horizon: 4.0\nslice_py: .nan"), "slice_py must be a finite number >= 0 m"),
    (("chunk_size: 16}", "chunk_size: 16, labels: {source: hybrid, audit: 5, more_audit: 1000000000}}"),
     "dataset.labels.more_audit must be a whole number in [0, 1000000]"),
    (("{samples: 40,", "{samples: 1000000000,"), "dataset.samples must be a whole number in [10, 10000000]"),
    (("fidelity: {starts: 3", "fidelity: {starts: 300000000"), "fidelity.starts must be a whole number in [0, 1000000]"),
    (("check_starts: 2", "check_starts: 200000000"), "guard.check_starts must be a whole number in [0, 1000000]"),
    (("horizon: 4.0", "horizon: 4.0\ntest_random: {count: 1000000000, seed: 5}"),
     "test_random.count must be a whole number in [0, 1000]"),
    (("horizon: 4.0", "horizon: 4.0\ntest_random: {count: 1, seed: 5, prefix: ÄÖ}"),
     "test_random.prefix must be letters and digits (1 to 16, ASCII)"),
])
def test_run_file_numbers_must_be_finite_and_in_range(edit, message):
    assert edit[0] in TINY
    with pytest.raises(ScenarioError, match=re.escape(message)):
        load_run_spec(data=TINY.replace(*edit))


def test_hybrid_labels_need_an_audit():
    text = TINY.replace("chunk_size: 16}", "chunk_size: 16, labels: {source: hybrid, audit: 0}}")
    with pytest.raises(ScenarioError, match=re.escape("dataset.labels.audit must be >= 1 for the "
                                                      "hybrid source")):
        load_run_spec(data=text)
    with pytest.raises(ValueError, match="held_out_labels.audit must be >= 1"):
        LabelSpec("hybrid", audit=0).validate("held_out_labels")
    LabelSpec("brt", audit=0).validate()                # the audit is read by hybrid alone
    LabelSpec("hybrid", audit=1).validate()


def test_a_float_written_as_text_is_read_as_the_number():
    spec = load_run_spec(data=TINY.replace("epochs: 1\n", "epochs: 1\n  learning_rate: 1e-4\n"))
    assert spec.detector.learning_rate == 1e-4 and isinstance(spec.detector.learning_rate, float)
    assert spec.detector.epochs == 1 and spec.grid == [5, 3, 5]            # the rest as written
    s = load_scenario(data="controller: {factory: 'mine.control:make', "
                           "parameters: {gain: -2E-1}, speed: '+5e0'}\n")
    assert s.controller.parameters == {"gain": -0.2} and s.controller.speed == 5.0
    for text, where in [("controller: {speed: 5e0x}", "scenario.controller.speed: expected float"),
                        ("camera: {width: 1e3}", "scenario.camera.width: expected int"),
                        ("controller: {checkpoint: 1e-4}", "controller.checkpoint: file not found")]:
        with pytest.raises(ScenarioError, match=re.escape(where)):
            load_scenario(data=text)


def test_controller_parameters_without_a_factory_are_refused_not_ignored():
    """Before: loaded, and silently unread by the default TaxiNet + P-controller."""
    with pytest.raises(ScenarioError, match=re.escape(
            "controller.parameters: only a controller.factory reads them")) as info:
        load_scenario(data="controller: {parameters: {gain_deg: 10.0}}\n")
    assert "gain_deg" in str(info.value) and len(str(info.value)) < 300
    with pytest.raises(ValueError, match=re.escape("scenario.controller.parameters: only")):
        load_run_spec(data=TINY + "scenario:\n  controller: {parameters: {gain: 1.0}}\n")


BOMB = "".join(f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi"))


def test_yaml_alias_bombs_are_refused_before_they_are_built_and_briefly(monkeypatch):
    from reachwatch.diagrams import scenario as scenario_module
    loader, built = scenario_module._UniqueKeyLoader, []
    construct = loader.construct_document
    monkeypatch.setattr(loader, "construct_document",
                        lambda self, node: (built.append(1), construct(self, node))[1])
    in_parameters = "controller:\n  parameters:\n" + "".join(
        f"    {line}\n" for line in ("a: &a [1.0]\n" + BOMB).splitlines())
    for text in (in_parameters, "grid: &a [5, 3, 5]\n" + BOMB):
        with pytest.raises(ScenarioError, match="holds more than 100000 values") as info:
            load_scenario(data=text)
        assert len(str(info.value)) < 300
    with pytest.raises(ScenarioError, match="holds more than 100000 values"):
        load_run_spec(data=TINY.replace("grid: [5, 3, 5]", "x: &a [5]\n" + BOMB + "grid: *i"))
    with pytest.raises(ScenarioError, match="a YAML alias refers to a node that contains it"):
        load_scenario(data="camera: &c {width: *c}\n")
    assert built == []              # refused on the node graph: no bomb was ever built
    # a flat list of 200,000 numbers (800 KB, no alias) is answered, not blamed on aliases
    with pytest.raises(ScenarioError, match="holds more than 100000 values") as info:
        load_scenario(data="grid:\n" + "- 1\n" * 200_000)
    assert "alias" not in str(info.value).split("(")[0] and built == []
    # a number of 500,000 digits: one line in our words, not Python's advice
    with pytest.raises(ScenarioError, match="a number of thousands of digits") as info:
        load_scenario(data="camera: {width: " + "9" * 500_000 + "}")
    assert "set_int_max_str_digits" not in str(info.value)
    # an alias that stands for a little is still fine
    s = load_scenario(data="environment: {hour: &h 17.0}\ninitial_state: {theta_deg: *h}\n")
    assert s.environment.hour == s.initial_state.theta_deg == 17.0 and built   # (counted)


def test_error_messages_cut_long_values():
    long_list = "[" + ", ".join(["5"] * 50_000) + "]"
    for text in (f"camera: {long_list}", f"environment: {{sky: {'x' * 100_000}}}",
                 f"environment: {{runway: {'Z' * 100_000}}}", f"{'k' * 100_000}: 1"):
        with pytest.raises(ScenarioError) as info:
            load_scenario(data=text)
        assert len(str(info.value)) < 400 and "\n" not in str(info.value)
    with pytest.raises(ScenarioError) as info:
        load_run_spec(data=TINY.replace("grid: [5, 3, 5]", f"grid: {long_list}"))
    assert "grid must be 3 sizes" in str(info.value) and len(str(info.value)) < 400


def test_a_scenario_path_too_long_for_the_system_is_one_error(tmp_path, capsys):
    path = str(tmp_path / ("s" * 5000)) + ".yaml"
    with pytest.raises(ScenarioError, match="scenario file not found"):
        load_scenario(path)
    assert cli.main(["render", "--scenario", path, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "scenario file not found" in err and len(err) < 700


def test_a_huge_file_is_refused_before_it_is_read(tmp_path, capsys, monkeypatch):
    path = tmp_path / "big.yaml"
    path.write_text("# padding\n" * 120_000 + "{}\n")
    read = Path.read_bytes

    def never_this_one(self):
        assert self.name != "big.yaml", "the huge file was read"
        return read(self)
    monkeypatch.setattr(Path, "read_bytes", never_this_one)
    with pytest.raises(ScenarioError, match=r"bytes; a scenario file is at most 1048576 bytes"):
        load_scenario(path)
    assert cli.main(["run", "--scenario", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "a scenario file is at most" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_two_environments_of_one_name_must_be_the_same():
    mine = "{{runway: MINE, hour: 9.0, runway_spec: {{name: MINE, half_width: {}}}}}"

    def run_file(test_width, guard_width):
        return TINY.replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                            f"test: [{mine.format(test_width)}]").replace(
            "guard: {", f"guard: {{environments: [{mine.format(guard_width)}], ")

    with pytest.raises(ScenarioError, match=re.escape(
            "test[0] and guard.environments[0] are both named 'MINE_9h_clear' but differ")):
        load_run_spec(data=run_file(12.0, 14.0))
    assert load_run_spec(data=run_file(12.0, 12.0)).guard_environments()[0].half_width == 12.0
    catalog_named = TINY.replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                                 "test: [{runway: X, hour: 9.0, runway_spec: {name: KMWH}}]")
    with pytest.raises(ScenarioError, match=re.escape("train[0] and test[0] are both named "
                                                      "'KMWH_9h_clear' but differ")):
        load_run_spec(data=catalog_named)
    for guard_env, message in [("{runway: XXXX}", "guard.environments[0]: environment.runway: "
                                                   "unknown runway 'XXXX'"),
                               ("{runway: A, runway_spec: {name: a/b}}",
                                "guard.environments[0]: environment.runway_spec.name must be")]:
        with pytest.raises(ScenarioError, match=re.escape(message)):
            load_run_spec(data=TINY.replace("guard: {", f"guard: {{environments: [{guard_env}], "))
    with pytest.raises(ScenarioError, match=re.escape("incremental.environment: environment.hour")):
        load_run_spec(data=TINY.replace("environment: {runway: KMWH, hour: 17.0",
                                        "environment: {runway: KMWH, hour: 24.0"))


def test_a_factory_that_is_no_python_function_or_fails_on_the_config_is_one_error(tmp_path, capsys):
    path = tmp_path / "s.yaml"
    path.write_text("controller: {factory: 'os:system'}\n")
    # (a command that builds the controller: rendering alone does not import it)
    assert cli.main(["simulate", "--scenario", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "controller.factory: 'os:system' is a builtin_function_or_method" in err
    assert err.count("\n") == 1 and not (tmp_path / "o").exists()
    with pytest.raises(ValueError, match=re.escape("controller.factory 'json:dumps': calling it "
                                                   "with the ControllerConfig failed (TypeError")):
        make_controller(ControllerConfig(factory="json:dumps"))


def test_out_naming_a_file_is_one_error(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("camera: {width: 16, height: 16}\n")
    (tmp_path / "taken").write_text("a file")
    assert cli.main(["render", "--scenario", str(scenario), "--out", str(tmp_path / "taken")]) == 2
    err = capsys.readouterr().err
    assert "cannot write" in err and "a file stands where a folder is needed" in err
    assert err.count("\n") == 1 and (tmp_path / "taken").read_text() == "a file"
    run = tmp_path / "run.yaml"                  # the run command says it as render does
    run.write_text("name: t\ntrain: [{runway: KMWH, hour: 9.0, sky: clear}]\n"
                   "test: [{runway: KSFO, hour: 17.0, sky: clear}]\n")
    assert cli.main(["run", "--scenario", str(run), "--out", str(tmp_path / "taken"),
                     "--until", "sweep"]) == 2
    err = capsys.readouterr().err
    assert "taken: File exists (a file stands where a folder is needed)" in err
    assert err.count("\n") == 1 and (tmp_path / "taken").read_text() == "a file"


def test_taxinet_train_never_writes_the_shipped_checkpoint(capsys):
    with pytest.raises(SystemExit) as stop:            # no default --out
        cli.main(["taxinet", "train", "--epochs", "1", "--samples", "1"])
    assert stop.value.code == 2 and "--out" in capsys.readouterr().err
    before = REFERENCE_TAXINET.stat().st_mtime_ns
    assert cli.main(["taxinet", "train", "--epochs", "1", "--samples", "1",
                     "--out", str(REFERENCE_TAXINET)]) == 2
    assert "is the shipped reference TaxiNet" in capsys.readouterr().err
    assert REFERENCE_TAXINET.stat().st_mtime_ns == before


def test_runway_spec_validate_checks_programmatic_specs_too():
    for bad, message in [(dict(name="../x"), NAME_ERROR), (dict(half_width=float("inf")), "half_width"),
                         (dict(buildings=-3), "buildings"), (dict(heading_deg=float("nan")), "heading_deg")]:
        with pytest.raises(ValueError, match=re.escape(message)):
            RunwaySpec(**bad).validate()


@pytest.mark.parametrize("argv, message", [
    (["brt", "--seed", "-1"], "--seed: '-1' is not a seed"),
    (["guard", "--scenario", "x", "--noise-seed", "-5"], "--noise-seed: '-5' is not a seed"),
    (["evaluate", "--seed", "-3"], "--seed: '-3' is not a seed"),
    (["taxinet", "train", "--seed", "-1"], "--seed: '-1' is not a seed"),
    (["sweep", "--shape", "5", "5", "100000"], "--shape: '100000' is not a whole number of grid nodes"),
    (["evaluate", "--shape", "5", "5", "100000"], "--shape: '100000' is not a whole number of grid nodes"),
    (["brt", "--horizon", "1e9"], "--horizon: '1e9' is not a finite number > 0 of at most 120 s"),
    (["brt", "--refine", "50"], "--refine: '50' is not a whole number in [0, 5]"),
    (["brt", "--solved-py-max", "1e12"], "--solved-py-max: '1e12' is not a finite number of metres"),
    (["guard", "--scenario", "x", "--mission-limit", "0.5"],
     "--mission-limit: '0.5' is not a multiple of the horizon in [1, 100]"),
])
def test_bad_numbers_on_the_command_line_are_bounded(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as stop:
        cli.main(argv + ["--out", str(tmp_path / "o")])
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_bad_command_line_environments_are_one_error(tmp_path, capsys):
    out = tmp_path / "o"
    for argv, message in [
            (["taxinet", "evaluate", "--runways", "XXXX"], "--runways / --hours: environment.runway: "
                                                           "unknown runway 'XXXX'"),
            (["taxinet", "evaluate", "--hours", "nan"], "environment.hour must be a finite number in [0, 24) h, got nan")]:
        assert cli.main(argv + ["--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    assert not out.exists()


def test_a_device_this_machine_lacks_is_refused_before_any_work():
    """A CUDA device the machine does not have failed at the train stage, after the
    sweeps and datasets, with a traceback; now it is refused where the file is loaded."""
    with pytest.raises(ScenarioError, match=re.escape("detector.device is 'cuda:99', and this "
                                                      "machine has")):
        load_run_spec(data=TINY.replace("device: cpu", "device: 'cuda:99'"))
    assert load_run_spec(data=TINY).detector.device == "cpu"


@pytest.mark.parametrize("edit, message", [
    (("name: tiny", "name: ''"), "name must be 1 to 200 printable characters on one line"),
    (("name: tiny", "name: \"a\\nb\""), "name must be 1 to 200 printable characters on one line"),
    (("name: tiny", "name: \"x\\u202ey\""), "name must be 1 to 200 printable characters on one line"),
    (("name: tiny", "name: " + "n" * 5000), "name must be 1 to 200 printable characters on one line"),
    (("name: tiny", "name: tiny\nmonitor: {kind: history, variants: [{name: \"a\\nb\"}]}"),
     "monitor.variants[0].name must be 1 to 200 printable characters on one line"),
    (("name: tiny", "name: tiny\nmonitor: {kind: history, also_held_out: ["
                    "{runway: KMWH, hour: 21.0, sky: clear}, {runway: KMWH, hour: 21.0, sky: clear}]}"),
     "monitor.also_held_out lists an environment name twice: ['KMWH_21h_clear']"),
    (("horizon: 4.0", "horizon: 0.01"),
     "horizon (0.01 s) must be at least one control period (scenario.controller.period 0.05 s)"),
    (("horizon: 4.0", "horizon: 1.0e-9"), "horizon (1e-09 s) must be at least one control period"),
    (("online_seconds: 0.2", "online_seconds: 1.0e-12"),
     "guard.online_seconds (1e-12 s) must be at least one control period"),
])
def test_labels_monitor_environments_and_horizons_that_make_no_sense_are_refused(edit, message):
    """Each was accepted: a run name of 5000 characters or with a newline titled the
    report, a monitor environment listed twice counted twice in its pooled rates, a
    horizon shorter than a control period ran the whole study (rc 0) on a loop whose
    controller never acts, and an online timing that short divided by zero at the guard
    stage, after the sweeps, datasets and training."""
    assert edit[0] in TINY
    with pytest.raises(ScenarioError, match=re.escape(message)) as e:
        load_run_spec(data=TINY.replace(*edit))
    assert "\n" not in str(e.value) and len(str(e.value)) < 300
    assert load_run_spec(data=TINY.replace("name: tiny", "name: 'Étude de nuit (KMWH)'"))


def test_hour_minus_zero_is_hour_zero_and_cannot_hide_a_training_environment_in_test():
    """``hour: -0.0`` was named ``KMWH_-0h_clear``: the same environment as a training
    ``KMWH_0h_clear`` under another name, so the run tested on a training environment
    (rc 0). One hour, one name: the duplicate is refused."""
    assert Environment("KMWH", -0.0).name == Environment("KMWH", 0.0).name == "KMWH_0h_clear"
    text = TINY.replace("test: [{runway: KSFO, hour: 17.0, sky: clear}]",
                        "test: [{runway: KMWH, hour: -0.0, sky: clear}]").replace(
        "train: [{runway: KMWH, hour: 9.0", "train: [{runway: KMWH, hour: 0.0")
    with pytest.raises(ScenarioError, match=re.escape("train/test: an environment is listed "
                                                      "twice: ['KMWH_0h_clear']")):
        load_run_spec(data=text)


def test_an_unknown_only_name_is_shown_short_and_the_runs_names_kept():
    """A 100 000-character ``--only`` name filled the 600-character error line, cutting
    off the list of the run's environments that the message is for."""
    from reachwatch.pipeline.run import check_slice
    with pytest.raises(ValueError) as e:
        check_slice(load_run_spec(data=TINY), ["K" * 100_000, "a\nb"], "fidelity")
    message = str(e.value)
    assert len(message) < 300 and "\n" not in message
    assert message.endswith("its environments are: KMWH_9h_clear, KSFO_17h_clear, KMWH_17h_clear")


def test_an_environment_flag_names_itself_and_the_value():
    from reachwatch.pipeline.evaluate_commands import parse_environment
    with pytest.raises(ValueError, match=r"^--test 'BOGUS:25:clear': environment.runway: unknown "
                                         r"runway 'BOGUS'"):
        parse_environment("BOGUS:25:clear", "--test")
    with pytest.raises(ValueError, match=r"^--train 'KMWH:9' must read RUNWAY:HOUR:SKY"):
        parse_environment("KMWH:9", "--train")
    assert parse_environment("KSFO:17:overcast", "--test").runway == "KSFO"


def test_a_runway_name_beside_a_runway_spec_is_warned_of_as_unread(caplog, monkeypatch):
    """{runway: A, runway_spec: {...}} was named CUSTOM_..., A silently unread."""
    import logging
    import reachwatch.systems.checks as checks
    monkeypatch.setattr(checks, "WARNED", set())
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        env = Environment("A", 9.0, "clear", RunwaySpec(half_width=12.0)).validate()
        Environment("MINE", 9.0, "clear", RunwaySpec(name="MINE")).validate()   # the same
        Environment(runway_spec=RunwaySpec(name="MINE")).validate()           # left out
    assert env.name == "CUSTOM_9h_clear"
    assert [r.getMessage() for r in caplog.records] == [
        "environment.runway 'A' is not read beside runway_spec: the environment is named by "
        "runway_spec.name ('CUSTOM'); set that to name it"]
