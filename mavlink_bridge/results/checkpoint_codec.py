"""A checkpoint's state as data: plain JSON for its structure and numbers, numpy arrays beside
it (``mavlink_bridge/results/checkpoint.py`` stores both in one .npz read with
``allow_pickle=False``).

:func:`encode` turns the decision loop's state (the planner, the recorder, the loop variables,
the daemon's counters) into a JSON-able tree and a list of arrays; :func:`decode` builds it
back. Nothing in a file names code to run: the tree holds JSON values and these tagged forms
only (one key, starting with ``$``):

* ``{"$float": "nan" | "inf" | "-inf"}``: a float JSON cannot hold;
* ``{"$scalar": [dtype, value]}``: a numpy number (dtype from :data:`SCALAR_DTYPES`);
* ``{"$array": k}``: the k-th array of the file (numbers or booleans, never objects);
* ``{"$tuple": [...]}``, ``{"$set": [...]}``, ``{"$dict": [[key, value], ...]}``;
* ``{"$generator": state}``: a numpy ``Generator`` on ``PCG64`` (its ``bit_generator.state``);
* ``{"$object": [name, {attribute: value, ...}]}``: an object of one of the project's own
  classes (:data:`CLASSES`, by name), rebuilt as ``cls.__new__(cls)`` plus its attributes,
  without calling any of its code;
* ``{"$method": [name, object]}``: a bound method on such an object, only those of
  :data:`METHODS` (the planner's observers).

Anything else is refused, naming where it is (``planner.tpm.maps``, ``recorder.tracks[3]``).
A decoded tree is not yet trusted: ``checkpoint_layout.check_state`` compares it with the state
this daemon builds for the mission before it is used.
"""

from __future__ import annotations

import functools
import importlib
import math
from typing import Any

import numpy as np

#: The project's classes a checkpoint may hold (module, class).
CLASSES = (
    ("planner.hapf_aco", "HapfAcoPlanner"),
    ("planner.swarm_beliefs", "SwarmBeliefs"),
    ("planner.pso", "PsoPlanner"),
    ("planner.pso", "PsoSettings"),
    ("planner.acoapf", "AcoApfPlanner"),
    ("planner.acoapf", "ApfBeliefs"),
    ("planner.acoapf", "StaticTargetProbabilityMaps"),
    ("planner.target_probability_map", "TargetProbabilityMaps"),
    ("planner.target_priors", "LayerSpec"),
    ("planner.pheromone", "PheromoneMaps"),
    ("planner.config", "PlannerConfig"),
    ("planner.scenario", "Scenario"),
    ("planner.scenario", "TargetSpec"),
    ("planner.scenario", "ThreatSpec"),
    ("planner.scenario", "UavStart"),
    ("planner.scenario", "Origin"),
    ("planner.grid", "Grid"),
    ("planner.metrics", "MissionRecorder"),
    ("planner.engagement", "EngagementOutcome"),
    ("planner.pursuit_log", "PursuitLog"),
    ("mavlink_bridge.results.mission_result", "LinkEvent"),
    # a planner node's (``swarmplan node``): one UAV's planner over the swarm link
    ("mavlink_bridge.mission.onboard_planner", "OnboardPlanner"),
    ("mavlink_bridge.mission.onboard_planner", "NodeLinkStats"),
    ("planner.uav_node", "UavNode"),
    ("planner.uav_node", "ClaimStats"),
    ("planner.swarm_messages", "UavState"),
    ("mavlink_wire.swarm_wire", "SwarmSender"),
    ("mavlink_wire.swarm_wire", "SwarmWireStats"),
)
#: Bound methods a checkpoint may hold: (class name, method name).
METHODS = {("PursuitLog", "record")}
#: Attributes never written (nor are ``functools.cached_property`` values): caches an object
#: computes again when they are missing; a planner node's parts bound to its process (its link,
#: clock, progress lines, wire tables, reassembly buffers), which the planner a resumed node
#: builds hands over (``OnboardPlanner.hand_over``), and what only one step's exchanges use (set
#: by ``UavNode.begin``).
CACHES = {
    "PursuitLog": ("_square", "_gather"),
    "OnboardPlanner": (
        "link", "period_wall_s", "say", "wire", "reassembler", "_ahead", "_heard_flights",
        "_legs",
    ),  # fmt: skip
    "UavNode": ("inbox", "_report", "_seen", "_ranking", "_board"),
}
#: numpy number types a ``$scalar`` may have.
SCALAR_DTYPES = (
    "bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
    "float16", "float32", "float64",
)  # fmt: skip
_SPECIAL_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


