"""Is a decoded checkpoint state fit to resume this mission? Checked before any of it reaches the
planner, against the state this daemon builds for the mission (the *template*: a fresh planner,
recorder, loop and counters):

1. **layout** (:func:`check_like`): every part has the template's kind (the same class with the
   same attributes, the same container with the same length or keys, a number where it has a
   number), every array its dtype, order and shape (the scenario fixes them all), every float
   is finite. Parts that grow during a mission (tracks, curves, logs) or are None until first
   used are checked item by item against :data:`GROWING` instead.
2. **ranges** (:func:`check_ranges`): cells inside the grid, headings 0-7, probabilities and
   beliefs within [0, 1], pheromone within [tau_min, tau_max], distances and counts not
   negative, the random generator's state within its 128 bits.

A failure is a :class:`checkpoint_codec.StateError` naming the part (``planner.tpm.maps``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from mavlink_bridge.results.checkpoint_codec import METHODS, StateError, attributes, classes

Check = Callable[[Any, str, "Mission"], None]


@dataclass(frozen=True)
class Mission:
    """What the ranges depend on: the grid and the UAV count of the template."""

    nx: int
    ny: int
    n: int
    tau_min: float
    tau_max: float


def pattern(path: str) -> str:
    """``recorder.tracks[3]`` -> ``recorder.tracks[]`` (the key of the tables below)."""
    return re.sub(r"\[[^\]]*\]", "[]", path)


# ---------------------------------------------------------------------------- item checks


_NUMBERS = (int, float, np.integer, np.floating)


def number(low: float = -math.inf, high: float = math.inf, infinite: bool = False) -> Check:
    """A real number (int or float, numpy's too) within [low, high], finite unless told."""

    def check(v: Any, path: str, m: Mission) -> None:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, _NUMBERS):
            raise StateError(path, f"is a {type(v).__name__}, not a number")
        if math.isnan(v) or (math.isinf(v) and not infinite):
            raise StateError(path, f"is {v}, not a finite number")
        if not low <= v <= high:
            raise StateError(path, f"is {v}, outside [{low:g}, {high:g}]")

    return check


def integer(low: float = -math.inf, high: float = math.inf) -> Check:
    def check(v: Any, path: str, m: Mission) -> None:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise StateError(path, f"is a {type(v).__name__}, not an integer")
        if not low <= v <= high:
            raise StateError(path, f"is {v}, outside [{low:g}, {high:g}]")

    return check


def list_of(item: Check, kind: type = list) -> Check:
    """A ``kind`` (list or set) of any length whose every item passes ``item``."""

    def check(v: Any, path: str, m: Mission) -> None:
        if type(v) is not kind:
            raise StateError(path, f"is a {type(v).__name__}, not a {kind.__name__}")
        for i, x in enumerate(v):
            item(x, f"{path}[{i}]", m)

    return check


def row(kind: type, *items: Check) -> Check:
    """A list or tuple (``kind``) of exactly ``len(items)`` values, each passing its check."""

    def check(v: Any, path: str, m: Mission) -> None:
        if type(v) is not kind or len(v) != len(items):
            raise StateError(path, f"is not a {kind.__name__} of {len(items)} values")
        for i, (x, item) in enumerate(zip(v, items, strict=True)):
            item(x, f"{path}[{i}]", m)

    return check


def optional(inner: Check) -> Check:
    def check(v: Any, path: str, m: Mission) -> None:
        if v is not None:
            inner(v, path, m)

    return check


def record(name: str) -> Check:
    """An object of a flat dataclass of :data:`checkpoint_codec.CLASSES` (numbers, flags and
    names), each field of the type its annotation says."""
    simple = {"int": integer(), "float": number(), "str": None, "bool": None}

    def check(v: Any, path: str, m: Mission) -> None:
        cls = classes()[name]
        if type(v) is not cls:
            raise StateError(path, f"is a {type(v).__name__}, not a {name}")
        declared = {f.name: f.type for f in fields(cls)}
        if set(vars(v)) != set(declared):
            raise StateError(path, f"does not have the fields of a {name}")
        for key, annotation in declared.items():
            value, where = getattr(v, key), f"{path}.{key}"
            if simple[annotation] is not None:
                simple[annotation](value, where, m)
            elif type(value).__name__ != annotation:
                raise StateError(where, f"is a {type(value).__name__}, not a {annotation}")

    return check


