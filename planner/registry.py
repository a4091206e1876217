"""Planners by the name users give on the command line (``swarmplan run --algorithm NAME``,
``swarmplan experiment --algorithms A,B``): the paper's three, and any a Python package
registers under the entry point group :data:`ENTRY_POINT_GROUP`::

    # pyproject.toml of the package that holds the planner
    [project.entry-points."swarmplan.planners"]
    mine = "my_package.my_planner:MyPlanner"

The object an entry point names is a :data:`planner.planner_interface.PlannerFactory` (a class
built as ``MyPlanner(scenario, starts, seed)`` whose instances have ``step``, see
``planner.planner_interface``). A built-in name cannot be taken by a plug-in.
"""

from __future__ import annotations

from importlib.metadata import entry_points

from planner.acoapf import AcoApfPlanner
from planner.errors import UserError
from planner.hapf_aco import HapfAcoPlanner
from planner.planner_interface import PlannerFactory
from planner.pso import PsoPlanner

ENTRY_POINT_GROUP = "swarmplan.planners"

#: The paper's planners: HAPF-ACO (section 3) and its baselines (section 4.2).
BUILT_IN: dict[str, PlannerFactory] = {
    "hapf-aco": HapfAcoPlanner,
    "acoapf": AcoApfPlanner,  # baseline, section 4.2 Algorithm 2
    "pso": PsoPlanner,  # baseline, section 4.2 Algorithm 1
}


#: Planners registered in this process (``register``), e.g. from a notebook or a benchmark.
_REGISTERED: dict[str, PlannerFactory] = {}


class UnknownPlannerError(UserError):
    """An algorithm name no planner answers to, or a plug-in that cannot be loaded."""


def register(name: str, factory: PlannerFactory) -> None:
    """Make ``factory`` answer to ``name`` in this process (an entry point does it for every
    process of an installed package)."""
    if name in BUILT_IN:
        raise ValueError(f"{name!r} is a built-in planner's name; choose another")
    _REGISTERED[name] = factory


def planner_names() -> list[str]:
    """Every name a planner answers to: the built-in ones and the registered plug-ins."""
    plugged = {ep.name for ep in entry_points(group=ENTRY_POINT_GROUP)}
    return sorted(set(BUILT_IN) | set(_REGISTERED) | plugged)


def planner_factory(name: str) -> PlannerFactory:
    """The factory of planner ``name``; one :class:`UnknownPlannerError` line if there is none or
    its plug-in fails to load."""
    if name in BUILT_IN or name in _REGISTERED:
        return BUILT_IN.get(name) or _REGISTERED[name]
    found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not found:
        raise UnknownPlannerError(
            f"unknown algorithm {name!r}; choose from {', '.join(planner_names())} (a planner "
            f"of your own is registered under the entry point group {ENTRY_POINT_GROUP!r})"
        )
    try:
        factory = found[0].load()
    except Exception as exc:  # noqa: BLE001 - a plug-in's import error is the user's to fix
        raise UnknownPlannerError(
            f"planner {name!r} ({found[0].value}) cannot be loaded: {type(exc).__name__}: {exc}"
        ) from None
    if not callable(factory):
        raise UnknownPlannerError(
            f"planner {name!r} ({found[0].value}) is not a class or function that builds a "
            f"planner as factory(scenario, starts, seed)"
        )
    return factory
