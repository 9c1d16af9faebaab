"""The monitor study's settings (``monitor: {kind: history}`` in a run file): the spec
loads, round-trips and refuses nonsense by name; the starts have a random stream of
their own; the study's key covers every setting and its code."""

from dataclasses import replace as dc_replace

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline.spec import MonitorVariant, dump_run_spec, load_run_spec
from tiny_run import MONITOR_STUDY, TINY
from reachwatch.taxi.application import TAXI_APPLICATION


def test_the_study_spec_loads_round_trips_and_names_its_errors():
    spec = load_run_spec(data=TINY + MONITOR_STUDY)
    assert spec.monitor.enabled and [v.name for v in spec.monitor.variants] == [
        "one frame", "GRU 3 + signals"]
    assert load_run_spec(data=dump_run_spec(spec)).monitor == spec.monitor
    assert spec.monitor.judged_runs == 6
    more = load_run_spec(data=TINY + MONITOR_STUDY.replace("guarded_runs: 2", "guarded_runs: 7\n"
                                                   "  held_out_runs: 8")).monitor
    assert (more.runs, more.judged_runs, more.guarded_runs) == (6, 8, 7)
    assert (spec.monitor.calibration_environment_runs, more.calibration_environment_runs) == (6, 8)
    fewer = load_run_spec(data=TINY + MONITOR_STUDY.replace(
        "guarded_runs: 2", "guarded_runs: 2\n  held_out_runs: 8\n  calibration_runs: 5")).monitor
    assert (fewer.calibration_environment_runs, fewer.judged_runs) == (5, 8)
    assert not load_run_spec(data=TINY).monitor.enabled            # off by default
    import dataclasses as dc
    assert dc.asdict(spec.monitor)["flag_rules"] == [[1, 1]]
    # the kept monitor: fixed in advance (the first variant, or the one named), or chosen
    assert spec.monitor.keep is None and spec.monitor.kept_in_advance == "one frame"
    named = dc.replace(spec.monitor, keep="GRU 3 + signals").validate()
    assert named.kept_in_advance == "GRU 3 + signals"
    chosen = dc.replace(spec.monitor, keep="choose", flag_rules=[[1, 1], [2, 3]]).validate()
    assert chosen.kept_in_advance is None
    for field, value in (("augment", "no"), ("variants", [MonitorVariant("x", signals=1)])):
        with pytest.raises(ValueError, match=rf"monitor\.{field}(\[0\]\.signals)? must be "
                                             rf"true or false, got"):
            dc.replace(spec.monitor, **{field: value}).validate()
    with pytest.raises(ValueError, match=r"monitor\.lr_schedule must be one of \('constant', "
                                         r"'cosine'\), got 'linear'"):
        dc.replace(spec.monitor, lr_schedule="linear").validate()
    with pytest.raises(ValueError, match=r"monitor\.input_norm must be one of \('fixed', "
                                         r"'per_frame'\), got 'instance'"):
        dc.replace(spec.monitor, input_norm="instance").validate()
    with pytest.raises(ValueError, match=r"^monitor\.state_targets must list distinct state "
                                         r"components \(whole numbers >= 0\), got \[0, 0\]$"):
        dc.replace(spec.monitor, state_targets=[0, 0]).validate()
    with pytest.raises(ValueError, match=r"^monitor\.pool \[1, 11\] must fit in the encoder's "
                                         r"last map, 6 x 10 cells at 48 x 80 px with 3 layers "
                                         r"\(at most \[6, 10\]\)$"):
        dc.replace(spec.monitor, pool=[1, 11], height=48, width=80).validate()
    for edit, message in ((("kind: history", "kind: lstm"), "monitor.kind must be one of"),
                          (("alpha: 0.5", "alpha: 0.1"), "monitor.calibrate: 1 environments "
                                                         "cannot bound"),
                          (("within: 1.0", "within: 2.0"), "monitor.within (2 s) must be shorter"),
                          # the taxi's lead at 3 m/s^2 is 5/3 s: not shorter than 1.5 s runs
                          (("duration: 2.0", "duration: 1.5"), "monitor.duration (1.5 s) is "
                           "not longer than the fallback's lead (1.66667 s: the application's "
                           "stopping time braking at monitor.brake_deceleration 3 m/s^2): no "
                           "failure within a run can be warned of in time"),
                          # 8 flags come 0.35 s in at 0.05 s; a warning 5/3 s before 2 s
                          (("runs: 6", "runs: 6\n  flag_rules: [[8, 9]]"),
                           "monitor.flag_rules: .8, 9. flags 7 control periods (0.35 s at "
                           "scenario.controller.period 0.05 s) into a run at the earliest, and "
                           "a warning must come 1.66667 s before a failure within "
                           "monitor.duration (2 s): no run could be warned of"),
                          (("{name: one frame}", "{name: GRU 3 + signals}"),
                           "monitor.variants must list"),
                          (("{name: one frame}", "{name: single-image detector}"),
                           "monitor.variants: 'single-image detector' is the name of the "
                           "detector's row"),
                          (("runs: 6", "runs: 0"), "monitor.runs must be a whole number"),
                          (("runs: 6", "runs: 6\n  flag_rules: [[2, 2], [2, 2]]"),
                           "monitor.flag_rules: a list of"),
                          (("runs: 6", "runs: 6\n  flag_rules: [[3, 2]]"),
                           "monitor.flag_rules: the k-of-n flag rule needs"),
                          (("runs: 6", "runs: 6\n  flag_rules: [[1, 1], [2, 3]]"),
                           "monitor.flag_rules lists 2 rules, and the kept monitor is fixed in "
                           "advance (monitor.keep): list one rule, or set monitor.keep: choose"),
                          (("runs: 6", "runs: 6\n  keep: GRU 3"),
                           "monitor.keep must be null (the first variant), 'choose' or a "
                           "variant's name, got 'GRU 3'"),
                          (("{name: one frame}", "{name: choose}"),
                           "monitor.variants: 'choose' is monitor.keep's word for choosing"),
                          (("{name: one frame}", "{name: oracle (privileged)}"),
                           "monitor.variants: 'oracle (privileged)' is the name of the oracle "
                           "monitor's row"),
                          (("runs: 6", "runs: 6\n  ensemble: 0"),
                           "monitor.ensemble must be a whole number in .1, 32., got 0"),
                          (("runs: 6", "runs: 6\n  held_out_runs: -1"),
                           "monitor.held_out_runs must be a whole number"),
                          (("{seed: 4}", "{seed: 4, count: 5}"),
                           "monitor.family.count is train . calibrate . held_out here (3); "
                           "leave it out, got 5"),
                          (("guarded_runs: 2", "guarded_runs: 7"),
                           "monitor.guarded_runs (7) must be at most the runs recorded per "
                           "held-out environment (6: monitor.held_out_runs, or monitor.runs")):
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")
                           .replace("^", r"\^")):
            load_run_spec(data=TINY + MONITOR_STUDY.replace(*edit))