def optional_positions(v: Any, path: str, m: Mission) -> None:
    """None, or each UAV's measured position (N, 2) km, finite."""
    if v is None:
        return
    if not isinstance(v, np.ndarray) or v.dtype != np.float64 or v.shape != (m.n, 2):
        raise StateError(path, f"is not None or an ({m.n}, 2) float64 array")
    _finite(v, path)


_PAIR = row(list, number(), number())


def dict_of(key: Check, value: Check) -> Check:
    """A dict of any size whose every key and value pass their checks."""

    def check(v: Any, path: str, m: Mission) -> None:
        if type(v) is not dict:
            raise StateError(path, f"is a {type(v).__name__}, not a dict")
        for k, x in v.items():
            key(k, f"{path}[{k!r}]", m)
            value(x, f"{path}[{k!r}]", m)

    return check


def _uav_state(v: Any, path: str, m: Mission) -> None:
    """A neighbour's state as a node last heard it (``planner.swarm_messages.UavState``)."""
    cls = classes()["UavState"]
    if type(v) is not cls or set(vars(v)) != {f.name for f in fields(cls)}:
        raise StateError(path, "is not a UavState")
    for name, high in (("uav", 255), ("step", math.inf), ("heading", 7)):
        integer(0, high)(getattr(v, name), f"{path}.{name}", m)
    row(tuple, integer(0, m.nx - 1), integer(0, m.ny - 1))(v.cell, f"{path}.cell", m)
    row(tuple, number(), number())(v.position_km, f"{path}.position_km", m)
    number(0.0)(v.radius_km, f"{path}.radius_km", m)
    if type(v.flying) is not bool:
        raise StateError(f"{path}.flying", "is not a flag")


def _beliefs_growing(beliefs: str) -> dict[str, Check]:
    """The parts of the beliefs at ``beliefs`` that grow during a mission."""
    log = f"{beliefs}.observers[].__self__"
    return {
        f"{log}.beliefs": list_of(row(list, integer(0), integer(0), integer(0), number(0.0, 1.0))),
        f"{log}.tracks": list_of(row(list, *[integer(-1)] * 5)),
        f"{log}.engage_requests": list_of(row(list, integer(0), integer(0))),
        f"{beliefs}.measured_km": optional_positions,
    }


#: A planner node's (``swarmplan node``, ``mavlink_bridge/mission/onboard_planner.py``) parts
#: that grow: its link's counters per step, the sequence and the state last heard of each
#: neighbour.
_NODE_GROWING: dict[str, Check] = {
    **{f"planner.stats.{name}": list_of(integer(0))
       for name in ("bytes_sent", "bytes_received", "neighbours_heard")},
    **{f"planner.stats.{name}": list_of(number(0.0)) for name in ("cpu_s", "wall_s")},
    "planner._sequence": dict_of(integer(0, 255), integer(0, 0xFFFF)),
    "planner.node.last_heard": dict_of(integer(0), _uav_state),
    **_beliefs_growing("planner.node.planner.beliefs"),
}  # fmt: skip
#: Parts that grow during a mission, or are None until first used: their items' checks.
GROWING: dict[str, Check] = {
    "recorder.tracks[]": list_of(_PAIR),
    "recorder.planned[]": list_of(_PAIR),
    "recorder.coverage_curve": list_of(number(0.0, 1.0)),
    "recorder.engaged_curve": list_of(integer(0)),
    "recorder.min_separation_curve": list_of(number(0.0, infinite=True)),
    "recorder.mean_min_separation_curve": list_of(number(0.0, infinite=True)),
    "recorder.engagements": list_of(lambda v, path, m: _engagement(v, path, m)),
    **_beliefs_growing("planner.beliefs"),
    "last_target[]": optional(row(tuple, number(), number())),
    "engagements[]": optional(record("EngagementOutcome")),
    "engaged_ids": list_of(integer(), kind=set),
    "daemon.events": list_of(record("LinkEvent")),
    **_NODE_GROWING,
}
#: Arrays whose float values may be NaN (e.g. no leg yet: ``MissionRecorder.break_legs``).
MAY_BE_NAN = {"recorder._last", "recorder._last_leg"}


def _engagement(v: Any, path: str, m: Mission) -> None:
    if type(v) is not dict or set(v) != {"step", "uav", "target_id", "value"}:
        raise StateError(path, "is not an engagement {step, uav, target_id, value}")
    for key in ("step", "uav", "target_id"):
        integer(0)(v[key], f"{path}[{key!r}]", m)
    number(0.0)(v["value"], f"{path}['value']", m)


