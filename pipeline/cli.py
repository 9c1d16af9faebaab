"""The ``reachwatch`` command line.

Building the parser (and so ``--help`` and a refused argument) imports neither drake
nor torch: the subcommand modules import those inside the functions that run a
command, and `main` imports `reachwatch.systems` (its process-wide settings first)
only once the arguments are parsed."""

import argparse
import importlib.metadata
import os
import signal
import sys
import threading
import time

from .memory import return_large_blocks
from .overlays import add_overlay_arguments
from . import (commands, console, evaluate_commands, graph_commands, guard_commands,
               reach_commands, run_commands, simulate_commands, taxinet_commands)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reachwatch",
        description="Find, detect and mitigate system-level failures of vision-based "
                    "controllers (Drake + HJ reachability).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    noise = parser.add_mutually_exclusive_group()
    noise.add_argument("-v", "--verbose", action="store_true", help="debug messages too")
    noise.add_argument("-q", "--quiet", action="store_true",
                       help="warnings and errors only; no progress bars")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    render = sub.add_parser("render", help="render the wing-camera image of a scenario, "
                            "or a contact sheet of every environment")
    render.add_argument("--scenario", help="scenario YAML (default: built-in defaults)")
    add_overlay_arguments(render)
    render.add_argument("--out", required=True, help="output folder")
    render.add_argument("--contact-sheet", action="store_true",
                        help="render all 5 runways x hours 9, 17, 21 x clear/overcast "
                             "at the scenario's state into one PNG")
    render.set_defaults(func=commands.render)

    graph_commands.add_parsers(sub)
    taxinet_commands.add_parsers(sub)
    simulate_commands.add_parsers(sub)
    reach_commands.add_parsers(sub)
    evaluate_commands.add_parsers(sub)
    guard_commands.add_parsers(sub)
    run_commands.add_parsers(sub)
    return parser


def version() -> str:
    try:
        return importlib.metadata.version("reachwatch")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


class Terminated(KeyboardInterrupt):
    """SIGTERM (what ``timeout``, container stops and batch schedulers send), raised
    like Ctrl-C so that workers are stopped and finished work is kept."""


#: Seconds a stopped command has to unwind (stop its workers, close its files) before
#: the process exits anyway: a thread stopped inside a lock another one waits for
#: (a progress bar's, a logger's) must not keep it alive. A second signal exits at once.
STOP_GRACE_S = 30.0

_stopping = threading.Event()


def _exit_now(code: int, why: str):
    try:
        os.write(2, f"reachwatch: {why}; exiting now; {KEPT}\n".encode())
    finally:
        os._exit(code)


def _watchdog(code: int):
    """Exit the process ``STOP_GRACE_S`` after the first stop signal, unless it has."""
    def wait():
        time.sleep(STOP_GRACE_S)
        _exit_now(code, f"still stopping {STOP_GRACE_S:g} s after the signal")
    threading.Thread(target=wait, name="reachwatch-stop-watchdog", daemon=True).start()


def _stop(signum, frame):
    """SIGTERM and SIGINT: the first raises in the main thread (`Terminated`, or
    KeyboardInterrupt for Ctrl-C) and starts the watchdog; the second exits at once."""
    code = 143 if signum == signal.SIGTERM else 130
    if _stopping.is_set():
        _exit_now(code, "stopped again")
    _stopping.set()
    _watchdog(code)
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


KEPT = ("finished work is kept (stage records, sweep and dataset chunks, checkpoints are "
        "written atomically); run the same command again to resume")


def _clip(text: str) -> str:
    from reachwatch.systems.checks import clip
    return clip(text)


def _clip_message(error: BaseException) -> str:
    """``error``'s message, clipped to leave room for where it was raised."""
    from reachwatch.systems.checks import clip
    return clip(str(error), 300)


def user_frame(error: BaseException):
    """Where the user's own code raised ``error`` (`diagrams.user_errors.user_frame`)."""
    from reachwatch.diagrams.user_errors import user_frame as frame
    return frame(error)


#: The options that name a file or folder; an empty one is refused.
PATH_OPTIONS = ("out", "scenario", "cache", "sweep_cache", "work_dir", "checkpoint", "run")


