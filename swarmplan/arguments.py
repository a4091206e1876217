"""What every ``swarmplan`` subcommand shares on its command line: usage errors as one line, the
value types (whole numbers, seeds, finite numbers, ports, planner names), the one default seed,
and the output folder checked before any work starts. The option groups that several commands
offer (the scenario, the output, signing, the live view...) are written once, in
``swarmplan/option_groups.py``.

An input error is one line naming the problem and the fix, exit status 2 (README), argparse's
included: :class:`OneLineParser` replaces its usage block with a pointer to ``--help``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path
from typing import NoReturn

from planner.errors import UserError

#: The seed of every command that takes one (run, demo, sim, daemon), so that ``swarmplan sim``
#: and ``swarmplan daemon`` in two shells fly the same mission as ``swarmplan demo``.
DEFAULT_SEED = 1


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, exit status 2.

    Arguments a subcommand does not know are reported by that subcommand's parser (naming it),
    not by the top parser after the subcommand has parsed the rest."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message}; see '{self.prog} --help'", file=sys.stderr)
        sys.exit(2)

    def parse_known_args(self, args=None, namespace=None):  # noqa: ANN001 (argparse's signature)
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def _whole_number(
    text: str,
    minimum: int,
    out_of_range: str,
    maximum: int | None = None,
    kind: str = "whole number",
) -> int:
    """``text`` as an int in ``minimum..maximum``; ``out_of_range`` ends the message otherwise."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a {kind}") from None
    if value < minimum or (maximum is not None and value > maximum):
        raise argparse.ArgumentTypeError(f"{text!r} {out_of_range}")
    return value


def positive_int(text: str) -> int:
    return _whole_number(text, 1, "must be at least 1")


def non_negative_int(text: str) -> int:
    return _whole_number(text, 0, "must be 0 or more")


def uav_index(text: str) -> int:
    """A UAV of a scenario, 0-based (its autopilot is system id index + 1)."""
    return _whole_number(text, 0, "must be 0 or more (0-based: system id - 1)", 254)


def system_id(text: str) -> int:
    """A MAVLink system id, 1..255."""
    return _whole_number(text, 1, "must be a MAVLink system id, 1..255", 255)


def seed_int(text: str) -> int:
    return _whole_number(text, 0, "must be 0 or more")


def finite_float(text: str) -> float:
    """A number that is neither NaN nor infinite (``1e400`` overflows to infinity)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def km_point(text: str) -> tuple[float, float]:
    """A point of the mission frame, ``X,Y`` in km (east, north of the area's south-west
    corner)."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not a point X,Y in km; e.g. 50,50")
    return finite_float(parts[0].strip()), finite_float(parts[1].strip())


def positive_float(text: str) -> float:
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return value


def non_negative_float(text: str) -> float:
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be 0 or more")
    return value


def port_number(text: str) -> int:
    """A UDP or TCP port (0: a free one, where a command takes that)."""
    return _whole_number(
        text, 0, "is not a port number (0..65535)", maximum=65535, kind="port number"
    )


def endpoint(text: str) -> str:
    """A MAVLink endpoint spec that parses (``tcp:HOST:PORT``, ``udpin:...``, ``udpout:...``)."""
    from mavlink_wire.links import EndpointError, parse_endpoint

    try:
        parse_endpoint(text)
    except EndpointError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--connect ")) from None
    return text


def tile_template(text: str) -> str:
    """An XYZ tile server's URL template (``https://host/{z}/{x}/{y}.png``) for the view."""
    if not text.startswith(("http://", "https://")) or not all(
        part in text for part in ("{z}", "{x}", "{y}")
    ):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a tile URL template: give http(s)://HOST/PATH with {{z}}, {{x}} "
            "and {y}, e.g. http://localhost:8080/tile/{z}/{x}/{y}.png"
        )
    return text


def planner_name(text: str) -> str:
    """The name of a planner that can be built (built in, or registered by a plug-in)."""
    from planner.registry import planner_factory  # here: the planners import scipy.ndimage

    try:
        planner_factory(text)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def writable_folder(out: Path, option: str = "--out") -> Path:
    """``out``, created if missing and proven writable (a probe file is written and removed), so
    that a run that cannot keep its results is refused before it starts, not after."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise UserError(
            f"cannot write to {out} ({reason}); choose another {option} folder"
        ) from None
    return out