def test_the_starts_do_not_repeat_the_environments_random_numbers():
    """Environment ``i`` of the family is drawn from ``[seed, i]``; the study's starts
    of it have a stream of their own. Seeded the same, the first start's lateral offset
    followed the hour (correlation 0.94 over 40 environments)."""
    from reachwatch.pipeline.monitor_study import starts_seed
    from reachwatch.reach.application import load_application
    spec = load_run_spec(data=TINY + MONITOR_STUDY).monitor
    application, scenario = load_application(TAXI_APPLICATION), load_scenario(data="")
    hours, offsets = [], []
    for i, environment in enumerate(dc_replace(spec.family, count=60).environments()):
        here = dc_replace(scenario, environment=environment)
        box = application.grid(here, (3, 3, 3))
        start = application.starts(here, (box.lo, box.hi), 5, starts_seed(spec, i))[0]
        assert not np.allclose(np.random.default_rng([spec.family.seed, i]).random(3),
                               np.random.default_rng(starts_seed(spec, i)).random(3))
        hours.append(environment.hour)
        offsets.append(start[0] / environment.half_width)
    assert abs(np.corrcoef(hours, offsets)[0, 1]) < 0.4


def test_the_study_key_covers_every_training_setting_and_the_study_code(monkeypatch):
    """The monitor stage's key changes with ``augment`` (which reaches training), with
    a training setting the run file does not name, and with the code of `STUDY_CODE`."""
    import dataclasses as dc
    import reachwatch.pipeline.monitor_study as study
    from reachwatch.reach.application import load_application
    spec = load_run_spec(data=TINY + MONITOR_STUDY)
    taxi = load_application(TAXI_APPLICATION)
    key = lambda monitor: study.study_key(monitor, taxi, spec.scenario)  # noqa: E731
    before = key(spec.monitor)
    assert before == key(spec.monitor)
    off = dc.replace(spec.monitor, augment=False)
    assert study.train_settings(off).augment is False and study.train_settings(spec.monitor).augment
    assert key(off) != before
    seeded = load_run_spec(data=TINY + MONITOR_STUDY.replace("  epochs: 1", "  epochs: 1\n  seed: 3"))
    assert study.train_settings(seeded.monitor).seed == 3 and key(seeded.monitor) != before
    ensemble = load_run_spec(data=TINY + MONITOR_STUDY.replace("  epochs: 1", "  epochs: 1\n  ensemble: 2"))
    assert [s.seed for s in study.member_settings(ensemble.monitor)] == [0, 1]
    assert [s.seed for s in study.member_settings(dc.replace(ensemble.monitor, seed=3))] == [6, 7]
    assert [s.seed for s in study.member_settings(seeded.monitor)] == [3]
    assert key(ensemble.monitor) != before
    cosine = load_run_spec(data=TINY + MONITOR_STUDY.replace("  epochs: 1",
                                                     "  epochs: 1\n  lr_schedule: cosine"))
    assert study.train_settings(cosine.monitor).lr_schedule == "cosine"
    assert key(cosine.monitor) != before
    fixed = load_run_spec(data=TINY + MONITOR_STUDY.replace("  epochs: 1",
                                                    "  epochs: 1\n  input_norm: fixed"))
    assert fixed.monitor.input_norm == "fixed" and key(fixed.monitor) != before
    # left out: the application's estimated state (the taxi's cross-track error, heading)
    assert spec.monitor.state_targets is None
    assert study.train_settings(spec.monitor).state_targets == (0, 2)
    for line, field, value in (("state_targets: [0]", "state_targets", (0,)),
                               ("state_targets: []", "state_targets", ()),
                               ("state_weight: 0.5", "state_weight", 0.5)):
        taught = load_run_spec(data=TINY + MONITOR_STUDY.replace("  epochs: 1",
                                                         f"  epochs: 1\n  {line}"))
        assert getattr(study.train_settings(taught.monitor), field) == value
        assert key(taught.monitor) != before
    assert spec.monitor.pool == [2, 3]
    whole = load_run_spec(data=TINY + MONITOR_STUDY.replace("pool: [2, 3]", "pool: [1, 1]"))
    assert whole.monitor.pool == [1, 1] and key(whole.monitor) != before
    settings = study.train_settings
    monkeypatch.setattr(study, "train_settings",
                        lambda monitor, application=None: dc.replace(
                            settings(monitor, application), batch_size=64))
    assert key(spec.monitor) != before
    monkeypatch.setattr(study, "train_settings", settings)
    import sys
    fp = sys.modules["reachwatch.reach.fingerprint"]    # the module, not the function
    real = fp.modules_source_digest
    monkeypatch.setattr(fp, "modules_source_digest",
                        lambda *names: real(*names) + ("!" if set(names) == set(
                            study.STUDY_CODE) else ""))
    assert key(spec.monitor) != before


