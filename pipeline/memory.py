"""The command line's memory policy: glibc maps every block over 1 MiB on its own and
gives it back to the system when it is freed.

By default glibc raises its mmap threshold to the size of each mapped block freed (up
to 32 MiB), so after the first recorded run's frames (161 frames at 48x80 are 1.9 MB)
are freed, later ones come from its heaps, which it keeps as the heaps fragment. A
monitor study's driver held 16.0 GiB that way where 10.6 GiB sufficed with the
threshold fixed at 1 MiB (measured 2026-12-06 with ``MALLOC_MMAP_THRESHOLD_``: the
monitor-protocol results page). Set here for the process (`mallopt`) and, through the
environment, for the worker processes it starts; a threshold the user set in the
environment is left as it is."""

import ctypes
import os

#: The fixed mmap threshold (bytes).
MMAP_THRESHOLD = 1 << 20
#: glibc's environment variable, read by each process when its allocator starts.
ENVIRONMENT_VARIABLE = "MALLOC_MMAP_THRESHOLD_"
_M_MMAP_THRESHOLD = -3                   # mallopt's parameter number (malloc.h)


def _glibc():
    """glibc, loaded; None elsewhere (musl, macOS, Windows)."""
    try:
        libc = ctypes.CDLL(None)                # this process's C library
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()
        return libc
    except (OSError, AttributeError, TypeError):
        return None


def return_large_blocks() -> bool:
    """Fixes glibc's mmap threshold at `MMAP_THRESHOLD` in this process and in the ones
    it starts (through ``os.environ``, which it changes for good), unless the user set
    a threshold (``MALLOC_MMAP_THRESHOLD_``, or ``glibc.malloc.mmap_threshold`` in
    ``GLIBC_TUNABLES``). True when this call set it."""
    if (ENVIRONMENT_VARIABLE in os.environ
            or "glibc.malloc.mmap_threshold" in os.environ.get("GLIBC_TUNABLES", "")):
        return False
    libc = _glibc()
    if libc is None or libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) != 1:
        return False
    os.environ[ENVIRONMENT_VARIABLE] = str(MMAP_THRESHOLD)
    return True
