"""torch's intra-op thread count for a block of work, safe when blocks run in several
threads at once (a worker runs several loops on threads of its own)."""

import contextlib
import threading

import torch

_LOCK = threading.Lock()
_HELD = {"blocks": 0, "count": None, "before": None}


@contextlib.contextmanager
def torch_threads(count: int):
    """Runs the block with torch on ``count`` intra-op threads (0: as it is), and gives
    back the count it found when the last block running, in any thread, ends. The count
    is process-wide: blocks that each saved and restored it could leave the process on
    another's count for good (A saves 2 and sets 1, B saves 1, A restores 2, B restores
    1). Blocks that overlap must ask the same count (a RuntimeError otherwise)."""
    if not count:
        yield
        return
    with _LOCK:
        if _HELD["blocks"] == 0:
            _HELD["before"], _HELD["count"] = torch.get_num_threads(), int(count)
            if _HELD["before"] != _HELD["count"]:
                torch.set_num_threads(_HELD["count"])
        elif _HELD["count"] != count:
            raise RuntimeError(f"torch_threads({count}) while another block runs torch on "
                               f"{_HELD['count']} threads")
        _HELD["blocks"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _HELD["blocks"] -= 1
            if _HELD["blocks"] == 0 and _HELD["before"] != _HELD["count"]:
                torch.set_num_threads(_HELD["before"])


@contextlib.contextmanager
def one_torch_thread():
    """Runs the block in torch's inference mode on one intra-op thread, then gives the
    caller's thread count back (`torch_threads`). A monitor's per-frame network is a few
    small layers: a second thread saves little there and costs a wake-up and a wait per
    layer; on a loaded machine the wait runs to milliseconds when that thread is not
    scheduled."""
    with torch_threads(1), torch.inference_mode():
        yield
