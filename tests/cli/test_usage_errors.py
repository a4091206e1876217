"""A usage error of any ``swarmplan`` subcommand is one line on stderr naming the problem and
where the fix is (``--help``), exit status 2: argparse's 3-6 line usage block is gone (README:
"Every error caused by input is one line on stderr with exit status 2")."""

from __future__ import annotations

import subprocess
import sys

import pytest
from loopback import REPO, env

from swarmplan.cli import SUBCOMMANDS, main

#: (arguments, words the one line must hold): for every subcommand an unknown option, a value of
#: the wrong kind, a non-finite number where one is taken, a missing argument where one is needed.
CASES = [
    (["run", "paper-2uav", "--bogus"], "unrecognized arguments: --bogus"),
    (["run", "paper-2uav", "--seed", "x"], "--seed"),
    (["run", "paper-2uav", "--steps", "0"], "--steps"),
    (["run", "paper-2uav", "--algorithm", "nope"], "--algorithm"),
    (["run"], "required: scenario"),
    (["demo", "--bogus"], "unrecognized arguments: --bogus"),
    (["demo", "--seed", "-1"], "--seed"),
    (["demo", "--speedup", "nan"], "--speedup"),
    (["demo", "--speedup", "1e400"], "--speedup"),
    (["demo", "--speedup", "0"], "--speedup"),
    (["sim", "--bogus"], "unrecognized arguments: --bogus"),
    (["sim", "--seed", "1.5"], "--seed"),
    (["sim", "--speedup", "inf"], "--speedup"),
    (["sim", "--boot-s", "nan"], "--boot-s"),
    (["sim", "--vehicles", "0"], "--vehicles"),
    (["sim", "--gcs-port", "70000"], "--gcs-port"),
    (["payload", "--connect", "tcp:127.0.0.1:5762", "--bogus"], "unrecognized arguments: --bogus"),
    (["payload", "--vehicles", "0"], "--vehicles"),
    (["payload", "--min-look-altitude", "nan"], "--min-look-altitude"),
    (["payload", "--connect", "bogus"], "--connect: 'bogus' is not an endpoint"),
    (["payload", "--connect", "tcp:127.0.0.1:99999"], "--connect: 'tcp:127.0.0.1:99999'"),
    (["payload"], "required: --connect"),
    (["radio-relay"], "required: --connect"),
    (["radio-relay", "--connect", "bogus"], "--connect: 'bogus' is not an endpoint"),
    (
        ["radio-relay", "--connect", "tcp:127.0.0.1:5760", "--radio-range-km", "nan"],
        "--radio-range-km",
    ),
    (["daemon", "--bogus"], "unrecognized arguments: --bogus"),
    (["daemon", "--seed", "x"], "--seed"),
    (["daemon", "--timeout", "inf"], "--timeout"),
    (["daemon", "--lost-after", "nan"], "--lost-after"),
    (["daemon", "--time-scale", "-2"], "--time-scale"),
    (["daemon", "--threat-margin-km", "1e400"], "--threat-margin-km"),
    (["daemon", "--ready-timeout", "0"], "--ready-timeout"),
    (["daemon", "--expect", "0"], "--expect"),
    (["daemon", "--steps", "two"], "--steps"),
    (["daemon", "--airspeed-range", "100:inf"], "--airspeed-range"),
    (["demo", "--onboard", "--radio-loss", "nan"], "--radio-loss"),
    (["node", "paper-2uav", "--connect", "udpin:127.0.0.1:0", "--uav", "-1"], "--uav"),
    (
        [
            "node",
            "paper-2uav",
            "--connect",
            "udpin:127.0.0.1:0",
            "--uav",
            "0",
            "--system-id",
            "256",
        ],
        "--system-id",
    ),
    (["node", "paper-2uav", "--uav", "0"], "required: --connect"),
    (
        ["node", "paper-2uav", "--connect", "udpin:127.0.0.1:0", "--uav", "0", "--bogus"],
        "unrecognized arguments: --bogus",
    ),
    (["export", "--bogus", "x"], "unrecognized arguments: --bogus"),
    (["export"], "required: result"),
    (["export", "somewhere", "--format", "pdf"], "--format"),
    (["account", "somewhere"], "required: --truth"),
    (["account", "--truth", "t.json"], "required: run"),
    (["account", "somewhere", "--truth", "t.json", "--bogus"], "unrecognized arguments: --bogus"),
    (["experiment", "swarm", "--bogus"], "unrecognized arguments: --bogus"),
    (["experiment"], "required: experiment"),
    (["view"], "required: result_dir"),
    (["view", "somewhere", "--port", "x"], "--port"),
    (["view", "somewhere", "--bogus"], "unrecognized arguments: --bogus"),
    (["nope"], "invalid choice: 'nope'"),
]


def test_every_subcommand_has_cases():
    assert {name for name, _ in SUBCOMMANDS} <= {args[0] for args, _ in CASES}


@pytest.mark.parametrize(("args", "words"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_usage_error_is_one_line_naming_problem_and_fix(capsys, args, words):
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    prog = "swarmplan" if args[0] == "nope" else f"swarmplan {args[0]}"
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    assert words in lines[0] and f"see '{prog} --help'" in lines[0]
    assert "usage:" not in captured.err and not captured.out


def test_usage_errors_of_the_real_command_line():
    """Real processes (started together: they only parse and exit; every one imports every
    subcommand, so three stand for all)."""
    first = {args[0]: args for args, _ in reversed(CASES)}
    cases = {name: first[name] for name in ("run", "daemon", "nope")}
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-m", "swarmplan", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env(),
            cwd=REPO,
        )
        for name, args in cases.items()
    }
    try:
        for name, proc in procs.items():
            out, err = proc.communicate(timeout=120)
            assert proc.returncode == 2, (name, err)
            assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (name, err)
            assert "error:" in err and "--help" in err and not out, (name, err)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.parametrize(
    "args",
    [["sim", "--scenario", "swarm-500uav", "--quiet"], ["sim", "--vehicles", "251", "--quiet"]],
)
def test_a_simulator_of_more_vehicles_than_one_mavlink_network_holds_is_one_line(capsys, args):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "250" in err, err
