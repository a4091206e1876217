"""Fixtures for tests against the real ArduPlane SITL (tests/sitl/sitl_harness.py).

``sitl_binary``: the binary from ``ARDUPLANE_SITL``, or the test is skipped with the reason.
``sitl_swarm``: a factory ``sitl_swarm(homes, speedup=10, params={...})`` returning a started
:class:`SitlSwarm`; every swarm it made is stopped at teardown (process groups killed).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")

import px4_harness  # noqa: E402
from sitl_harness import SitlSwarm, sitl_binary_from_env, skip_reason  # noqa: E402


@pytest.fixture(scope="session")
def px4_sitl() -> Path:
    """The PX4 SITL folder from ``PX4_SITL`` (tests/sitl/px4_harness.py), or a skip."""
    root = px4_harness.px4_root_from_env()
    if root is None:
        pytest.skip(px4_harness.skip_reason())
    return root


@pytest.fixture(scope="session")
def sitl_binary() -> Path:
    binary = sitl_binary_from_env()
    if binary is None:
        pytest.skip(skip_reason())
    return binary


@pytest.fixture
def sitl_swarm(sitl_binary: Path, tmp_path: Path) -> Iterator:
    started: list[SitlSwarm] = []

    def make(homes, **options) -> SitlSwarm:
        options.setdefault("workdir", tmp_path / f"sitl{len(started)}")
        swarm = SitlSwarm(sitl_binary, homes, **options)
        started.append(swarm)
        swarm.start()
        return swarm

    yield make
    for swarm in started:
        swarm.stop()


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups, however invoked
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under pytest-xdist, the SITL tests run one after another on one worker: each starts
    several autopilot instances, and two missions at once on a 2-core machine would fly late
    (pytest-xdist hands the largest group out first: that worker flies them from the suite's
    start). The tests at real time (marked ``xdist_group("realtime")``) wait on the wall
    clock and run on a lane of their own instead (tests/xdist_lanes.py)."""
    here = Path(__file__).parent
    for item in items:
        grouped = item.get_closest_marker("xdist_group") is not None
        if here in Path(item.fspath).parents and not grouped:
            item.add_marker(pytest.mark.xdist_group("sitl"))
