"""``swarmplan``: the one command-line entry point. It only composes the packages' commands.

Each subcommand is a module of this package with ``HELP`` (one line), ``add_arguments(parser)``
and ``main(args) -> int``; the options several commands share are written once, in
``swarmplan/option_groups.py``. The packages below never parse a command line. A command that
fails because of the user's input raises ``planner.errors.UserError``; it is printed here as one
line, exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# MAVLink 2 everywhere: pymavlink reads this once, at import, for the whole process.
os.environ.setdefault("MAVLINK20", "1")

from planner.errors import UserError  # noqa: E402
from swarmplan.arguments import OneLineParser  # noqa: E402

#: (name, module) of every subcommand, in the order --help lists them.
SUBCOMMANDS = (
    ("run", "swarmplan.run_command"),
    ("demo", "swarmplan.demo"),
    ("sim", "swarmplan.sim_command"),
    ("payload", "swarmplan.payload_command"),
    ("radio-relay", "swarmplan.radio_relay_command"),
    ("daemon", "swarmplan.daemon_command"),
    ("node", "swarmplan.node_command"),
    ("export", "swarmplan.export_command"),
    ("account", "swarmplan.account_command"),
    ("experiment", "swarmplan.experiment_command"),
    ("view", "swarmplan.view_command"),
)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or with ``only`` of that one alone (a command run loads
    its own module and not the others', which keeps a process's start short: the planner's,
    the view server's and the statistics' imports are a second or more)."""
    parser = OneLineParser(
        prog="swarmplan",
        description="HAPF-ACO cooperative UAV-swarm search planner (offline, simulator, MAVLink).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name, module_name in SUBCOMMANDS:
        if only is not None and name != only:
            continue
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:  # a dependency of the command missing from this install
            print(f"swarmplan: command {name!r} unavailable ({exc})", file=sys.stderr)
            continue
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(command)
        command.set_defaults(handler=module.main)
    return parser


def _command_named(argv: list[str]) -> str | None:
    """The subcommand ``argv`` runs (its first word, if that names one), else None."""
    first = argv[0] if argv else None
    return first if first in dict(SUBCOMMANDS) else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(_command_named(argv))
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except UserError as exc:
        print(f"swarmplan {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"swarmplan {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
