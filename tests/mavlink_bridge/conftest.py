"""Shared fixtures: free loopback ports, a small scenario, a fake swarm."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

os.environ.setdefault("MAVLINK20", "1")

from bridge_fake_swarm import FakeSwarm  # noqa: E402
from loopback import free_udp_port  # noqa: E402

from planner.scenario import Scenario, load_scenario  # noqa: E402


@pytest.fixture
def udp_port() -> int:
    return free_udp_port()


@pytest.fixture(scope="session")
def paper10() -> Scenario:
    return load_scenario("paper-10uav")


@pytest.fixture
def fake_swarm_factory(paper10: Scenario) -> Iterator:
    started: list[FakeSwarm] = []

    def make(n: int, port: int, **kwargs: object) -> FakeSwarm:
        swarm = FakeSwarm(
            n, port, lat0=paper10.origin.lat_deg, lon0=paper10.origin.lon_deg, **kwargs
        )
        swarm.start()
        started.append(swarm)
        return swarm

    yield make
    for swarm in started:
        swarm.stop()
