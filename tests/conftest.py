"""Puts the shared helpers in reach: pytest's default ("prepend") import mode inserts the folder
of this file, tests/, on sys.path, so every test folder can ``import loopback``. And keeps the
CPU for the SITL missions: a pytest-xdist worker that runs any other test lowers its priority."""

import os

import pytest

#: how much a pytest-xdist worker lowers its priority (and its children's) once it runs a test
#: outside tests/sitl: the SITL missions fly in real or scaled time and must not starve
#: (with three workers on 2 cores, a PX4 mission at 5x lost all its planes for 4-7 s once)
NICE_BESIDE_SITL = 10
_niced: list[bool] = []


@pytest.fixture(autouse=True)
def _yield_the_cpu_to_sitl(request: pytest.FixtureRequest) -> None:
    if _niced or not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if f"{os.sep}sitl{os.sep}" not in str(request.node.fspath):
        os.nice(NICE_BESIDE_SITL)
        _niced.append(True)
