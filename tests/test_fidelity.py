"""Fidelity of BRT verdicts against real runs: the interval arithmetic, the counts, and
box exits of a real Drake loop."""

import re

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario, make_state_feedback_diagram, simulate
from reachwatch.reach import compare_verdicts, left_box, select_map, wilson_interval
from reachwatch.taxi import OffRunway, on_runway_starts, paper_grid


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(98, 100)
    assert (lo, hi) == pytest.approx((0.929988, 0.994498), abs=1e-6)
    # 0 of n: lower end 0, upper end z^2 / (n + z^2) (the normal interval would be [0, 0])
    z2 = 1.959963984540054 ** 2
    assert wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z2), 1.0))
    for n in (1, 6, 7, 3969):             # exact ends, not a rounding error away from them
        assert wilson_interval(0, n)[0] == 0.0 and wilson_interval(n, n)[1] == 1.0
    lo, hi = wilson_interval(15, 150)          # symmetric in successes and failures
    assert wilson_interval(135, 150) == pytest.approx((1 - hi, 1 - lo))
    for bad, says in [((3, 2), "got 3 of 2"), ((-1, 5), "got -1 of 5"), ((0, 0), "got 0 of 0"),
                      ((True, 4), "counts, not booleans")]:
        with pytest.raises(ValueError, match=says):
            wilson_interval(*bad)


def test_compare_verdicts_counts_each_kind_of_error():
    predicted = [True, True, False, False, False, True]
    failed = [True, False, True, False, True, True]
    left = [False, False, True, True, False, False]
    f = compare_verdicts(predicted, failed, left)
    assert (f.n, f.real_failures, f.predicted_failures) == (6, 4, 3)
    assert (f.agree, f.false_safe, f.false_unsafe) == (3, 2, 1)
    assert (f.box_exits, f.exits_missed) == (2, 1)
    rate, lo, hi = f.rate("false_safe")
    assert rate == pytest.approx(2 / 6) and (lo, hi) == pytest.approx(wilson_interval(2, 6))
    assert "false-safe 33.3 %" in f.summary()
    with pytest.raises(ValueError, match="equal non-empty"):
        compare_verdicts([True], [True, False])


def test_select_map_weighs_false_safe_verdicts_and_breaks_ties_by_cost():
    failed = np.array([True] * 4 + [False] * 16)
    def scored(false_safe, false_unsafe):
        predicted = failed.copy()
        predicted[:false_safe] = False                       # failures called safe
        predicted[4:4 + false_unsafe] = True                 # safe starts called failing
        return compare_verdicts(predicted, failed)
    nominal, robust, coarse = scored(2, 0), scored(0, 3), scored(1, 0)
    # 2 false-safe weigh 4 errors at weight 2 (more than robust's 3), 2 at weight 1 (fewer)
    assert select_map([nominal, robust]) == 1
    assert select_map([nominal, robust], false_safe_weight=1.0) == 0
    # equal weighted errors: fewer false-safe verdicts first, then the cheaper map
    assert select_map([scored(1, 1), scored(0, 3)]) == 1
    assert select_map([coarse, scored(1, 0)], costs=[40_000, 11_781]) == 1
    assert select_map([coarse, scored(1, 0)]) == 0
    with pytest.raises(ValueError, match="same selection runs"):
        select_map([nominal, compare_verdicts(failed[:10], failed[:10])])
    for bad, says in [(dict(fidelities=[]), "at least one candidate"),
                      (dict(fidelities=[nominal], costs=[1, 2]), "2 costs for 1 candidates"),
                      (dict(fidelities=[nominal], false_safe_weight=0.5), "got 0.5"),
                      (dict(fidelities=[0.9]), "takes Fidelity records")]:
        with pytest.raises(ValueError, match=says):
            select_map(**bad)


def test_a_loop_turning_beyond_the_box_is_reported():
    """A P-controller with the heading gain's sign flipped turns away: its real run
    leaves the box's +-28 deg within 1.2 s, and left_box says so; run on, its command
    passes a quarter turn (2 x 45 deg), which the plant refuses."""
    grid = paper_grid(10.0, (5, 3, 5))
    turning = load_scenario(data="controller: {px_gain: 0.0, theta_gain: 2.0}\n")
    run = simulate(make_state_feedback_diagram(turning), initial_state=[0.0, 120.0, 0.05],
                   duration=1.2, period=0.05)
    assert np.max(np.abs(run.state[:, 2])) > np.deg2rad(28.0)
    with pytest.raises(ValueError, match="'steering_angle' is .* rad at t = 1.[0-9]* s; a "
                                         "wheel angle lies within"):
        simulate(make_state_feedback_diagram(turning), initial_state=[0.0, 120.0, 0.05],
                 duration=8.0, period=0.05)
    assert left_box(run.state, grid, axes=(1, 2))
    steady = simulate(make_state_feedback_diagram(load_scenario(data="")),
                      initial_state=[0.0, 120.0, 0.05], duration=8.0, period=0.05,
                      failed=OffRunway(10.0))
    assert not left_box(steady.state, grid, axes=(1, 2))


