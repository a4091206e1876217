"""Puts the shared helpers in reach: pytest's default ("prepend") import mode inserts the folder
of this file, tests/, on sys.path, so every test folder can ``import loopback``; and gives the
tests that wait on the wall clock a pytest-xdist worker of their own (tests/xdist_lanes.py)."""


def pytest_xdist_make_scheduler(config, log):
    """Three or more workers under ``--dist loadgroup``: the wall-clock-bound tests get a
    worker of their own (tests/xdist_lanes.py)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist_lanes import RealTimeLane

    return RealTimeLane(config, log)
