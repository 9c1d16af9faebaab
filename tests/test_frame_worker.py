"""`FrameWorker`: a frame's work in a process of its own gives the answer the work gives
here, for exactly the pixels begun, and a process that fails or ends hands the work back
to the caller, said once; a history monitor whose encoder runs so outputs the same
scores, bit for bit, as one that encodes in the loop, and so does a single-image
detector."""

import functools
import gc
import signal
import logging

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario, make_guarded_diagram, simulate
from reachwatch.systems import HistoryMonitorConfig
from reachwatch.systems import checks
from reachwatch.systems.frame_worker import FrameWorker
from reachwatch.taxi import OffRunway
from test_history_monitor import _checkpoint


@pytest.fixture
def said():
    checks.WARNED.clear()
    seen = []
    handler = logging.Handler()
    handler.emit = lambda record: seen.append(record.getMessage())
    logger = logging.getLogger("reachwatch")
    logger.addHandler(handler)
    yield seen
    logger.removeHandler(handler)


def _frames(count, shape=(6, 10, 4), seed=0):
    return np.random.default_rng(seed).integers(0, 256, (count, *shape), dtype=np.uint8)


def test_the_answer_is_the_works_own_for_exactly_the_pixels_begun(said):
    work = functools.partial(np.multiply, 0.5)
    worker = FrameWorker(work, name="test")
    try:
        first, second = _frames(2)
        assert worker.result(first) is None                      # nothing begun
        assert worker._process is None                           # nor started
        assert worker.start(wait=300)                             # loaded: takes frames
        worker.begin(first)
        assert worker.result(second) is None                     # other pixels
        answer = worker.result(first)
        assert answer.dtype == np.float64
        np.testing.assert_array_equal(answer, work(first))
        assert worker.result(first) is None                      # answered once
        worker.begin(first)
        worker.begin(second)                 # the first's answer read and dropped
        np.testing.assert_array_equal(worker.result(second), work(second))
        larger = _frames(1, (8, 12, 4), seed=1)[0]                # another size: remapped
        worker.begin(larger)
        np.testing.assert_array_equal(worker.result(larger), work(larger))
        assert worker.answered == 3 and worker.alive and not said
    finally:
        worker.close()
    assert worker._process.poll() is not None                    # closed: ended
    worker.begin(first)
    assert worker.result(first) is None


def test_a_work_that_fails_or_a_process_that_ends_hands_the_frames_back(said):
    failing = FrameWorker(functools.partial(np.take, indices=10 ** 9), name="failing work")
    frame = _frames(1)[0]
    assert failing.start(wait=300)
    failing.begin(frame)
    assert failing.result(frame) is None and not failing.alive
    assert len(said) == 1 and said[0].startswith("failing work: its frame work failed in its "
                                                 "own process (IndexError: ")
    assert failing._process.wait(timeout=30) == 0                 # given up: ended
    failing.begin(frame)                                          # asked no more, said once
    assert failing.result(frame) is None and len(said) == 1
    ended = FrameWorker(functools.partial(np.multiply, 2.0), name="killed")
    assert ended.start(wait=300)
    ended.begin(frame)
    assert ended.result(frame) is not None
    ended._process.kill()
    ended._process.wait()
    ended.begin(frame)
    assert ended.result(frame) is None and not ended.alive
    assert any(m.startswith("killed: its frame work's own process ended (") for m in said)


def test_an_interrupt_midway_ends_the_process_and_a_work_that_cannot_go_is_refused(said):
    """An answer left on its way would put every later answer one frame behind: an
    interrupt while one is read gives the process up, and the frames come back."""
    worker = FrameWorker(functools.partial(np.multiply, 3.0), name="interrupted")
    frame = _frames(1)[0]
    assert worker.start(wait=300)
    worker.begin(frame)

    def interrupted():
        raise KeyboardInterrupt
    worker._conn.recv = interrupted
    with pytest.raises(KeyboardInterrupt):
        worker.result(frame)
    assert not worker.alive and worker._process.wait(timeout=30) == -signal.SIGKILL
    worker.begin(frame)
    assert worker.result(frame) is None and not said         # the interrupt is the caller's
    with pytest.raises(TypeError, match=r"^unpicklable: its frame work cannot go to a "
                                        r"process of its own: "):
        FrameWorker(lambda frame: frame, name="unpicklable")


def _refuse():
    raise RuntimeError("not in this process")


class _Unloadable:
    """Pickles here; unpickling it raises (in the worker's process)."""

    def __reduce__(self):
        return _refuse, ()


def test_a_frame_before_the_process_is_ready_is_the_callers_and_a_work_it_cannot_load_is_said(
        said):
    worker = FrameWorker(functools.partial(np.multiply, 3.0), name="slow start")
    frame = _frames(1)[0]
    worker.begin(frame)                  # starts it; loading takes seconds: no tick waits
    assert worker._process is not None and worker.result(frame) is None
    assert worker.start(wait=300) and worker.answered == 0
    worker.close()
    unloadable = FrameWorker(_Unloadable(), name="unloadable")
    assert not unloadable.start(wait=300) and not unloadable.alive
    assert said == ["unloadable: its frame work failed in its own process (loading the work: "
                    "RuntimeError: not in this process); frames are worked in the loop from "
                    "now on"]
    assert unloadable._process.wait(timeout=30) == 0


