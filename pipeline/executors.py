"""``--executor`` values: ``local`` (a spawned process pool), ``inline`` (this
process), ``dask://HOST:PORT`` (an existing Dask scheduler; needs the
``distributed`` extra)."""

from reachwatch.reach import InlineExecutor, default_executor


def make_executor(spec: str):
    """An executor and a ``close()`` callable for ``spec``."""
    if spec == "local":
        executor = default_executor()
        return executor, executor.shutdown
    if spec == "inline":
        return InlineExecutor(), lambda: None
    if spec.startswith("dask://") or spec.startswith("tcp://"):
        try:
            from dask.distributed import Client
        except ImportError:
            raise ValueError("--executor dask://... needs dask: pip install "
                             "'reachwatch[distributed]'") from None
        address = "tcp://" + spec.split("://", 1)[1]
        client = Client(address, timeout=30)
        return client.get_executor(), client.close
    raise ValueError(f"--executor must be local, inline or dask://HOST:PORT, got '{spec}'")
