"""Every bad input to ``swarmplan experiment`` is one line on stderr and exit status 2."""

import pytest

from swarmplan.cli import main as swarmplan


def run(capsys, *args):
    try:
        code = swarmplan(["experiment", *args])
    except SystemExit as exc:  # argparse-level errors
        code = exc.code
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["nope"], "unknown experiment"),
        ([], "required"),
        (["efficiency", "--runs", "0"], "--runs"),
        (["efficiency", "--runs", "many"], "--runs"),
        (["efficiency", "--jobs", "0"], "--jobs"),
        (["efficiency", "--seed-base", "-1"], "--seed-base"),
        (["efficiency", "--steps", "1.5"], "--steps"),
        (["efficiency", "--algorithms", "pso,nope"], "unknown algorithm"),
        (["efficiency", "--algorithms", "pso,pso"], "twice"),
        (["swarm", "--dask", "localhost:8786"], "scheduler address"),
        (["swarm", "--dask", "tcp://127.0.0.1:8786", "--jobs", "2"], "not both"),
        (["swarm", "--bogus"], "unrecognized"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, args, words):
    code, lines = run(capsys, *args, *(["--out", str(tmp_path / "o")] if args else []))
    assert code == 2
    assert len(lines) == 1, lines
    assert "error" in lines[0] and words in lines[0]
    assert not (tmp_path / "o").exists()  # nothing started


def test_out_that_is_a_file_is_refused(capsys, tmp_path):
    target = tmp_path / "file.txt"
    target.write_text("keep me")
    code, lines = run(capsys, "efficiency", "--out", str(target))
    assert code == 2 and len(lines) == 1 and "is a file" in lines[0]
    assert target.read_text() == "keep me"