def command_name(args) -> str:
    """The command as typed, its action included (``taxinet evaluate``)."""
    action = getattr(args, f"{args.command}_command", None)
    return f"{args.command} {action}" if isinstance(action, str) else args.command


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    console.setup(-1 if args.quiet else (1 if args.verbose else 0))
    import reachwatch.systems  # noqa: F401  (first: process-wide settings before torch loads)
    return_large_blocks()         # glibc gives freed frames back (`pipeline.memory`)
    commands.check_run_file_flags(parser, args)     # a flag as its run-file key is bounded
    commands.fill_run_file_defaults(args)
    signals = (signal.SIGTERM, signal.SIGINT)
    previous = [signal.getsignal(s) for s in signals]
    if threading.current_thread() is threading.main_thread():
        _stopping.clear()
        for s, handler in zip(signals, previous):
            if handler is not signal.SIG_IGN:      # a background job's ignored Ctrl-C stays so
                signal.signal(s, _stop)
    name = command_name(args)
    empty = [option for option in PATH_OPTIONS if getattr(args, option, None) == ""]
    if empty:           # "" would quietly mean the current folder or the built-in defaults
        print(f"reachwatch {name}: error: --{empty[0].replace('_', '-')} is empty: "
              f"name a path", file=sys.stderr)
        return 2
    try:
        return args.func(args) or 0
    except (ValueError, FileNotFoundError, NotImplementedError) as e:
        # bad input, or an application without what the run asks of it: say what, exit 2
        # (and where, when the user's own code raised it)
        where = user_frame(e)
        at = f" (raised at {where[0]}:{where[1]}, in {where[2]})" if where else ""
        message = _clip_message(e) if where else e      # room left for where
        print(_clip(f"reachwatch {name}: error: {message}{at}"), file=sys.stderr)
        return 2
    except (PermissionError, FileExistsError, NotADirectoryError, IsADirectoryError) as e:
        # e.g. --out naming a file where a folder goes
        blocked = isinstance(e, (FileExistsError, NotADirectoryError))
        print(_clip(f"reachwatch {name}: error: cannot write {e.filename}: {e.strerror}"
                    + (" (a file stands where a folder is needed)" if blocked else "")),
              file=sys.stderr)
        return 2
    except OSError as e:
        # the system refused (a name too long, a full or read-only disk): say what, exit 1
        where = f"{e.filename}: " if e.filename else ""
        print(_clip(f"reachwatch {name}: error: {where}{e.strerror or e}"),
              file=sys.stderr)
        return 1
    except Exception as e:
        if type(e).__name__ == "WorkerLost" and not args.verbose:
            # (`reach.executors.WorkerLost`, by name: the parser imports no torch) a worker
            # died, ran other code, or the cluster lost a task: what, and what is kept
            print(_clip(f"reachwatch {name}: error: {_clip_message(e)}; -v shows the "
                        f"traceback"), file=sys.stderr)
            return 1
        # raised inside the user's own code (a controller's calc): where, in one line;
        # anything else (a bug of reachwatch's) keeps its traceback, as does -v
        where = None if args.verbose else user_frame(e)
        if where is None:
            raise
        what = f"{type(e).__name__}: {_clip_message(e)}" if str(e) else type(e).__name__
        print(f"reachwatch {name}: error: {what}, raised at {where[0]}:{where[1]} (in "
              f"{where[2]}); -v shows the traceback", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:
        what = "terminated" if isinstance(e, Terminated) else "interrupted"
        print(f"reachwatch {name}: {what}; {KEPT}", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except SystemExit as e:
        # sys.exit() in the user's code while it runs (a controller's calc at a tick):
        # was the process ending at once, unfinished, with its status (0 too) and no word
        where = user_frame(e)
        if where is None:
            raise
        print(_clip(f"reachwatch {name}: error: the user's code called sys.exit({e.code!r}) "
                    f"at {where[0]}:{where[1]} (in {where[2]}), so the command stopped "
                    f"unfinished; {KEPT}"), file=sys.stderr)
        return 1
    finally:
        if threading.current_thread() is threading.main_thread():
            for s, handler in zip(signals, previous):
                signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(main())