def test_on_runway_starts_are_seeded_and_on_the_runway():
    grid = paper_grid(10.0, (5, 3, 5))
    a, b = (on_runway_starts(grid, 200, 3, half_width=10.0) for _ in range(2))
    np.testing.assert_array_equal(a, b)
    assert np.all(np.abs(a[:, 0]) < 10.0) and np.abs(a[:, 0]).max() > 9.0
    assert not np.array_equal(a, on_runway_starts(grid, 200, 4, half_width=10.0))


def test_brt_command_reports_real_loop_fidelity_with_intervals(tmp_path, capsys):
    from reachwatch.pipeline.cli import main
    scenario = tmp_path / "s.yaml"
    scenario.write_text("environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    assert main(["brt", "--scenario", str(scenario), "--shape", "5", "3", "5", "--out",
                 str(tmp_path / "out"), "--cache", str(tmp_path / "cache"), "--executor",
                 "inline", "--horizon", "1.0", "--drake-starts", "3", "--refine", "1",
                 "--refine-band", "0.5"]) == 0
    text = capsys.readouterr().out
    assert "adaptive refinement: 5x3x5 (75 rendered) -> 9x5x9 (" in text
    assert "3 starts" in text and "false-safe" in text and "left the box" in text
    assert re.search(r"agreement \d+\.\d % \[\d+\.\d, \d+\.\d\]", text)
    nominal = float(re.search(r"BRT volume: (\d+\.\d+)%", text).group(1))
    # the same maps solved robustly: no new renders, a BRT at least as large
    assert main(["brt", "--scenario", str(scenario), "--shape", "5", "3", "5", "--out",
                 str(tmp_path / "robust"), "--cache", str(tmp_path / "cache"), "--executor",
                 "inline", "--horizon", "1.0", "--drake-starts", "0",
                 "--robust-spread", "0"]) == 0
    text = capsys.readouterr().out
    assert "robust BRT: the steering takes its worst value" in text
    assert float(re.search(r"BRT volume: (\d+\.\d+)%", text).group(1)) >= nominal


def test_brt_command_widens_the_solved_box_but_checks_starts_in_the_paper_box(
        tmp_path, capsys, monkeypatch):
    from reachwatch.pipeline import reach_commands
    from reachwatch.pipeline.cli import main
    from reachwatch.reach import ValueFunction
    seen = {}
    real = reach_commands.real_loop_fidelity

    def spy(scenario, vf, starts, **kwargs):
        seen["starts"] = starts
        return real(scenario, vf, starts, **kwargs)
    monkeypatch.setattr(reach_commands, "real_loop_fidelity", spy)
    scenario = tmp_path / "s.yaml"
    scenario.write_text("environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    assert main(["brt", "--scenario", str(scenario), "--shape", "5", "3", "5", "--out",
                 str(tmp_path / "out"), "--cache", str(tmp_path / "cache"), "--executor",
                 "inline", "--horizon", "0.5", "--drake-starts", "4",
                 "--solved-theta-deg", "70", "--solved-py-max", "290"]) == 0
    vf = ValueFunction.load(next((tmp_path / "out").glob("value_*.npz")))
    np.testing.assert_allclose(vf.grid.hi[1:], [290.0, np.deg2rad(70.0)])
    np.testing.assert_allclose(vf.grid.lo[1:], [100.0, np.deg2rad(-70.0)])
    starts = seen["starts"]
    assert len(starts) == 4
    assert np.all((starts[:, 1] >= 100.0) & (starts[:, 1] <= 250.0))
    assert np.all(np.abs(starts[:, 2]) <= np.deg2rad(28.0))