def _finite(v: np.ndarray, path: str) -> None:
    if v.dtype.kind == "f" and not np.isfinite(v).all():
        raise StateError(path, "holds NaN or infinite values")


# ---------------------------------------------------------------------------- layout


def check_like(v: Any, t: Any, path: str, m: Mission, skip: frozenset[str]) -> None:
    """``v`` (from the file) has the layout of ``t`` (this daemon's); ``skip``: paths written
    as None (the scenario alone determines them)."""
    key = pattern(path)
    if path in skip:
        if v is not None:
            raise StateError(path, "must not be in a checkpoint (the scenario determines it)")
        return
    if key in GROWING:
        GROWING[key](v, path, m)
        return
    if type(v) is not type(t):
        raise StateError(path, f"is a {_kind(v)}, this daemon's is a {_kind(t)}")
    if isinstance(t, np.ndarray):
        _check_array(v, t, path, key)
    elif isinstance(t, (float, np.floating)):
        number(infinite=True)(v, path, m) if math.isinf(t) else number()(v, path, m)
    elif isinstance(t, (list, tuple)):
        if len(v) != len(t):
            raise StateError(path, f"has {len(v)} items, this daemon's has {len(t)}")
        for i, (a, b) in enumerate(zip(v, t, strict=True)):
            check_like(a, b, f"{path}[{i}]", m, skip)
    elif isinstance(t, dict):
        if set(v) != set(t):
            raise StateError(path, f"has keys {_diff(v, t)} that this daemon's has not, or lacks")
        for k in t:
            check_like(v[k], t[k], f"{path}[{k!r}]", m, skip)
    elif isinstance(t, (set, frozenset)):
        if not all(type(x) in (int, str) for x in v):
            raise StateError(path, "holds items other than numbers and names")
    elif isinstance(t, np.random.Generator):
        _check_generator(v, t, path, m)
    elif type(t).__name__ in classes():
        _check_object(v, t, path, m, skip)
    elif callable(t) and hasattr(t, "__self__"):
        if (type(v.__self__).__name__, v.__name__) not in METHODS or v.__name__ != t.__name__:
            raise StateError(path, f"is the method {v.__name__}, this daemon's is {t.__name__}")
        check_like(v.__self__, t.__self__, f"{path}.__self__", m, skip)


def _check_array(v: np.ndarray, t: np.ndarray, path: str, key: str) -> None:
    if v.dtype != t.dtype:
        raise StateError(path, f"is a {v.dtype} array, this daemon's is {t.dtype}")
    if v.shape != t.shape:
        raise StateError(path, f"has shape {v.shape}, this mission's is {t.shape}")
    if v.flags.c_contiguous != t.flags.c_contiguous:
        raise StateError(path, "is not laid out in memory as this daemon's (C order)")
    if key not in MAY_BE_NAN:
        _finite(v, path)


def _check_object(v: Any, t: Any, path: str, m: Mission, skip: frozenset[str]) -> None:
    mine, theirs = attributes(v), attributes(t)
    if set(mine) != set(theirs):
        raise StateError(
            path, f"has attributes {_diff(mine, theirs)} that this daemon's has not, or lacks"
        )
    for k in theirs:
        check_like(mine[k], theirs[k], f"{path}.{k}", m, skip)


def _check_generator(v: np.random.Generator, t: np.random.Generator, path: str, m: Mission):
    state, template = v.bit_generator.state, t.bit_generator.state
    if type(v.bit_generator) is not type(t.bit_generator):
        raise StateError(path, "is not this daemon's kind of random generator")
    for part in ("state", "inc"):
        integer(0, 2**128 - 1)(state["state"][part], f"{path}.state.{part}", m)
    if set(state) != set(template):
        raise StateError(path, "is not a random generator state of this daemon's")


def _kind(x: Any) -> str:
    if isinstance(x, np.ndarray):
        return f"{x.dtype} array"
    return type(x).__name__


def _diff(a: Any, b: Any) -> str:
    return ", ".join(sorted(str(k) for k in set(a) ^ set(b))[:4])


# ---------------------------------------------------------------------------- ranges


def _cells(v: np.ndarray, path: str, m: Mission, none_allowed: bool = False) -> None:
    inside = (v[..., 0] >= 0) & (v[..., 0] < m.nx) & (v[..., 1] >= 0) & (v[..., 1] < m.ny)
    if none_allowed:
        inside |= (v == -1).all(axis=-1)
    if not inside.all():
        bad = tuple(int(c) for c in v[~inside][0])
        raise StateError(path, f"holds cell {bad}, outside the {m.nx} x {m.ny} grid")


