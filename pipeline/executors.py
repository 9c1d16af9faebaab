"""``--executor`` values: ``local`` (a spawned process pool, one worker per usable
core), ``local:N`` (N workers), ``inline`` (this process), ``dask://HOST:PORT`` (an
existing Dask scheduler; needs the ``distributed`` extra)."""

import contextlib

from reachwatch.reach import InlineExecutor, default_executor
from reachwatch.reach.sweep import stop_executor
from reachwatch.systems.checks import short

#: The most local workers ``local:N`` may start (each is a process with its renderer).
MAX_WORKERS = 256


def make_executor(spec: str, *, connect_timeout: float = 10.0):
    """An executor and a ``close(abort=False)`` callable for ``spec``; ``abort`` stops
    local workers at once instead of letting their current chunk finish."""
    if spec == "local" or spec.startswith("local:"):
        count = spec.partition(":")[2]
        if count and not (count.isascii() and count.isdigit() and len(count) <= 6
                          and 1 <= int(count) <= MAX_WORKERS):
            raise ValueError(f"--executor local:N needs a whole number of workers N in "
                             f"[1, {MAX_WORKERS}], got {short(spec)}")
        executor = default_executor(int(count) if count else None)
        return executor, lambda abort=False: stop_executor(executor, abort=abort)
    if spec == "inline":
        return InlineExecutor(), lambda abort=False: None
    if spec.startswith("dask://") or spec.startswith("tcp://"):
        try:
            from dask.distributed import Client
        except ImportError:
            raise ValueError("--executor dask://... needs dask: pip install "
                             "'reachwatch[distributed]'") from None
        address = "tcp://" + spec.split("://", 1)[1]
        try:
            client = Client(address, timeout=f"{connect_timeout}s")
        except (OSError, TimeoutError) as e:
            raise ValueError(f"--executor {spec}: no Dask scheduler answered at {address} "
                             f"within {connect_timeout:g} s ({type(e).__name__})") from None
        return client.get_executor(), lambda abort=False: client.close()
    raise ValueError(f"--executor must be local, local:N, inline or dask://HOST:PORT, got "
                     f"{short(spec)}")


@contextlib.contextmanager
def open_executor(spec: str, **kwargs):
    """``with open_executor("local") as executor:`` closes it on the way out, and on an
    error or interrupt stops its workers at once."""
    executor, close = make_executor(spec, **kwargs)
    try:
        yield executor
    except BaseException:
        close(abort=True)
        raise
    close()