@pytest.mark.parametrize("temporal, frames, signals", [("stack", 3, 0), ("gru", 4, 3)])
def test_a_history_monitor_encoding_in_its_own_process_gives_the_same_scores(
        tmp_path, temporal, frames, signals):
    config = HistoryMonitorConfig(frames=frames, stride=1, height=24, width=40,
                                  channels=[4, 8], features=6, temporal=temporal, hidden=8,
                                  signals=signals, signal_mean=[0.1] * signals,
                                  signal_std=[2.0] * signals)
    path = _checkpoint(tmp_path / "monitor.pt", config)
    scores = {}
    for own in (False, True):
        scenario = load_scenario(data=f"monitor: "
                                      f"{{detector: {path}, threshold: 0.5, "
                                      f"encoder_process: {str(own).lower()}}}\n")
        diagram = make_guarded_diagram(scenario)
        if own:                                 # ready before the run's first frame
            assert diagram.GetSubsystemByName("anomaly_detector").frame_worker.start(wait=300)
        run = simulate(diagram, initial_state=[2.0, 120.0, 0.1], duration=0.6, period=0.05,
                       failed=OffRunway(scenario.environment.half_width))
        scores[own] = run.score
        worker = diagram.GetSubsystemByName("anomaly_detector").frame_worker
        assert (worker is None) == (not own)
        if own:     # every tick's row came from the process (the last, after the run: not read)
            assert worker.answered >= len(run.score) - 1 and worker.alive
            process = worker._process
    assert len(scores[True]) == 13 and np.ptp(scores[True]) > 1e-6
    np.testing.assert_array_equal(scores[True], scores[False])
    del diagram, worker, run                # the loop let go: its process ends with it
    gc.collect()
    assert process.wait(timeout=30) == 0


def test_an_ensembles_encoders_give_the_same_features_in_their_own_process():
    import torch
    from reachwatch.systems import FrameEncoder, HistoryRiskModel
    from reachwatch.systems.detector import inference_model
    config = HistoryMonitorConfig(frames=1, height=24, width=40, channels=[4, 8], features=6)
    torch.manual_seed(0)
    encode = FrameEncoder([inference_model(HistoryRiskModel(config).eval()) for _ in range(2)],
                          config.image_config)
    worker = FrameWorker(encode, name="ensemble")
    assert worker.start(wait=300)
    try:
        for frame in _frames(3, (50, 90, 4)):
            worker.begin(frame)
            answer = worker.result(frame)
            assert answer.shape == (12,)
            np.testing.assert_array_equal(answer, encode(frame))
    finally:
        worker.close()


def test_a_single_image_detector_scores_the_same_in_its_own_process(tmp_path):
    """Its own process scores on one thread, and so does the loop when the process does
    not answer: the same numbers bit for bit; the loop without the option scores on
    torch's count, the same up to rounding."""
    import torch
    from reachwatch.diagrams import save_checkpoint
    from reachwatch.systems import DetectorConfig, build_detector
    path = tmp_path / "detector.pt"
    config = DetectorConfig(height=24, width=40)
    torch.manual_seed(0)
    save_checkpoint(path, kind="detector", model=build_detector(config), model_config=config,
                    preprocess_config=None, metadata={"threshold": 0.5})
    scores = {}
    for case in ("own process", "its process closed", "in the loop"):
        own = case != "in the loop"
        scenario = load_scenario(data=f"monitor: {{detector: {path}, threshold: 1.0, "
                                      f"encoder_process: {str(own).lower()}}}\n")
        diagram = make_guarded_diagram(scenario)
        worker = diagram.GetSubsystemByName("anomaly_detector").frame_worker
        assert (worker is None) == (not own)
        in_loop = []                  # frames the loop scored itself (the process has its copy)
        if own:
            score = worker._local
            worker._local = lambda rgba: in_loop.append(1) or score(rgba)
        if case == "own process":
            assert worker.start(wait=300)
        elif own:
            worker.close()
        scores[case] = simulate(diagram, initial_state=[2.0, 120.0, 0.1], duration=0.3,
                                period=0.05,
                                failed=OffRunway(scenario.environment.half_width)).score
        if case == "own process":     # every tick's score from the process
            assert worker.answered >= len(scores[case]) - 1 and len(in_loop) <= 1
        elif own:
            assert len(in_loop) == len(scores[case])
    assert len(scores["own process"]) == 7 and np.ptp(scores["own process"]) > 1e-9
    np.testing.assert_array_equal(scores["own process"], scores["its process closed"])
    np.testing.assert_allclose(scores["own process"], scores["in the loop"], rtol=1e-6)