class StateError(ValueError):
    """A part of a checkpoint's state that is not what it must be: ``path`` and ``problem``."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


def classes() -> dict[str, type]:
    """:data:`CLASSES` by class name (imported on first use)."""
    if not _CLASSES:
        for module, name in CLASSES:
            _CLASSES[name] = getattr(importlib.import_module(module), name)
    return _CLASSES


_CLASSES: dict[str, type] = {}


def attributes(obj: Any) -> dict[str, Any]:
    """The attributes of one of :data:`CLASSES` that a checkpoint holds: caches (those of
    :data:`CACHES`, and ``functools.cached_property`` values) are left out, computed again."""
    cls = type(obj)
    skip = CACHES.get(cls.__name__, ())
    return {
        k: v
        for k, v in vars(obj).items()
        if k not in skip and not isinstance(getattr(cls, k, None), functools.cached_property)
    }


# ---------------------------------------------------------------------------- encoding


def encode(value: Any, arrays: list[np.ndarray], path: str, none_at: frozenset[str]) -> Any:
    """``value`` as a JSON-able tree; its arrays are copied into ``arrays`` (the state changes
    at the next step) and referred to by index. ``none_at``: paths written as None (parts the
    scenario alone determines). A value of any other kind is a programming error (TypeError)."""
    if path in none_at or value is None or isinstance(value, (bool, str)):
        return None if path in none_at else value
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise TypeError(f"{path}: a {value.dtype} array cannot go into a checkpoint")
        arrays.append(value.copy(order="K"))
        return {"$array": len(arrays) - 1}
    if isinstance(value, np.generic):
        return {"$scalar": [value.dtype.name, _encode_float(value.item())]}
    if isinstance(value, (int, float)):
        return _encode_float(value)
    if isinstance(value, list):
        if _plain(value):  # (tracks, curves, logs: JSON as they are, at once)
            return value
        return [encode(v, arrays, f"{path}[{i}]", none_at) for i, v in enumerate(value)]
    if isinstance(value, tuple):
        return {"$tuple": [encode(v, arrays, f"{path}[{i}]", none_at) for i, v in enumerate(value)]}
    if isinstance(value, (set, frozenset)):
        return {"$set": [encode(v, arrays, f"{path}[]", none_at) for v in sorted(value)]}
    if isinstance(value, dict):
        pairs = [[k, encode(v, arrays, f"{path}[{k!r}]", none_at)] for k, v in value.items()]
        if not all(isinstance(k, (int, str)) and not isinstance(k, bool) for k, _ in pairs):
            raise TypeError(f"{path}: only numbers and names can be keys in a checkpoint")
        return {"$dict": pairs}
    if isinstance(value, np.random.Generator):
        return {"$generator": value.bit_generator.state}
    name = type(value).__name__
    if classes().get(name) is type(value):
        attrs = {k: encode(v, arrays, f"{path}.{k}", none_at) for k, v in attributes(value).items()}
        return {"$object": [name, attrs]}
    owner = getattr(value, "__self__", None)
    if owner is not None and (type(owner).__name__, getattr(value, "__name__", "")) in METHODS:
        return {"$method": [value.__name__, encode(owner, arrays, f"{path}.__self__", none_at)]}
    raise TypeError(f"{path}: a {type(value).__qualname__} cannot go into a checkpoint")


def _plain(items: list[Any]) -> bool:
    """Whether a list is JSON as it is: finite floats, ints, names, flags, None, such lists."""
    for v in items:
        kind = type(v)
        if kind is list:
            if not _plain(v):
                return False
        elif kind is float:
            if not math.isfinite(v):
                return False
        elif kind not in _PLAIN:
            return False
    return True


_PLAIN = (int, str, bool, type(None))


def _encode_float(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return {"$float": "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")}
    return value


# ---------------------------------------------------------------------------- decoding


def decode(tree: Any, arrays: Any, path: str) -> Any:
    """The value a tree of :func:`encode` stands for; ``arrays[k]`` the k-th array (read on
    demand). Raises :class:`StateError` for anything that is not one of the forms above."""
    if tree is None or isinstance(tree, (bool, str, int, float)):
        return tree
    if isinstance(tree, list):
        return [decode(v, arrays, f"{path}[{i}]") for i, v in enumerate(tree)]
    if not isinstance(tree, dict) or len(tree) != 1:
        raise StateError(path, "is not a value a checkpoint holds")
    ((tag, body),) = tree.items()
    decoder = _DECODERS.get(tag)
    if decoder is None:
        raise StateError(path, f"has an unknown form {tag[:40]!r}")
    return decoder(body, arrays, path)


def _decode_float(body: Any, arrays: Any, path: str) -> float:
    if body not in _SPECIAL_FLOATS:
        raise StateError(path, "is not a number")
    return _SPECIAL_FLOATS[body]


def _decode_scalar(body: Any, arrays: Any, path: str) -> Any:
    if not (isinstance(body, list) and len(body) == 2 and body[0] in SCALAR_DTYPES):
        raise StateError(path, "is not a numpy number")
    value = decode(body[1], arrays, path)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise StateError(path, "is not a numpy number")
    try:
        return np.dtype(body[0]).type(value)
    except (OverflowError, ValueError):
        raise StateError(path, f"{value!r} is out of range for {body[0]}") from None


def _decode_array(body: Any, arrays: Any, path: str) -> np.ndarray:
    if isinstance(body, bool) or not isinstance(body, int):
        raise StateError(path, "is not an array reference")
    return arrays(body, path)


def _items(body: Any, arrays: Any, path: str) -> list[Any]:
    if not isinstance(body, list):
        raise StateError(path, "is not a list of items")
    return [decode(v, arrays, f"{path}[{i}]") for i, v in enumerate(body)]


def _decode_set(body: Any, arrays: Any, path: str) -> set[Any]:
    items = _items(body, arrays, path)
    if not all(isinstance(v, (int, str)) for v in items):
        raise StateError(path, "holds items a set of a checkpoint cannot hold")
    return set(items)


def _decode_dict(body: Any, arrays: Any, path: str) -> dict[Any, Any]:
    if not isinstance(body, list) or not all(isinstance(p, list) and len(p) == 2 for p in body):
        raise StateError(path, "is not a list of [key, value] pairs")
    out = {}
    for key, value in body:
        if not isinstance(key, (int, str)) or isinstance(key, bool):
            raise StateError(path, f"has a key {key!r} that is not a number or a name")
        out[key] = decode(value, arrays, f"{path}[{key!r}]")
    return out


def _decode_generator(body: Any, arrays: Any, path: str) -> np.random.Generator:
    if not isinstance(body, dict) or body.get("bit_generator") != "PCG64":
        raise StateError(path, "is not the state of a PCG64 random generator")
    generator = np.random.Generator(np.random.PCG64())
    try:
        generator.bit_generator.state = body
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise StateError(path, f"is not a PCG64 state ({exc})") from None
    return generator


def _decode_object(body: Any, arrays: Any, path: str) -> Any:
    if not (isinstance(body, list) and len(body) == 2 and isinstance(body[1], dict)):
        raise StateError(path, "is not an object")
    name, attrs = body
    cls = classes().get(name) if isinstance(name, str) else None
    if cls is None:
        raise StateError(path, f"is a {str(name)[:40]!r}, which is not part of a checkpoint")
    obj = cls.__new__(cls)  # object.__new__: none of the class's own code runs
    obj.__dict__.update({str(k): decode(v, arrays, f"{path}.{k}") for k, v in attrs.items()})
    return obj


def _decode_method(body: Any, arrays: Any, path: str) -> Any:
    if not (isinstance(body, list) and len(body) == 2):
        raise StateError(path, "is not a method")
    owner = decode(body[1], arrays, f"{path}.__self__")
    if (type(owner).__name__, body[0]) not in METHODS:
        raise StateError(path, f"is a method {str(body[0])[:40]!r} not part of a checkpoint")
    return getattr(owner, body[0])


_DECODERS = {
    "$float": _decode_float,
    "$scalar": _decode_scalar,
    "$array": _decode_array,
    "$tuple": lambda body, arrays, path: tuple(_items(body, arrays, path)),
    "$set": _decode_set,
    "$dict": _decode_dict,
    "$generator": _decode_generator,
    "$object": _decode_object,
    "$method": _decode_method,
}
