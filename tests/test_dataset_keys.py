"""A dataset's folder is keyed by everything its images depend on: the camera's
placement and the shadows too, not only the image size (a loop whose BRT ignores the
camera, such as the privileged oracle's, would otherwise reuse images of another view)."""

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.reach import ValueFunction
from reachwatch.taxi import paper_grid
from reachwatch.training.dataset import KEYED_VIEW, DatasetSpec, camera_view, dataset_folder
from reachwatch.taxi.application import TAXI_APPLICATION
from tiny_run import taxi_application


@pytest.fixture(scope="module")
def value_function():
    grid = paper_grid(10.0, (3, 3, 3))
    return ValueFunction(grid, np.linspace(-1.0, 1.0, grid.size).reshape(grid.shape), 2.0,
                         "test")


def _folder(tmp_path, value_function, text=""):
    return dataset_folder(tmp_path, load_scenario(data=text), value_function, DatasetSpec(), application=taxi_application())


@pytest.mark.parametrize("text", [
    "camera: {fov_x_deg: 60.0}\n", "camera: {pitch_down_deg: 12.0}\n",
    "camera: {right: 1.0, up: 0.8}\n", "camera: {near: 0.2}\n", "shadows: true\n"])
def test_a_camera_placed_otherwise_or_shadows_key_another_dataset(tmp_path, value_function,
                                                                   text):
    assert _folder(tmp_path, value_function, text) != _folder(tmp_path, value_function)


def test_the_default_view_keys_nothing_new_and_the_loop_settings_leave_the_key(
        tmp_path, value_function):
    """The default camera adds nothing to the key (datasets built before it held the
    view keep their folders); the start, duration and monitor change no image."""
    assert camera_view(load_scenario(data="")) == {}
    assert set(KEYED_VIEW) == set(camera_view(load_scenario(data=(
        "camera: {fov_x_deg: 61, right: 1, up: 1, forward: 1, reference_height: 1, "
        "yaw_out_deg: 1, pitch_down_deg: 1, near: 0.1, far: 100}\nshadows: true\n"))))
    same = ("camera: {fov_x_deg: 80.0}\n", "duration: 3.0\nseed: 4\n",
            "initial_state: {py: 200.0}\n", "monitor: {threshold: 0.7}\n")
    assert {_folder(tmp_path, value_function, t) for t in same} == {
        _folder(tmp_path, value_function)}


def test_the_taxis_dataset_images_are_what_its_loops_camera_sees_shadows_included():
    """The taxi's dataset renderer (a StateRenderer, for speed) renders the pixels of
    the closed loop's own camera (the generic renderer): shadows too, so that a
    detector trained on a run with ``shadows: true`` sees the shadows it will see."""
    from reachwatch.reach.application import Application, load_application
    taxi = load_application(TAXI_APPLICATION)
    scenario = taxi.resolved(load_scenario(data="camera: {width: 64, height: 32}\n"
                                                "shadows: true\nenvironment: {hour: 17.0}\n"))
    state = np.array([1.0, 150.0, 0.1])
    np.testing.assert_array_equal(taxi.renderer(scenario).render(state),
                                  Application.renderer(taxi, scenario).render(state))


def test_a_datasets_states_draw_from_streams_no_environment_or_study_start_uses():
    """With one seed for the dataset, the random family and the monitor study (0 each by
    default), the dataset's uniform states and path starts share random numbers with no
    environment's draw and no study start (until dataset format 4 they were
    environment 0's and environment 1's)."""
    import dataclasses as dc

    from reachwatch.pipeline.monitor_study import starts_seed
    from reachwatch.pipeline.monitor_spec import MonitorStudySpec
    from reachwatch.systems.random_environments import MAX_COUNT
    from reachwatch.training.dataset import PATHS_STREAM, STATES_STREAM
    spec = MonitorStudySpec()
    spec = dc.replace(spec, family=dc.replace(spec.family, seed=0))
    state = lambda seed: tuple(np.random.SeedSequence(seed).generate_state(4))   # noqa: E731
    others = {state([0, i]) for i in range(MAX_COUNT)}
    others |= {state(starts_seed(spec, i)) for i in range(MAX_COUNT)}
    ours = {state([0, *PATHS_STREAM]), state([0, *STATES_STREAM])}
    assert len(others) == 2 * MAX_COUNT and len(ours) == 2 and not ours & others
    assert {state([0, 1]), state(0)} <= others      # the streams of before: environments 1, 0


def test_real_loop_labels_key_the_brts_horizon_and_grid(tmp_path, value_function):
    """A converged BRT solved for a longer horizon can hold the same values; labels the
    real loop gives, run for that horizon, are other labels: another folder. BRT labels
    read the values alone and keep theirs."""
    from reachwatch.training.labels import LabelSpec
    longer = ValueFunction(value_function.grid, value_function.values, 4.0, "test")
    scenario = load_scenario(data="")
    for source in ("rollout", "hybrid"):
        spec = DatasetSpec(labels=LabelSpec(source))
        assert dataset_folder(tmp_path, scenario, value_function, spec, application=taxi_application()) != \
            dataset_folder(tmp_path, scenario, longer, spec, application=taxi_application())
    assert dataset_folder(tmp_path, scenario, value_function, DatasetSpec(), application=taxi_application()) == \
        dataset_folder(tmp_path, scenario, longer, DatasetSpec(), application=taxi_application())
