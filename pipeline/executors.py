"""``--executor`` values: ``local`` (a spawned process pool, one worker per usable
core), ``local:N`` (N workers), ``inline`` (this process), ``dask://HOST:PORT`` (an
existing Dask scheduler; needs the ``distributed`` extra; its workers must have this
process's versions (`reach.fingerprint.distribution_versions`), reachwatch source and
render stack, and may run any number of threads; each task brings the files its
arguments name, `ShippingExecutor`)."""

import contextlib
import importlib.metadata
import logging
import math

from reachwatch.reach import InlineExecutor, default_executor
from reachwatch.reach.fingerprint import (DISTRIBUTIONS, STACK, library_code_digest,
                                          module_versions)
from reachwatch.reach.executors import has_no_workers
from reachwatch.reach.sweep import stop_executor
from reachwatch.systems.checks import clip, short

from .executor_option import check_executor, dask_address, local_workers

_log = logging.getLogger("reachwatch")


def _version(name: str):
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def process_identity() -> dict:
    """This process's versions of `DISTRIBUTIONS` (in every cache key), render stack and
    reachwatch source (`reach.fingerprint.library_code_digest`; cache keys carry parts
    of it): what a worker must share with the driver (`check_worker_versions`, and every
    task on a Dask worker). Read once per process (installed code does not change under
    a running process)."""
    from reachwatch.diagrams.render_stack import render_stack
    return {"versions": dict(STACK), "render": render_stack(), "code": library_code_digest()}


def describe_identity(identity: dict) -> str:
    """`process_identity` in words, on one line."""
    return (f"{_describe(identity['versions'])}, reachwatch source {identity['code'][:12]}, "
            f"renders with {_stack_text(identity['render'])}")


def _describe(versions) -> str:
    return ", ".join(f"{name} {versions.get(name) or 'missing'}" for name in versions)


def _module_versions_here() -> dict:
    return module_versions()


def check_worker_versions(client, spec: str = "dask"):
    """Raise a one-line ValueError when a worker now connected to ``client`` has another
    version of one of `DISTRIBUTIONS`, or of a module `module_versions` reads, than this
    process (or lacks it). The distributions are asked of each worker with
    `importlib.metadata.version` itself, so a worker without reachwatch is reported, not
    an unpickling error; the modules then, of the workers that have reachwatch."""
    mine = {**{name: _version(name) for name in DISTRIBUTIONS}, **_module_versions_here()}
    theirs = {}
    for name in DISTRIBUTIONS:
        answers = client.run(importlib.metadata.version, name, on_error="return")
        for worker, answer in answers.items():
            theirs.setdefault(worker, {})[name] = answer if isinstance(answer, str) else None
    with_reachwatch = [w for w, versions in theirs.items() if versions["reachwatch"]]
    answers = client.run(module_versions, workers=with_reachwatch, on_error="return") \
        if with_reachwatch else {}
    for worker in theirs:
        answer = answers.get(worker)
        theirs[worker].update(answer if isinstance(answer, dict) else
                              {name: None for name in mine if name not in DISTRIBUTIONS})
    for worker, versions in sorted(theirs.items()):
        if versions != mine:
            raise ValueError(f"--executor {spec}: the worker at {worker} has "
                             f"{_describe(versions)}, this process {_describe(mine)}; "
                             f"install the same versions on every worker")
    check_worker_render_stacks(client, spec)


