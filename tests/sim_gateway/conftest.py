"""Fixtures for the simulator tests (the harness itself is in sim_harness.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sim_harness import GroundStation, RunningSim, start_sim


@pytest.fixture
def gcs() -> Iterator[GroundStation]:
    station = GroundStation()
    yield station
    station.close()


@pytest.fixture
def sim_factory(gcs: GroundStation) -> Iterator:
    started: list[RunningSim] = []

    def factory(**options) -> RunningSim:
        running = start_sim(gcs.port, **options)
        started.append(running)
        gcs.ensure_peer()
        return running

    yield factory
    for running in started:
        running.close()