def test_label_verdicts_follow_each_source_and_box_exits_refuse_brt_labels():
    from reachwatch.pipeline.fidelity_stages import BoxExitError, check_box_exits, label_verdicts
    values = np.array([-1.0, 0.5, 3.0, 4.0])
    real = np.array([True, True, True, False])
    labels = lambda source, **audit: {"source": source, "audit": audit}  # noqa: E731
    np.testing.assert_array_equal(label_verdicts(labels("brt"), 2.0, values, real), values <= 0)
    np.testing.assert_array_equal(label_verdicts(labels("rollout"), 2.0, values, real), real)
    # hybrid with a trusted map rolls out only |V| < band; with a distrusted one all V > -band
    np.testing.assert_array_equal(label_verdicts(labels("hybrid", map_trusted=True), 2.0, values, real),
                                  [True, True, False, False])
    survives = np.array([False, True, True, False])      # the map's unsafe -1.0 is wrong
    np.testing.assert_array_equal(label_verdicts(labels("hybrid", map_trusted=True), 2.0, values,
                                                 survives), [False, True, False, False])
    np.testing.assert_array_equal(label_verdicts(labels("hybrid", map_trusted=False), 2.0, values, real),
                                  real)
    # a distrusted map keeps its unsafe verdicts beyond the band, unless the dataset fell
    # back to trajectory labels: then every fresh state is its own run
    deep, wrong_deep = np.array([-5.0, 0.5, 3.0, 4.0]), np.array([False, True, True, False])
    distrusted = labels("hybrid", map_trusted=False)
    np.testing.assert_array_equal(label_verdicts(distrusted, 2.0, deep, wrong_deep),
                                  [True, True, True, False])
    np.testing.assert_array_equal(label_verdicts({**distrusted, "labelled_by": "trajectory"},
                                                 2.0, deep, wrong_deep), wrong_deep)
    from reachwatch.pipeline.fidelity_sections import _audit_text        # the report names the fallback
    assert _audit_text({"map_trusted": False, "labelled_by": "trajectory"}) == \
        "map not trusted: trajectory labels"
    assert _audit_text({"map_trusted": False, "labelled_by": None}) == "map not trusted"
    assert _audit_text({"map_trusted": True, "band": 0.1, "audit_runs": 100}) == \
        "map trusted after 100 runs, band 0.10 m"
    # what each environment's labels cost: a trusted hybrid's rollout frames hold its
    # audit's; a fallback adds the audit to its trajectory runs; paths add their own
    from reachwatch.pipeline.fidelity_sections import label_renders
    counts = {"brt": 700, "rollout": 300, "path": 0}
    assert label_renders({"source": "brt", "counts": counts}) == [1000, 0, "0.0"]
    assert label_renders({"source": "hybrid", "rollout_frames": 37440, "counts": counts}) == \
        [1000, 37440, "37.4"]
    assert label_renders({"source": "hybrid", "labelled_by": "trajectory", "audit_frames": 8000,
                          "rollout_frames": 22000, "paths": {"frames": 500},
                          "counts": {"rollout": 100, "path": 900}}) == [1000, 30500, "30.5"]
    assert label_renders({}) == ["-", "-", "-"]
    # the band the audit widened to (recorded in the manifest) wins over the run file's
    np.testing.assert_array_equal(label_verdicts(labels("hybrid", map_trusted=True, band=3.5), 2.0,
                                                 values, real), [True, True, True, False])
    results = {"A": {"brt": {"box_exits_rate": 0.3}, "labels": {"source": "brt"}},
               "B": {"brt": {"box_exits_rate": 0.3}, "labels": {"source": "hybrid"}},
               "C": {"brt": {"box_exits_rate": 0.01}, "labels": {"source": "brt"}},
               "D": {"brt": {"box_exits_rate": 0.5}}}
    with pytest.raises(BoxExitError, match=r"A: 30 % of runs \(fidelity.max_box_exits 5 %\)"):
        check_box_exits(results, 0.05)
    check_box_exits(results, 0.3)                     # at the limit: accepted
    check_box_exits({k: results[k] for k in "BCD"}, 0.05)