def render_shares(client) -> dict:
    """``{worker address: render threads}``: each host's usable cores shared among the
    threads of all workers on that host (at least 1 each), as the local pool shares
    them (`reachwatch.reach.sweep.render_threads`)."""
    workers = client.scheduler_info(n_workers=-1)["workers"] if _takes_n_workers(client) \
        else client.scheduler_info()["workers"]
    cores = client.run(_usable_cores, on_error="return")
    from distributed.comm import get_address_host

    def host_of(address, info):
        return info.get("host") or get_address_host(address)

    per_host = {}
    for address, info in workers.items():
        host = host_of(address, info)
        per_host[host] = per_host.get(host, 0) + int(info.get("nthreads") or 1)
    shares = {}
    for address, info in workers.items():
        host = host_of(address, info)
        count = cores.get(address)
        count = count if isinstance(count, int) else 1
        shares[address] = max(1, count // max(1, per_host[host]))
    return shares


def _takes_n_workers(client) -> bool:
    import inspect
    return "n_workers" in inspect.signature(client.scheduler_info).parameters


def _usable_cores() -> int:
    from reachwatch.reach.sweep import usable_cores
    return usable_cores()


def _worker_render_stack(render_threads: int) -> dict:
    """A worker's `render_stack` (imported there: the worker's own, whatever this
    process's module holds), its renderer first given ``render_threads`` threads
    unless ``LP_NUM_THREADS`` is set there."""
    from reachwatch.reach.sweep import render_threads as set_render_threads
    set_render_threads(render_threads)
    from reachwatch.diagrams.render_stack import render_stack
    return render_stack()


def _stack_text(stack) -> str:
    libraries = ", ".join(f"{name}{' ' + digest[:8] if digest else ''}"
                          for name, digest in sorted(stack["libraries"].items()))
    return f"probe {stack['probe'][:12]} with {libraries or 'no GL driver seen'}"


def check_worker_render_stacks(client, spec: str = "dask"):
    """Raise a one-line ValueError when a worker now connected to ``client`` renders
    the probe scene (`reachwatch.diagrams.render_stack`) to other pixels, or with other
    GL libraries, than this process: its sweeps and real-loop runs would be cached under
    keys this process computes, for images it would not render."""
    from reachwatch.diagrams.render_stack import render_stack
    mine = render_stack()
    shares = render_shares(client)
    answers = {}
    for share in sorted(set(shares.values())):
        answers.update(client.run(_worker_render_stack, share, on_error="return",
                                  workers=[w for w, s in shares.items() if s == share]))
    for worker, theirs in sorted(answers.items()):
        if not isinstance(theirs, dict):
            raise ValueError(f"--executor {spec}: the worker at {worker} cannot render "
                             f"({short(theirs, 200)}); install Mesa EGL or a GPU driver there")
        if theirs != mine:
            raise ValueError(f"--executor {spec}: the worker at {worker} renders with "
                             f"{_stack_text(theirs)}, this process with {_stack_text(mine)}; "
                             f"run the driver and every worker on the same GL driver")


#: The scheduler setting that queues no task on a busy worker thread; the variable that
#: sets it when the scheduler starts.
SATURATION, SATURATION_VARIABLE = 1.0, "DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION"


def _scheduler_saturation(dask_scheduler=None):
    return float(dask_scheduler.WORKER_SATURATION)


def scheduler_saturation(client):
    """The connected scheduler's ``worker-saturation`` (tasks it sends a worker per
    thread), or None where it cannot say."""
    try:
        return client.run_on_scheduler(_scheduler_saturation)
    except Exception:           # another Dask, a scheduler that does not say: no advice
        return None


def saturation_advice(saturation) -> str:
    """A one-line warning when ``saturation`` lets the scheduler queue chunks on busy
    worker threads, or '' when it does not. Dask's default, 1.1, sends a worker of 8
    threads 9 tasks: at the end of a batch one thread still has a chunk to start while
    others idle (measured: 14 % of a 3.2 s batch of equal tasks at 32 threads, 6 %
    at 1.0; docs/scale.md). Results do not depend on it."""
    if saturation is None or math.isnan(saturation) or saturation <= SATURATION:
        return ""
    return (f"the Dask scheduler has worker-saturation {saturation:g}: it queues chunks on "
            f"busy worker threads, so a batch's last chunks wait while other threads idle; "
            f"start it with {SATURATION_VARIABLE}={SATURATION:g} to send a thread one chunk "
            f"at a time")


def _connect(client_type, address: str, spec: str, timeout: float):
    """A Dask client of the scheduler at ``address``, or a ValueError in one line within
    about ``timeout`` s. A plain TCP connection goes first: a refused port, a host that
    does not resolve or no answer within ``timeout`` is refused at once (Dask retries a
    refused port until its timeout). Dask's own timeout covers the connection, not a
    handshake with a service that is not a scheduler (a web server, the dashboard),
    which can hang or fail in any way; the client is made in a thread that is given up
    after the time and 5 s."""
    import socket
    import threading
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:                        # Dask retries a refused connection until its timeout
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except ConnectionRefusedError:
        raise ValueError(f"--executor {spec}: no Dask scheduler answered at {address}: "
                         f"connection refused (is the scheduler running, on this port?)"
                         ) from None
    except socket.gaierror as e:
        raise ValueError(f"--executor {spec}: cannot resolve the host {short(host)} "
                         f"({clip(e, 120)})") from None
    except OSError as e:        # a timeout, an unreachable network: Dask could not either
        raise ValueError(f"--executor {spec}: no Dask scheduler answered at {address} "
                         f"within {timeout:g} s ({type(e).__name__}: {clip(e, 120)})") from None
    done, out = threading.Event(), {}

    def connect():
        try:
            out["client"] = client_type(address, timeout=f"{timeout}s")
        except BaseException as e:          # delivered to the caller
            out["error"] = e
        done.set()

    threading.Thread(target=connect, name="reachwatch-dask-connect", daemon=True).start()
    hint = ("; the scheduler listens on 8786 by default, its dashboard on 8787"
            if address.endswith(":8787") else "")
    if not done.wait(timeout + 5.0):
        raise ValueError(f"--executor {spec}: something at {address} answered but no Dask "
                         f"scheduler handshake came within {timeout + 5.0:g} s{hint}")
    error = out.get("error")
    if isinstance(error, (OSError, TimeoutError)):
        raise ValueError(f"--executor {spec}: no Dask scheduler answered at {address} "
                         f"within {timeout:g} s ({type(error).__name__}){hint}") from None
    if isinstance(error, Exception):
        raise ValueError(f"--executor {spec}: {address} did not answer as a Dask scheduler "
                         f"({type(error).__name__}: {clip(error, 200)}){hint}") from None
    if error is not None:
        raise error
    return out["client"]


def make_executor(spec: str, *, connect_timeout: float = 10.0):
    """An executor and a ``close(abort=False)`` callable for ``spec``; ``abort`` stops
    local workers at once instead of letting their current chunk finish."""
    check_executor(spec)
    if spec == "local" or spec.startswith("local:"):
        executor = default_executor(local_workers(spec))
        return executor, lambda abort=False: stop_executor(executor, abort=abort)
    if spec == "inline":
        return InlineExecutor(), lambda abort=False: None
    if spec.startswith("dask://") or spec.startswith("tcp://"):
        try:
            from dask.distributed import Client
        except ImportError:
            raise ValueError("--executor dask://... needs dask: pip install "
                             "'reachwatch[distributed]'") from None
        address = "tcp://" + dask_address(spec)
        from .shipping_executor import ShippingExecutor
        client = _connect(Client, address, spec, connect_timeout)
        try:
            check_worker_versions(client, spec)
        except BaseException:
            client.close()
            raise
        executor = ShippingExecutor(client)
        if has_no_workers(executor):
            _log.warning("--executor %s: the scheduler has no workers yet: the run's chunks "
                         "wait until one joins (dask worker %s), and a stage that sends "
                         "files to the cluster stops after Dask's timeout", spec, address)
        advice = saturation_advice(scheduler_saturation(client))
        if advice:
            _log.warning("--executor %s: %s", spec, advice)
        return executor, lambda abort=False: client.close()
    raise AssertionError(spec)                  # check_executor knows no other form


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
