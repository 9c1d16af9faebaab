"""The ``--executor`` option, defined once for every subcommand that runs chunks, and
its check, which needs no worker, scheduler, drake or torch: a malformed value is
refused by argparse in one line before a run file or scenario is loaded. Making the
executor (starting a pool, connecting to a scheduler) is `pipeline.executors`'s."""

import argparse
import re


def short(spec: str) -> str:
    """``spec`` as an error message shows it: quoted, cut to 60 characters (as
    `reachwatch.systems.checks.short`, whose package would import drake and OpenCV)."""
    return repr(spec if len(spec) <= 60 else spec[:28] + "..." + spec[-28:])


#: The most local workers ``local:N`` may start (each is a process with its renderer).
MAX_WORKERS = 256

#: ``HOST:PORT`` of a Dask scheduler: a host name or IPv4 address, or an IPv6 one in
#: brackets, and a port.
_ADDRESS = re.compile(r"(?:[A-Za-z0-9_.-]{1,253}|\[[0-9A-Fa-f:.]{2,45}\]):[0-9]{1,5}")

HELP = ("local (one worker per core) | local:N | inline | dask://HOST:PORT (a Dask "
        "scheduler; its workers get the files each task names with it and return results, "
        "so they need neither the run directory nor this machine's paths)")


def dask_address(spec: str) -> str:
    """The ``HOST:PORT`` of ``--executor dask://HOST:PORT`` (or ``tcp://``); a one-line
    ValueError for anything else, before a client is made (dask would answer a bad
    address with its own words, or a connection attempt)."""
    address = spec.split("://", 1)[1]
    if not _ADDRESS.fullmatch(address) or not 1 <= int(address.rpartition(":")[2]) <= 65535:
        raise ValueError(f"--executor dask://HOST:PORT needs a host and a port in [1, 65535] "
                         f"(an IPv6 host in brackets), got {short(spec)}")
    return address


def local_workers(spec: str):
    """The N of ``local:N`` (None for ``local``: one worker per usable core)."""
    count = spec.partition(":")[2]
    if count and not (count.isascii() and count.isdigit() and len(count) <= 6
                      and 1 <= int(count) <= MAX_WORKERS):
        raise ValueError(f"--executor local:N needs a whole number of workers N in "
                         f"[1, {MAX_WORKERS}], got {short(spec)}")
    return int(count) if count else None


def check_executor(spec: str) -> str:
    """``spec`` if it is a well-formed ``--executor`` value, else a one-line ValueError
    that names the forms."""
    if spec == "local" or spec.startswith("local:"):
        local_workers(spec)
    elif spec.startswith(("dask://", "tcp://")):
        dask_address(spec)
    elif spec != "inline":
        raise ValueError(f"--executor must be local, local:N, inline or dask://HOST:PORT, "
                         f"got {short(spec)}")
    return spec


def _executor_type(text: str) -> str:
    try:
        return check_executor(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--executor ")) from None


_executor_type.__name__ = "executor"


def add_executor_argument(parser, *, default: str = "local"):
    """``--executor`` on ``parser`` (its default ``default``), checked as it is parsed."""
    parser.add_argument("--executor", default=default, type=_executor_type,
                        help=f"{HELP} (default: {default})")
