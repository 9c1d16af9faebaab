"""What a worker thread keeps between tasks: built loops, probes and renderers, the
few most recently used. A Drake Context is not thread-safe and a VTK/EGL render context
works only on the thread that created it, so each thread builds its own; each holds a
renderer (tens of MB at 200x360), so a thread that runs chunks of many environments or
monitors in turn must not keep them all (a local worker that kept every loop of a
guarded study's 32 environments grew to 11 GB).

Building is serialized across a process's threads
(`reachwatch.diagrams.render_stack.BUILD_LOCK`, which the render-stack probe holds
too): two renderers built at once in one process (VTK over EGL, llvmpipe) do not always draw the same pixels
afterwards. Measured on the taxi's camera (600 states, 2 threads each building a
renderer then rendering them all): 2-10 frames of 600 per thread off, by up to 136
grey levels, against one thread; with only the building under a lock, none in four
threads' 2,400 frames, and rendering itself needs no lock."""

import collections
import gc
import threading

from reachwatch.diagrams.render_stack import BUILD_LOCK


#: Loops or probes a worker thread keeps (the most recently used): each holds a renderer.
KEPT_DIAGRAMS = 4


class ThreadKept:
    """Per thread, the values ``build()`` made for the ``limit`` most recently used
    keys; the least recently used is dropped (and collected) before a new one is
    built."""

    def __init__(self, limit: int):
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"ThreadKept needs a whole number limit >= 1, got {limit!r}")
        self.limit = limit
        self._local = threading.local()

    def kept(self) -> collections.OrderedDict:
        """This thread's values, least recently used first."""
        kept = getattr(self._local, "kept", None)
        if kept is None:
            kept = self._local.kept = collections.OrderedDict()
        return kept

    def get(self, key, build):
        """This thread's value for ``key``, built by ``build()`` on first use, while no
        other thread of the process builds (`BUILD_LOCK`)."""
        kept = self.kept()
        if key not in kept:
            with BUILD_LOCK:
                if len(kept) == self.limit:         # never more: one is added at a time
                    kept.popitem(last=False)
                    # a diagram's systems hold reference cycles: free the dropped one
                    # now, before the new one is built, not at some later collection
                    gc.collect()
                kept[key] = build()
        kept.move_to_end(key)
        return kept[key]
