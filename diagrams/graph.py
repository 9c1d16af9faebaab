"""Export a Drake diagram's graph as Graphviz ``.dot``, and ``.svg``/``.png`` via ``dot``."""

import shutil
import subprocess
import warnings
from pathlib import Path

from reachwatch.systems.files import atomic_write_bytes

INSTALL_HINT = ("graphviz's 'dot' program is not installed, so only the .dot file was "
                "written; install it with 'apt-get install graphviz' (Debian/Ubuntu) or "
                "'brew install graphviz' (macOS) to get .svg and .png")


class GraphvizMissing(RuntimeError):
    """Raised when an .svg/.png export is asked for and ``dot`` is not on PATH."""


def export_graph(diagram, path, *, formats=("dot", "svg", "png"), max_depth=2,
                 strict=False):
    """Writes ``path`` with each suffix in ``formats``; returns the written paths.

    ``.dot`` needs nothing; ``.svg``/``.png`` need graphviz's ``dot``. Without it those
    are skipped with a warning (or `GraphvizMissing` when ``strict``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dot_text = diagram.GetGraphvizString(max_depth=max_depth)
    written = []
    stem = path.with_suffix("")
    if "dot" in formats:
        target = stem.with_suffix(".dot")
        atomic_write_bytes(target, dot_text.encode())
        written.append(target)
    rendered = [f for f in formats if f != "dot"]
    if rendered and shutil.which("dot") is None:
        if strict:
            raise GraphvizMissing(INSTALL_HINT)
        warnings.warn(INSTALL_HINT, stacklevel=2)
        return written
    for fmt in rendered:
        target = stem.with_suffix(f".{fmt}")
        result = subprocess.run(["dot", f"-T{fmt}"], input=dot_text.encode(),
                                capture_output=True, check=False)
        if result.returncode != 0:
            raise RuntimeError(f"dot -T{fmt} failed: {result.stderr.decode()[:500]}")
        atomic_write_bytes(target, result.stdout)
        written.append(target)
    return written

