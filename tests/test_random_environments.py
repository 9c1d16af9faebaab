"""Random environment families: seeded and reproducible, every drawn runway valid and
within its ranges, bad fields named, and a family in a run file."""

import dataclasses as dc
import re

import numpy as np
import pytest

from reachwatch.diagrams import ScenarioError, StateRenderer
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.systems import RandomEnvironments, RandomRunwayRanges


def test_same_seed_same_family_and_each_member_stands_alone():
    a = RandomEnvironments(count=6, seed=3).environments()
    b = RandomEnvironments(count=6, seed=3).environments()
    assert [dc.asdict(e) for e in a] == [dc.asdict(e) for e in b]
    # Member i depends on (seed, i) only: a longer family starts with the shorter one.
    longer = RandomEnvironments(count=9, seed=3).environments()
    assert [dc.asdict(e) for e in longer[:6]] == [dc.asdict(e) for e in a]
    other = RandomEnvironments(count=6, seed=4).environments()
    assert {e.name for e in other}.isdisjoint(e.name for e in a)
    assert [e.spec().half_width for e in other] != [e.spec().half_width for e in a]
    assert re.fullmatch(r"RND3-0_[0-9p]+h_(clear|overcast)", a[0].name)


def test_draws_stay_in_their_ranges_and_vary():
    ranges = RandomRunwayRanges(half_width=[12.0, 14.0], pavement_tone=[0.5, 0.5],
                                surfaces=["concrete"], lights=0.0, buildings=[2, 3],
                                taxiway_lines=[1, 1])
    family = RandomEnvironments(count=40, seed=0, hours=[20.0, 22.0], skies=["overcast"],
                                runway=ranges).environments()
    specs = [e.spec() for e in family]
    assert all(12.0 <= s.half_width <= 14.0 for s in specs)
    assert all(s.surface.kind == "concrete" and not s.lights.enabled for s in specs)
    assert all(s.buildings in (2, 3) and len(s.taxiway_lines) == 1 for s in specs)
    assert all(abs(np.mean(s.surface.tone) - 0.5) <= 0.02 for s in specs)
    assert all(20.0 <= e.hour <= 22.0 and e.sky == "overcast" for e in family)
    assert {s.buildings for s in specs} == {2, 3}
    assert len({round(s.half_width, 3) for s in specs}) == 40
    # The defaults cover both surfaces, both skies and day and night.
    default = RandomEnvironments(count=40, seed=1).environments()
    assert {e.spec().surface.kind for e in default} == {"asphalt", "concrete"}
    assert {e.sky for e in default} == {"clear", "overcast"}
    assert min(e.hour for e in default) < 6 and max(e.hour for e in default) > 18


@pytest.mark.parametrize("edit, message", [
    ({"count": -1}, "random.count must be a whole number in [0, 1000]"),
    ({"hours": [10.0, 30.0]}, "random.hours[1] must be a finite number in [0, 24] h"),
    ({"hours": [12.0, 10.0]}, "random.hours must be [low, high] with low <= high"),
    ({"skies": ["foggy"]}, "random.skies must list some of"),
    ({"prefix": "R-1"}, "random.prefix must be letters and digits"),
    ({"runway": RandomRunwayRanges(half_width=[0.0, 5.0])}, "random.runway.half_width[0] must be"),
    ({"runway": RandomRunwayRanges(surfaces=["gravel"])}, "random.runway.surfaces must list"),
    ({"runway": RandomRunwayRanges(buildings=[1.5, 3])}, "random.runway.buildings[0] must be a whole number"),
    ({"runway": RandomRunwayRanges(lights=1.5)}, "random.runway.lights must be a finite number in [0, 1]"),
])
def test_bad_fields_are_named(edit, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        RandomEnvironments(**edit).validate()


RUN = """
train: [{runway: KMWH, hour: 9.0, sky: clear}]
train_random: {count: 3, seed: 0, runway: {half_width: [9, 20]}}
test_random: {count: 2, seed: 7}
"""


def test_a_run_file_asks_for_families():
    spec = load_run_spec(data=RUN)
    train, held_out = spec.training_environments(), spec.held_out_environments()
    assert [e.name for e in train[:1]] == ["KMWH_9h_clear"] and len(train) == 4
    assert len(held_out) == 2 and all(e.name.startswith("RND7-") for e in held_out)
    assert all(9.0 <= e.half_width <= 20.0 for e in train[1:])
    assert spec.guard_environments()[0].name == held_out[0].name
    with pytest.raises(ScenarioError, match=r"test_random.seed is train_random.seed \(0\): "
                                            r"one seed draws the same environments"):
        load_run_spec(data=RUN.replace("seed: 7", "seed: 0, runway: {half_width: [9, 20]}"))
    # another prefix names the same draws otherwise: the same family still
    with pytest.raises(ScenarioError, match=r"test: 'HELD0-0_\S+' is also a training "
                                            r"environment \('RND0-0_\S+'\)"):
        load_run_spec(data=RUN.replace("seed: 7", "seed: 0, prefix: HELD, count: 3, "
                                                   "runway: {half_width: [9, 20]}")
                      .replace("count: 2, ", ""))
    with pytest.raises(ScenarioError, match=re.escape("train_random.runway.length[0] must be")):
        load_run_spec(data=RUN.replace("half_width: [9, 20]", "length: [100, 200]"))
    with pytest.raises(ScenarioError, match="test: list at least one held-out"):
        load_run_spec(data=RUN.replace("test_random: {count: 2, seed: 7}", ""))


def test_a_random_runway_renders(small_camera):
    # No lights, no stripes, no buildings, no touchdown zone: the sparse corner renders too.
    ranges = RandomRunwayRanges(lights=0.0, threshold_stripes=[0, 0], buildings=[0, 0],
                                taxiway_lines=[3, 3])
    env = RandomEnvironments(count=1, seed=5, hours=[21.0, 21.0], runway=ranges).environments()[0]
    image = StateRenderer(environment=env, camera=small_camera).render([0.0, 120.0, 0.0])
    assert image.shape[2] == 3 and image.std() > 1.0


def test_a_prefix_ending_in_a_digit_is_refused():
    """RND1 with seed 1 and RND with seed 11 named their environments alike."""
    import pytest
    from reachwatch.systems import RandomEnvironments
    with pytest.raises(ValueError, match=r"test_random.prefix must be letters and digits "
                                         r"\(1 to 16, ASCII\) ending in a letter"):
        RandomEnvironments(count=1, seed=1, prefix="RND1").validate("test_random")
    RandomEnvironments(count=1, seed=1, prefix="RND1A").validate("test_random")


def test_a_family_whose_narrowest_runway_has_no_room_for_its_stripes_is_refused():
    """Before: validated, then a drawn runway of 1.5 m failed the scene build."""
    import pytest
    from reachwatch.systems import RandomEnvironments, RandomRunwayRanges
    with pytest.raises(ValueError, match=r"train_random.runway.half_width from 1 m leaves no "
                                         r"room for threshold stripes"):
        RandomEnvironments(count=1, runway=RandomRunwayRanges(half_width=[1.0, 3.0])).validate(
            "train_random")
    RandomEnvironments(count=1, runway=RandomRunwayRanges(
        half_width=[1.0, 3.0], threshold_stripes=[0, 0])).validate("train_random")
