"""What a worker thread keeps between tasks: the few most recently used loops, each
thread its own."""

import threading

import pytest

from reachwatch.reach.thread_kept import KEPT_DIAGRAMS, ThreadKept


def test_the_least_recently_used_is_dropped_before_a_new_one_is_built():
    built, kept = [], ThreadKept(2)

    def build(key):
        assert len(kept.kept()) < 2         # never more than the limit, even while building
        built.append(key)
        return key.upper()
    assert kept.get("a", lambda: build("a")) == "A"
    assert kept.get("b", lambda: build("b")) == "B"
    assert kept.get("a", lambda: build("a")) == "A"     # kept: not built again
    assert kept.get("c", lambda: build("c")) == "C"     # drops b, the least recently used
    assert list(kept.kept()) == ["a", "c"] and built == ["a", "b", "c"]
    assert kept.get("b", lambda: build("b")) == "B" and built[-1] == "b"


def test_each_thread_builds_its_own():
    kept, seen = ThreadKept(KEPT_DIAGRAMS), []
    here = kept.get("loop", object)
    worker = threading.Thread(target=lambda: seen.append(kept.get("loop", object)))
    worker.start()
    worker.join()
    assert seen[0] is not here and kept.get("loop", object) is here


def test_a_limit_below_one_is_refused():
    with pytest.raises(ValueError, match="limit >= 1, got 0"):
        ThreadKept(0)


def test_a_dropped_value_in_a_reference_cycle_is_freed_before_the_next_is_built():
    import weakref

    class Loop:                     # a diagram's systems refer to each other
        def __init__(self):
            self.me = self
    kept, freed = ThreadKept(1), []
    first = weakref.ref(kept.get("a", Loop))
    kept.get("b", lambda: freed.append(first() is None) or Loop())
    assert freed == [True]


def test_no_two_threads_of_a_process_build_at_once():
    """Two renderers built at once in one process do not always draw the same pixels
    afterwards: the builds of all threads (each its own `ThreadKept` or not) take turns,
    while what is kept is used freely."""
    import time
    kept, other, building, overlap = ThreadKept(1), ThreadKept(1), [], []

    def build():
        building.append(1)
        overlap.append(len(building))
        time.sleep(0.05)
        building.pop()
        return object()

    threads = [threading.Thread(target=lambda k=k: [k.get(key, build) for key in "abc"])
               for k in (kept, other, kept)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(overlap) == 9 and max(overlap) == 1
