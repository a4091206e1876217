"""Puts the shared helpers in reach: pytest's default ("prepend") import mode inserts the folder
of this file, tests/, on sys.path, so every test folder can ``import loopback``.

Under pytest-xdist it also keeps the real-time autopilots first in line for the CPU: the SITL
tests fly on the wall clock (tests/sitl), and with three workers on two cores at one priority
ArduPlane SITL missed its pre-arm checks and paced steps came late."""

import os

import pytest

#: how much lower (``os.nice``) a worker runs its tests outside the SITL group, and so every
#: process those tests start
OTHER_TESTS_NICE = 10

_NICED = pytest.StashKey[bool]()


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Under pytest-xdist, a worker lowers its own priority before its first test outside the
    SITL group. pytest-xdist hands the group (all on one worker, tests/sitl/conftest.py) out
    first, so the worker that flies it does so at full priority, and only afterwards takes
    other tests, lowered like every other worker."""
    if not os.environ.get("PYTEST_XDIST_WORKER") or item.config.stash.get(_NICED, False):
        return
    group = item.get_closest_marker("xdist_group")
    if group is None or group.args[:1] != ("sitl",):
        os.nice(OTHER_TESTS_NICE)
        item.config.stash[_NICED] = True
