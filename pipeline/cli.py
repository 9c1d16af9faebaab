"""The ``reachwatch`` command line."""

import argparse
import sys

from . import commands, evaluate_commands, guard_commands, reach_commands, run, taxinet_commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reachwatch",
        description="Find, detect and mitigate system-level failures of vision-based "
                    "controllers (Drake + HJ reachability).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    render = sub.add_parser("render", help="render the wing-camera image of a scenario, "
                            "or a contact sheet of every environment")
    render.add_argument("--scenario", help="scenario YAML (default: built-in defaults)")
    render.add_argument("--out", required=True, help="output folder")
    render.add_argument("--contact-sheet", action="store_true",
                        help="render all 5 runways x hours 9, 17, 21 x clear/overcast "
                             "at the scenario's state into one PNG")
    render.set_defaults(func=commands.render)

    graph = sub.add_parser("graph", help="export the scenario's diagram graph "
                           "(.dot; .svg/.png with graphviz)")
    graph.add_argument("--scenario", help="scenario YAML (default: built-in defaults)")
    graph.add_argument("--out", required=True, help="output folder")
    graph.add_argument("--max-depth", type=int, default=2, help="Graphviz nesting depth")
    graph.set_defaults(func=commands.graph)

    taxinet_commands.add_parsers(sub)
    reach_commands.add_parsers(sub)
    evaluate_commands.add_parsers(sub)
    guard_commands.add_parsers(sub)
    run.add_parsers(sub)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except (ValueError, FileNotFoundError) as e:  # bad input: say what, exit 2
        print(f"reachwatch {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