def test_the_check_extends_to_more_starts_only_where_its_first_runs_find_a_wrong_verdict(
        tmp_path):
    """``fidelity.more_starts``: an environment whose first ``starts`` runs all agree
    with the map keeps them; one where a run contradicts it is checked on the longer
    draw, whose first rows are the same runs (the fake loop counts what it is asked)."""
    import copy
    import types

    from reachwatch.pipeline import fidelity_stages
    from reachwatch.pipeline.keys import digest
    from reachwatch.pipeline.spec import FidelitySpec, load_run_spec
    from reachwatch.reach.outcomes import Outcomes
    from reachwatch.taxi.application import TaxiApplication

    spec = load_run_spec(data="""
name: extend
train: [{runway: KMWH, hour: 9.0, sky: clear}]
test: [{runway: KSFO, hour: 21.0, sky: clear}]
grid: [5, 3, 5]
horizon: 2.0
fidelity: {starts: 4, more_starts: 10}
""")
    asked = []

    def fake_real_outcomes(scenario, states, **kw):      # fails where |px| >= the env's edge
        asked.append(np.array(states))
        edge = 5.0 if scenario.environment.name.startswith("KMWH") else 0.0
        failed = np.abs(states[:, 0]) >= edge
        n = len(states)
        return Outcomes({"failed": failed, "left_box": np.zeros(n, bool),
                         "max_abs_theta": np.zeros(n), "ticks": np.full(n, 7)}, key="fake")

    class FakeLoop(TaxiApplication):                   # the taxi with the fake real loop
        def real_outcomes(self, scenario, states, **kw):
            return fake_real_outcomes(scenario, states, **kw)

    class Map:                                           # the BRT: |px| >= 5 m fails
        def at(self, states):
            return 5.0 - np.abs(np.asarray(states)[:, 0])

        def in_brt(self, states):
            return self.at(states) <= 0

    def scenario_for(env):
        scenario = copy.deepcopy(spec.scenario)
        scenario.environment = env
        return scenario
    solved = paper_grid(11.0, (3, 3, 3), theta_deg=70.0, py_max=290.0)
    run = types.SimpleNamespace(
        spec=spec, application=FakeLoop(), outputs={"dataset": {"labels": {}}}, executor=None,
        progress=False,
        scenario_for=scenario_for, path=lambda p: tmp_path / p,
        grid_for=lambda env: paper_grid(env.half_width, (5, 3, 5)),
        solved_grid_for=lambda env: solved, value_function=lambda name: Map(),
        steering_table=lambda env: (solved, np.zeros((3, 3, 3, 1))))

    right = fidelity_stages.fidelity_env(run, spec.train[0])        # the map is the loop
    assert (right["starts"], right["brt"]["n"], right["extended"]) == (4, 4, False)
    assert right["frames"] == 4 * 7 and len(asked) == 1

    asked.clear()
    env = spec.test[0]
    wrong = fidelity_stages.fidelity_env(run, env)      # every start fails: the map errs
    draw = on_runway_starts(paper_grid(env.half_width, (5, 3, 5)), 10, 1000,
                            half_width=env.half_width)
    assert [len(a) for a in asked] == [4, 6]                          # 4 runs, then 6 more
    np.testing.assert_array_equal(np.concatenate(asked), draw)
    assert (wrong["starts"], wrong["brt"]["n"], wrong["table_rollouts"]["n"]) == (10, 10, 10)
    assert wrong["extended"] and wrong["frames"] == 10 * 7
    assert wrong["brt"]["false_safe"] == int(np.sum(np.abs(draw[:, 0]) < 5.0))

    # the report says how many starts and which environments were extended
    from reachwatch.pipeline.fidelity_sections import fidelity_section
    from reachwatch.pipeline.report import Page
    page = Page("t")
    run.outputs["fidelity"] = {spec.train[0].name: right, env.name: wrong}
    fidelity_section(page, run.spec, run.outputs["fidelity"],
                     run.outputs.get("dataset", {}).get("labels", {}), {})
    md = "".join(page.md)
    assert "from 4 seeded uniform on-runway starts per environment, 10 where the first 4 " \
        "found the BRT or the labels wrong or the labels' audit had distrusted the map " \
        "(fidelity.more_starts; found wrong: KSFO_21h_clear, whose rates lean" in md
    assert f"| {env.name} | extra | 10 |" in md and f"| {spec.train[0].name} | extra | 4 |" in md
    run.outputs["fidelity"] = {spec.train[0].name: right}
    page = Page("t")
    fidelity_section(page, run.spec, run.outputs["fidelity"],
                     run.outputs.get("dataset", {}).get("labels", {}), {})
    assert "the map (fidelity.more_starts; none was) (|px| < B" in "".join(page.md)

    # where the labels' audit distrusted the map, the check is extended even though its
    # first runs find every verdict right (the map and the loop agree here)
    asked.clear()
    run.outputs["dataset"]["labels"][spec.train[0].name] = {
        "source": "hybrid", "labelled_by": "trajectory",
        "audit": {"samples": 4, "map_trusted": False, "band": 0.1}}
    distrusted = fidelity_stages.fidelity_env(run, spec.train[0])
    assert [len(a) for a in asked] == [4, 6] and distrusted["starts"] == 10
    assert distrusted["brt"]["agree"] == 10
    assert (distrusted["extended"], distrusted["extended_because"]) == (True, "audit")
    assert "extended_because" not in right and wrong["extended_because"] == "check"
    run.outputs["fidelity"] = {spec.train[0].name: distrusted, env.name: wrong}
    page = Page("t")
    fidelity_section(page, run.spec, run.outputs["fidelity"],
                     run.outputs.get("dataset", {}).get("labels", {}), {})
    assert ("(fidelity.more_starts; found wrong: KSFO_21h_clear, whose rates lean slightly "
            "towards error, the extension having been chosen by it; distrusted by the audit: "
            "KMWH_9h_clear)") in "".join(page.md)
    del run.outputs["dataset"]["labels"][spec.train[0].name]

    # unset, it leaves the stage's key as it was before the field existed
    assert digest(FidelitySpec(starts=50).key()) == digest(
        {"starts": 50, "seed": 1000, "max_box_exits": 0.05})
    assert digest(FidelitySpec(starts=50, more_starts=200).key()) != digest(FidelitySpec(starts=50).key())
    # the extension rule is in the key: a check extended by the older rule runs again
    assert digest(FidelitySpec(starts=50, more_starts=200).key()) != digest(
        {"starts": 50, "seed": 1000, "max_box_exits": 0.05, "more_starts": 200})
    for bad, why in ((4, "must be 0 .* above fidelity.starts"), (2, "above"), (-1, r"in \[0, 1000000\]"),
                     (True, "expected int")):
        with pytest.raises(ValueError, match=f"fidelity.more_starts.*{why}"):
            load_run_spec(data=f"""
name: extend
train: [{{runway: KMWH, hour: 9.0, sky: clear}}]
test: [{{runway: KSFO, hour: 21.0, sky: clear}}]
fidelity: {{starts: 4, more_starts: {str(bad).lower()}}}
""")


