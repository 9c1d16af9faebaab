"""Checks of user input shared by the schemas: short reprs of offending values (an
error message never prints a whole value), names that become file names, and
one-line warnings given once (`warn_once`)."""

import logging
import re
import reprlib

_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 60
_repr.maxlist = _repr.maxtuple = _repr.maxdict = _repr.maxset = 6
_repr.maxlevel = 3

#: How long a repr in an error message may be (characters).
SHORT = 80


def short(value, limit: int = SHORT) -> str:
    """``repr(value)`` cut to about ``limit`` characters (without building the whole
    repr of a huge value)."""
    text = _repr.repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


#: The warnings `warn_once` has given in this process.
WARNED = set()


def warn_once(message: str, key=None) -> None:
    """``message`` as a one-line warning on the ``reachwatch`` logger, once a process per
    ``key`` (None: the message itself), e.g. a run file validated more than once: one
    warning, not one a validation."""
    key = message if key is None else key
    if key not in WARNED:
        WARNED.add(key)
        logging.getLogger("reachwatch").warning(message)


def clip(message, limit: int = 600) -> str:
    """``message`` on one line, cut to ``limit`` characters."""
    text = " ".join(str(message).splitlines())
    return text if len(text) <= limit else text[:limit - 3] + "..."


#: Characters a name that becomes part of a file name may hold.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")
MAX_NAME = 64


def check_name(where: str, name) -> str:
    """``name`` if it is safe as (part of) a file name: 1 to `MAX_NAME` of the characters
    A-Z a-z 0-9 _ . -, not starting with a dot; else a ValueError naming ``where``."""
    if not (isinstance(name, str) and len(name) <= MAX_NAME and NAME_PATTERN.fullmatch(name)):
        raise ValueError(f"{where} must be 1 to {MAX_NAME} of the characters A-Z a-z 0-9 _ . - "
                         f"(not starting with a dot; it names files), got {short(name)}")
    return name


#: How long a name that only labels things (a run's, a monitor variant's) may be.
MAX_LABEL = 200


def check_label(where: str, text) -> str:
    """``text`` if it can title a report and label a table row: 1 to `MAX_LABEL`
    printable characters (no newline, tab or other control or format character); else
    a ValueError naming ``where``."""
    if not (isinstance(text, str) and 1 <= len(text) <= MAX_LABEL and text.isprintable()):
        raise ValueError(f"{where} must be 1 to {MAX_LABEL} printable characters on one line "
                         f"(it labels the report), got {short(text)}")
    return text


def is_file(path) -> bool:
    """Whether ``path`` names a regular file; False, not an error, for a name the system
    refuses (too long, a NUL byte)."""
    from pathlib import Path

    from .files import local_copy      # a file that came with the running task
    try:
        return Path(local_copy(path)).is_file()
    except (OSError, ValueError):
        return False


def torch_device(name=None):
    """The `torch.device` ``name`` names; empty or None: CUDA when present, else the CPU
    (what a BRT solve and a detector's training use unless told)."""
    import torch
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def device_kind(name=None) -> str:
    """``"cpu"``, ``"cuda"``, ...: the kind of `torch_device` ``name`` (for cache keys: a
    result computed on another kind of device differs in its last digits, or more)."""
    return torch_device(name).type


def check_torch_device(where: str, name) -> str:
    """``name`` if torch can compute on it here (empty: CUDA when present, else the CPU);
    else a ValueError naming ``where``: a device that is not one, or a CUDA (or MPS)
    device this machine does not have, is refused before any work, not at training."""
    import torch
    try:
        device = torch.device(name or "cpu")
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"{where} must be a torch device such as cpu, cuda or cuda:1 (or "
                         f"empty for CUDA when present), got {short(name)}") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            have = f"has {count} CUDA device{'s' * (count != 1)}" if count else "has no CUDA device"
            raise ValueError(f"{where} is {short(name)}, and this machine {have}; use cpu, or "
                             f"leave it empty for CUDA when present")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{where} is {short(name)}, and MPS is not available here; use cpu")
    return name
