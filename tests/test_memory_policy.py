"""The command line's memory policy (`pipeline.memory`): glibc's mmap threshold fixed,
so a freed large array goes back to the system instead of staying in a heap."""

import os
import subprocess
import sys
import textwrap

import pytest

from reachwatch.pipeline import memory

# Runs in a fresh process: frees a 1.5 MB array, then holds a 1.2 MB one and prints
# whether glibc mapped it on its own (hblkhd: bytes in mapped blocks) and the variable
# its children would see.
PROBE = textwrap.dedent("""
    import ctypes, os, sys
    from reachwatch.pipeline.memory import return_large_blocks
    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                    "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
    libc = ctypes.CDLL(None)
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    set_here = return_large_blocks() if sys.argv[1] == "set" else None
    libc.free(libc.malloc(1_500_000))          # glibc raises its threshold past 1.2 MB here
    before = libc.mallinfo2().hblkhd
    held = libc.malloc(1_200_000)
    print(set_here, libc.mallinfo2().hblkhd - before >= 1_200_000,
          os.environ.get("MALLOC_MMAP_THRESHOLD_"))
    libc.free(held)
""")


def _probe(mode, **environment):
    env = {k: v for k, v in os.environ.items() if k != memory.ENVIRONMENT_VARIABLE}
    env.update(environment)
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True,
                         text=True, check=True)
    return out.stdout.split()


@pytest.mark.skipif(memory._glibc() is None or not hasattr(memory._glibc(), "mallinfo2"),
                    reason="glibc >= 2.33 only")
def test_a_freed_large_block_is_not_kept_for_the_next():
    # glibc's default: after the free, the 1.2 MB block comes from the heap
    assert _probe("unset") == ["None", "False", "None"]
    # fixed: mapped on its own, and the children are told the same
    assert _probe("set") == ["True", "True", str(memory.MMAP_THRESHOLD)]
    # the user's own value stands (and glibc read it at start: 2 MB, so heap again)
    assert _probe("set", MALLOC_MMAP_THRESHOLD_="2000000") == ["False", "False", "2000000"]
    assert _probe("set", GLIBC_TUNABLES="glibc.malloc.mmap_threshold=2000000") == [
        "False", "False", "None"]
