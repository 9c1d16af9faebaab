"""What the command line prints: `logging` to stdout (through tqdm, so progress bars
stay intact), ``-q`` / ``-v`` levels, progress bars off when quiet, and Python
warnings as one ``warning: ...`` line each."""

import logging
import sys
import warnings

from tqdm import tqdm

log = logging.getLogger("reachwatch")
_state = {"progress": True}


class _TqdmHandler(logging.Handler):
    def emit(self, record):
        try:
            message = self.format(record)
            tqdm.write(message, file=sys.stderr if record.levelno >= logging.WARNING else sys.stdout)
        except Exception:   # noqa: BLE001  (logging's own convention)
            self.handleError(record)


class _Formatter(logging.Formatter):
    def format(self, record):
        text = record.getMessage()
        if record.levelno >= logging.WARNING and not text.startswith(("warning:", "error:")):
            text = f"{record.levelname.lower()}: {text}"
        return text


def _warning_line(message, category, filename, lineno, file=None, line=None):
    log.warning(f"warning: {message}")


def setup(verbosity: int = 0):
    """``verbosity`` -1 (quiet: warnings and errors only, no bars), 0, or 1 (debug)."""
    level = {-1: logging.WARNING, 0: logging.INFO}.get(verbosity, logging.DEBUG)
    handler = _TqdmHandler()
    handler.setFormatter(_Formatter())
    log.handlers[:] = [handler]
    log.setLevel(level)
    log.propagate = False
    _state["progress"] = verbosity >= 0
    warnings.showwarning = _warning_line


def progress_enabled() -> bool:
    return _state["progress"]


def bar(iterable=None, **kwargs):
    """A tqdm bar that is off when quiet."""
    return tqdm(iterable, disable=not _state["progress"], **kwargs)