def test_the_report_judges_each_environments_labels_against_the_target():
    """Met only where the fresh starts and the re-run read-along states both reach 99 %
    agreement with at most 1 % false-safe; the misses are named with their figures."""
    from reachwatch.pipeline.fidelity_sections import label_target_text
    real = np.array([True] * 10 + [False] * 190)

    def check(false_safe=0, false_unsafe=0):
        labels = real.copy()
        labels[:false_safe] = False                          # failed, labelled safe
        labels[10:10 + false_unsafe] = True                  # survived, labelled failing
        return compare_verdicts(labels, real).as_dict()

    results = {"day": {"labels": check(false_unsafe=2)},           # 99.0 %: met
               "dusk": {"labels": check(false_safe=3)},            # 1.5 % false-safe
               "night": {"labels": check(), "path_labels": check(false_unsafe=3)},
               "unchecked": {"brt": {}}}
    text = label_target_text(results)
    assert "met in 1 of 3 environments, checked on 200 starts each" in text
    short = {**results, "short": {"labels": compare_verdicts(real[:50], real[:50]).as_dict()}}
    assert "met in 2 of 4 environments, checked on 50-200 starts each" in label_target_text(short)
    assert "dusk (starts: agreement 98.5 %, false-safe 1.5 % of 200)" in text
    assert "night (read-along states: agreement 98.5 %, false-safe 0.0 % of 200)" in text
    assert "day (" not in text
    assert "by construction" not in text
    assert label_target_text({"unchecked": {"brt": {}}}) == ""
    from reachwatch.pipeline.fidelity_sections import labels_meet_target   # the same rule, per record
    assert [labels_meet_target(results[n]) for n in ("day", "dusk", "night")] == [
        True, False, False]
    # labels that are runs of the real loop from their own state: the fresh starts
    # agree by construction, and the sentence says which environments those are
    results["night"]["labels"].update(source="hybrid", labelled_by="trajectory")
    results["rolled"] = {"labels": {**check(), "source": "rollout"}}
    text = label_target_text(results)
    assert "met in 2 of 4 environments" in text
    assert ("In 2 of them (night, rolled) a fresh start is labelled by its own real run "
            "and agrees by construction: there only the re-run read-along states test the "
            "labels (none where a dataset has no such states).") in text


def test_the_heading_figures_of_a_plant_without_a_heading_are_nan():
    """A plant's own `real_outcomes` may leave out the taxi's ``max_abs_theta``: its
    figures are NaN (the stage raised a KeyError)."""
    from reachwatch.pipeline.fidelity_stages import heading_percentiles
    headings = np.deg2rad([0.0, 10.0, 20.0, 30.0, 40.0])
    assert heading_percentiles({"max_abs_theta": headings}, 5) == [20.0, 36.0, 40.0]
    assert np.isnan(heading_percentiles({"failed": np.zeros(5, bool)}, 5)).all()