def test_the_study_key_holds_the_content_of_a_file_its_environments_name(tmp_path):
    """An environment of an application's own type may name a file (a map, a mesh):
    the study's settings are keyed by content, so an edit of that file runs the study
    again where its path alone kept it up to date."""
    import dataclasses as dc

    import reachwatch.pipeline.monitor_study as study
    from reachwatch.reach.application import load_application
    spec, taxi = load_run_spec(data=TINY + MONITOR_STUDY), load_application(TAXI_APPLICATION)
    named = tmp_path / "scene.txt"
    named.write_text("one scene")
    env = dc.replace(spec.test[0], runway=str(named))     # a string naming a file
    monitor = dc.replace(spec.monitor, also_held_out=[env])
    before = study.study_key(monitor, taxi, spec.scenario)
    assert study.study_key(monitor, taxi, spec.scenario) == before
    named.write_text("another scene")
    assert study.study_key(monitor, taxi, spec.scenario) != before


def test_the_study_key_holds_the_compared_detectors_content(tmp_path):
    """A study that judges a detector beside its variants is keyed by the detector's
    bytes, not its path: another detector at the same path runs the study again."""
    import torch

    import reachwatch.pipeline.monitor_study as study
    from reachwatch.diagrams import save_checkpoint
    from reachwatch.reach.application import load_application
    from reachwatch.systems import DetectorConfig, build_detector
    spec, taxi = load_run_spec(data=TINY + MONITOR_STUDY), load_application(TAXI_APPLICATION)
    path, keys = tmp_path / "detector.pt", []
    for seed in (0, 1):
        torch.manual_seed(seed)
        config = DetectorConfig(height=16, width=24, channels=[4])
        save_checkpoint(path, kind="detector", model=build_detector(config), model_config=config,
                        preprocess_config=None, metadata={"threshold": 0.5})
        keys.append(study.study_key(spec.monitor, taxi, spec.scenario, path))
    alone = study.study_key(spec.monitor, taxi, spec.scenario)
    assert len({alone, *keys}) == 3


