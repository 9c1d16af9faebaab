"""Checks of user input shared by the schemas: short reprs of offending values (an
error message never prints a whole value) and names that become file names."""

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


def is_file(path) -> bool:
    """Whether ``path`` names a regular file; False, not an error, for a name the system
    refuses (too long, a NUL byte)."""
    from pathlib import Path
    try:
        return Path(path).is_file()
    except (OSError, ValueError):
        return False
