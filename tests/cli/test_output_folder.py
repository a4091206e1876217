"""An ``--out`` folder that cannot be written is refused before any work (one line, exit 2) by
every command that writes one: run, demo, daemon, experiment. It used to be found only after the
whole run (run), or after waiting for vehicles (daemon)."""

from __future__ import annotations

import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from loopback import free_udp_port, run_swarmplan_on_terminal


def refuses_files(folder: Path) -> bool:
    try:
        with tempfile.NamedTemporaryFile(dir=folder):
            return False
    except OSError:
        return True


@pytest.fixture
def unwritable(tmp_path: Path) -> Path:
    """An existing folder this process cannot write into: a read-only folder, or for root (who
    writes anywhere) sysfs, which refuses new files."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        if refuses_files(folder):
            yield folder
        elif Path("/sys").is_dir() and refuses_files(Path("/sys")):
            yield Path("/sys")
        else:
            pytest.skip("no folder here refuses to be written to (root without sysfs)")
    finally:
        folder.chmod(0o700)


@pytest.mark.timeout(180)
def test_unwritable_out_is_refused_before_any_work(unwritable: Path, tmp_path: Path):
    """Each command's stderr is a terminal, so a run that started would show its progress bar;
    the daemon would first wait --timeout for vehicles that never come and say so."""
    in_the_way = tmp_path / "a-file"
    in_the_way.write_text("keep me")
    port = free_udp_port()
    commands = {
        "run": ["run", "paper-10uav", "--out", str(unwritable)],
        "run (a file in the way)": ["run", "paper-2uav", "--out", str(in_the_way / "sub")],
        "demo": ["demo", "paper-2uav", "--steps", "2", "--out", str(unwritable)],
        "daemon": [
            "daemon",
            "--connect",
            f"udpin:127.0.0.1:{port}",
            "--timeout",
            "60",
            "--out",
            str(unwritable),
        ],  # fmt: skip
        "experiment": [
            "experiment",
            "efficiency",
            "--runs",
            "1",
            "--steps",
            "2",
            "--out",
            str(unwritable / "exp"),
        ],  # fmt: skip
    }
    with ThreadPoolExecutor(len(commands)) as pool:  # they only check and exit: together
        done = dict(zip(commands, pool.map(lambda a: run_swarmplan_on_terminal(a, 150),
                                           commands.values()), strict=True))  # fmt: skip
    for name, (status, out, err) in done.items():
        err = err.strip()
        assert status == 2, (name, err)
        assert len(err.splitlines()) == 1 and "\r" not in err, (name, err)
        assert "cannot write to" in err and "choose another --out folder" in err, (name, err)
        assert not out, (name, out)
    assert in_the_way.read_text() == "keep me"