def test_keys_that_do_nothing_are_warned_of_and_a_family_drawn_twice_refused(caplog,
                                                                              monkeypatch):
    """A ``monitor:`` block that sets the study's keys without ``kind: history`` (the
    study does not run) is warned of in one line, once; ``test_random`` drawn from
    ``train_random``'s seed (the held-out environments would be trained on) and
    ``incremental.anomalies: 0`` (the stage fine-tunes on none, and failed hours later)
    are refused in one line naming the key."""
    import logging
    import reachwatch.systems.checks as checks
    monkeypatch.setattr(checks, "WARNED", set())                   # none said before
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        off = load_run_spec(data=TINY + "monitor: {train: 3, runs: 7}\n").monitor
        off.validate()
    assert not off.enabled
    said = [r.getMessage() for r in caplog.records if "does not run" in r.getMessage()]
    assert said == ["monitor.kind is 'detector', so the monitor study does not run and "
                    "['train', 'runs'] set in monitor do nothing (set monitor.kind: history "
                    "to run it)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        load_run_spec(data=TINY + "monitor: {kind: detector}\n")
        load_run_spec(data=TINY + MONITOR_STUDY)
    assert not caplog.records
    with pytest.raises(ValueError, match=r"test_random.seed is train_random.seed \(4\)"):
        load_run_spec(data=TINY + "train_random: {count: 1, seed: 4}\n"
                                  "test_random: {count: 1, seed: 4}\n")
    load_run_spec(data=TINY + "train_random: {count: 1, seed: 4}\n"
                              "test_random: {count: 1, seed: 5}\n")
    with pytest.raises(ValueError, match=r"incremental.anomalies must be at least 1 while "
                                         r"the stage runs"):
        load_run_spec(data=TINY.replace("anomalies: 20", "anomalies: 0"))
    load_run_spec(data=TINY.replace("anomalies: 20", "anomalies: 0\n  enabled: false"))


def test_a_guard_environment_that_is_a_training_one_is_warned_of(caplog, monkeypatch):
    """The guard's figures on an environment whose images the detector trained on are
    better than on a held-out one: a one-line warning names it (the incremental stage
    refuses one; the guard may be asked on purpose)."""
    import logging
    import reachwatch.systems.checks as checks
    monkeypatch.setattr(checks, "WARNED", set())
    text = TINY.replace("guard: {candidates: 2,", "guard: {environments: [{runway: KMWH, "
                        "hour: 9.0, sky: clear}], candidates: 2,")
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        load_run_spec(data=text)
        load_run_spec(data=text)                                  # said once
    said = [r.getMessage() for r in caplog.records]
    assert said == ["guard.environments[0]: 'KMWH_9h_clear' is a training environment: "
                    "the detector has seen its images, so the guard's figures there are "
                    "better than on a held-out one"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        load_run_spec(data=TINY)                           # the first test one: nothing
    assert not caplog.records



def test_a_run_files_single_run_settings_are_warned_of_not_silently_unread(caplog, monkeypatch):
    """scenario.initial_state, duration and seed are `reachwatch simulate`'s: a run's
    stages set their own (`without_run_settings`). Before, a run file setting them was
    run without a word."""
    import logging
    import reachwatch.systems.checks as checks
    monkeypatch.setattr(checks, "WARNED", set())
    text = TINY + "scenario:\n  duration: 20.0\n  initial_state: {px: 3.0}\n"
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        spec = load_run_spec(data=text)
        load_run_spec(data=text)                                  # said once
    assert [r.getMessage() for r in caplog.records] == [
        "scenario.initial_state, scenario.duration: a single run's (reachwatch simulate); a "
        "run's stages set their own starts, durations and seeds and do not read them"]
    assert spec.scenario.duration == 20.0             # kept as written: simulate reads it
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="reachwatch"):
        load_run_spec(data=TINY + "scenario:\n  duration: 10.0\n")   # the default: nothing
    assert not caplog.records


def test_a_batch_of_runs_encodes_in_the_loop_and_is_keyed_so():
    """``monitor.encoder_process`` is a single loop's: a batch's loops (and their keys)
    are those of a monitor encoding in the loop, the same scores without a process a loop."""
    from reachwatch.diagrams import load_scenario
    from reachwatch.reach.application import without_run_settings
    from reachwatch.reach.fingerprint import fingerprint
    own = load_scenario(data="monitor: {encoder_process: true}\nduration: 3.0\n")
    batch = without_run_settings(own)
    assert own.monitor.encoder_process and not batch.monitor.encoder_process
    assert fingerprint(batch) == fingerprint(without_run_settings(load_scenario(data="")))
