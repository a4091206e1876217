"""The options that several ``swarmplan`` commands offer, each written once: the same flag has
the same type, default and help in every command that takes it (only what differs by command,
such as a default or what a seed seeds, is a parameter).

=========================  ============================================================
group                      commands
=========================  ============================================================
scenario, seed             run, demo, sim, payload, daemon
``--vehicles``             sim, payload
``--steps``                run, demo, daemon
``--out``, ``--json``      run, demo, daemon, export, experiment (``--out`` only)
``--quiet``                sim, payload, experiment
``--duration-s``           sim (simulated seconds), payload (wall seconds)
``--target-account``       sim, payload
``--signing-key-file``     sim, daemon, demo
``--no-leg-timing``        daemon, demo
the live view              daemon, demo (``--no-view``, ``--view-host``, ``--view-port``)
=========================  ============================================================
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from mavlink_wire.signing import KEY_ENV
from planner.scenario import BUILTIN_SCENARIOS
from swarmplan.arguments import (
    DEFAULT_SEED,
    port_number,
    positive_float,
    positive_int,
    seed_int,
    tile_template,
)

if TYPE_CHECKING:
    from mission_view.view_session import ViewOptions

#: What takes options: a parser, or a group of its options (``add_mutually_exclusive_group``).
Options = argparse._ActionsContainer


def add_scenario_argument(
    parser: Options, default: str | None = None, *, positional: bool = False
) -> None:
    """The scenario to fly: ``--scenario NAME`` or, ``positional``, a positional argument
    (required when there is no ``default``)."""
    help_text = f"a built-in scenario ({', '.join(BUILTIN_SCENARIOS)}) or a TOML file"
    if default is not None:
        help_text += f" (default {default})"
    if not positional:
        parser.add_argument("--scenario", default=default, help=help_text)
    elif default is None:
        parser.add_argument("scenario", help=help_text)
    else:
        parser.add_argument("scenario", nargs="?", default=default, help=help_text)


def add_seed_argument(parser: Options, what: str) -> None:
    """``--seed S`` (default :data:`DEFAULT_SEED`); ``what`` says what it seeds."""
    parser.add_argument(
        "--seed", type=seed_int, default=DEFAULT_SEED, help=f"{what} (default {DEFAULT_SEED})"
    )


def add_world_arguments(parser: Options, default_scenario: str, seeds: str) -> None:
    """A simulated world: its scenario, its seed (``seeds``: what it seeds) and how many
    vehicles fly in it."""
    add_scenario_argument(parser, default_scenario)
    add_seed_argument(parser, seeds)
    parser.add_argument(
        "--vehicles",
        type=positive_int,
        default=None,
        help="number of vehicles (default: the scenario's)",
    )


def add_steps_option(parser: Options) -> None:
    parser.add_argument(
        "--steps", type=positive_int, default=None, help="decision steps (default: the scenario's)"
    )


def add_out_option(parser: Options, default_says: str, default: Path | None = None) -> None:
    """``--out FOLDER``; ``default_says`` is the default folder as the help names it (when
    ``default`` is None the command works it out)."""
    parser.add_argument(
        "--out", type=Path, default=default, help=f"output folder (default: {default_says})"
    )


def add_json_option(parser: Options) -> None:
    parser.add_argument("--json", action="store_true", help="print only the result JSON on stdout")


def add_quiet_option(parser: Options, shows: str = "progress lines") -> None:
    parser.add_argument("--quiet", action="store_true", help=f"no {shows}")


def add_duration_option(parser: Options, clock: str) -> None:
    """``--duration-s S``, counted on ``clock`` ("simulated" or "wall")."""
    parser.add_argument(
        "--duration-s", type=positive_float, default=None, help=f"stop after this many {clock} s"
    )


def add_target_account_option(parser: Options) -> None:
    parser.add_argument(
        "--target-account", type=Path, default=None, metavar="PATH",
        help="on exit, write the ground-truth half of the per-target account here as JSON; "
        "swarmplan account joins it to a daemon's result.json, swarmplan demo does it itself "
        "(docs/experiments.md)",
    )  # fmt: skip


def add_signing_key_option(parser: Options, use: str, otherwise: str) -> None:
    """``--signing-key-file PATH``: ``use`` says what the command does with the key,
    ``otherwise`` what it does with neither the file nor ``$SWARMPLAN_SIGNING_KEY``."""
    parser.add_argument(
        "--signing-key-file",
        type=Path,
        metavar="PATH",
        help=f"MAVLink 2 signing key (64 hex characters or 32 bytes): {use}; default ${KEY_ENV} "
        f"if set (never a command-line value), else {otherwise}",
    )


def add_leg_timing_option(parser: Options) -> None:
    parser.add_argument(
        "--no-leg-timing",
        dest="leg_timing",
        action="store_false",
        help="fly every leg at the scenario's speed instead of timing each leg to one decision "
        "step with MAV_CMD_DO_CHANGE_SPEED (the paper's grid flies a diagonal cell, 1.41 km, "
        "per step; at constant speed the planes fall behind it)",
    )


def add_view_options(parser: Options) -> None:
    """The live mission view in the browser (docs/view.md); :func:`view_options` reads them."""
    parser.add_argument(
        "--no-view", action="store_true", help="do not serve the live view in the browser"
    )
    parser.add_argument(
        "--view-host",
        default="127.0.0.1",
        help="address the live view listens on (default 127.0.0.1: this machine only)",
    )
    parser.add_argument(
        "--view-port",
        type=port_number,
        default=0,
        help="port of the live view (default 0: a free one; the URL is printed at start)",
    )
    add_tiles_option(parser)


def add_tiles_option(parser: Options) -> None:
    """``--tiles``: a map backdrop for the view (``swarmplan view``, ``demo``, ``daemon``)."""
    parser.add_argument(
        "--tiles",
        type=tile_template,
        default=None,
        metavar="URL_TEMPLATE",
        help="draw the map over an XYZ tile server you have (e.g. "
        "http://localhost:8080/{z}/{x}/{y}.png); default: no backdrop and no network",
    )


def view_options(args: argparse.Namespace) -> ViewOptions:
    """The view's options from ``--no-view``, ``--view-host`` and ``--view-port``."""
    from mission_view.view_session import ViewOptions

    return ViewOptions(
        serve=not args.no_view, host=args.view_host, port=args.view_port, tiles=args.tiles
    )