def _within(low: Callable[[Mission], float], high: Callable[[Mission], float]) -> Check:
    def check(v: Any, path: str, m: Mission) -> None:
        lo, hi = low(m), high(m)
        values = np.asarray(v, dtype=float)
        if values.size and not ((values >= lo) & (values <= hi)).all():
            found = values[(values < lo) | (values > hi)].flat[0]
            raise StateError(path, f"holds {found:g}, outside [{lo:g}, {hi:g}]")

    return check


def _tpm(tpm: Any, path: str, m: Mission) -> None:
    """Each layer's cell holds the expected number of its targets there, a probability."""
    if type(tpm) is not classes()["TargetProbabilityMaps"]:
        return  # the baselines' beliefs (planner/acoapf.py): their layout is checked
    _within(lambda m: 0.0, lambda m: math.inf)(tpm.maps, f"{path}.maps", m)
    for part in ("scale", "counts", "totals"):
        _within(lambda m: 0.0, lambda m: math.inf)(getattr(tpm, part), f"{path}.{part}", m)
    peak = tpm.maps.max(axis=(2, 3)) * tpm.scale  # (L, N)
    if (peak > 1.0 + 1e-4).any():
        raise StateError(f"{path}.maps", f"holds a probability of {peak.max():g}, above 1")


_ZERO, _INF = (lambda m: 0.0), (lambda m: math.inf)
_HEADINGS = _within(_ZERO, lambda m: 7)
_NOT_NEGATIVE = _within(_ZERO, _INF)
_PROBABILITY = _within(_ZERO, lambda m: 1.0)
#: Range checks, by the path of the part they check (after the layout check); a planner node's
#: planner (``OnboardPlanner``) has the same paths (``beliefs``, ``pheromone``, ``cfg``: its
#: node's planner's).
RANGES: dict[str, Check] = {
    "planner.beliefs.cells": _cells,
    "planner.beliefs.home": _cells,
    "planner.beliefs.info_cells": _cells,
    "planner.beliefs.track": lambda v, p, m: _cells(v, p, m, none_allowed=True),
    "planner.beliefs.escape_goal": lambda v, p, m: _cells(v, p, m, none_allowed=True),
    "planner.beliefs.engaged_cells": lambda v, p, m: _cells(v, p, m, none_allowed=True),
    "planner.beliefs.request_cells": lambda v, p, m: _cells(v, p, m, none_allowed=True),
    "planner.beliefs.home_flat": _within(_ZERO, lambda m: m.nx * m.ny - 1),
    "planner.beliefs.headings": _HEADINGS,
    "planner.beliefs.distance_km": _NOT_NEGATIVE,
    "planner.beliefs.radius_km": _NOT_NEGATIVE,
    "planner.beliefs.k": _NOT_NEGATIVE,
    "planner.beliefs.tpm": _tpm,
    "planner.pheromone.tau": _within(lambda m: m.tau_min, lambda m: m.tau_max),
    "planner.cfg.p_detect": _PROBABILITY,
    "planner.cfg.p_false": _PROBABILITY,
    "planner.cfg.q0": _PROBABILITY,
    "planner.cfg.confirm_threshold": _PROBABILITY,
    "planner.cfg.env_perception_lambda": _PROBABILITY,
    "recorder.distance_km": _NOT_NEGATIVE,
    "recorder.steps": _NOT_NEGATIVE,
    "cells": _cells,
    "commanded_cells": _cells,
    "headings": _HEADINGS,
    "commanded_headings": _HEADINGS,
    "flown_km": _NOT_NEGATIVE,
    "engaged_value": _NOT_NEGATIVE,
}


#: what :func:`range_part` gives for a path whose part the state lacks
MISSING = object()


def range_part(state: dict[str, Any], path: str) -> Any:
    """The part of ``state`` (the layout-checked roots) that the :data:`RANGES` path ``path``
    names: None where it is None, :data:`MISSING` where the state has no such part."""
    root, *names = path.split(".")
    value = state.get(root, MISSING)
    for name in names:
        if value is MISSING:
            break
        value = getattr(value, name, MISSING)
    return value


def check_ranges(state: dict[str, Any], m: Mission) -> None:
    """Every part of :data:`RANGES` within its range (``state``: the layout-checked roots)."""
    for path, check in RANGES.items():
        value = range_part(state, path)
        if value is not None and value is not MISSING:  # (a baseline planner may lack a part:
            check(value, path, m)  # its layout is checked)
