import json

from loopback import run_swarmplan, run_swarmplan_on_terminal


def test_run_writes_result_and_figures(tmp_path):
    out = tmp_path / "out"
    done = run_swarmplan(
        ["run", "paper-2uav", "--steps", "30", "--seed", "3", "--out", str(out)], timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "coverage" in done.stdout and "violations" in done.stdout
    result = json.loads((out / "result.json").read_text())
    assert result["steps"] == 30 and result["seed"] == 3
    assert (out / "paths.png").stat().st_size > 10_000 and (out / "coverage.png").exists()
    # the per-target account and its funnel figure
    account = result["target_account"]
    assert len(account["targets"]) == len(result["targets"])
    assert account["totals"]["engaged"] == result["engaged_count"]
    assert (out / "targets.png").stat().st_size > 10_000
    assert "conversion" in done.stdout


def test_json_flag_prints_only_the_result(tmp_path):
    done = run_swarmplan(
        ["run", "paper-2uav", "--steps", "5", "--json", "--out", str(tmp_path)], timeout=120
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    for key in ("scenario", "algorithm", "seed", "steps", "coverage", "coverage_curve",
                "coverage_slope_50", "engaged_count", "engaged_value", "min_separation_km",
                "returned_count", "violations", "wall_time_s"):  # fmt: skip
        assert key in result
    assert set(result["violations"]) == {"threat", "separation", "turn", "range"}


def test_bad_input_gives_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = 3\n[[targets]]\nkind='x'\n")
    for args in (["run", "no-such-scenario"], ["run", str(bad)],
                 ["run", "paper-2uav", "--steps", "0"],
                 ["run", "paper-2uav", "--seed", "abc"]):  # fmt: skip
        done = run_swarmplan(args, timeout=120)
        assert done.returncode == 2, args
        assert "Traceback" not in done.stderr
        assert "error" in done.stderr.strip().splitlines()[-1]


def test_demo_refuses_bad_seed_and_steps_before_starting_anything(tmp_path):
    out = tmp_path / "demo"
    for args in (["--seed", "-1"], ["--steps", "0"], ["--seed", "abc"]):
        done = run_swarmplan(["demo", "paper-2uav", *args, "--out", str(out)], timeout=30)
        assert done.returncode == 2, args
        assert "Traceback" not in done.stderr
        assert "error" in done.stderr.strip().splitlines()[-1]
        assert not out.exists(), args  # refused by argparse: no simulator, no output folder


def test_progress_bar_only_on_a_terminal_and_one_summary_line(tmp_path):
    """stderr a pipe: no ``\\r`` bar in it; stderr a terminal: the bar. stdout ends with one line
    naming the folder and how many files are in it (not every path)."""
    piped = tmp_path / "piped"
    done = run_swarmplan(["run", "paper-2uav", "--steps", "20", "--out", str(piped)], timeout=120)
    assert done.returncode == 0, done.stderr
    assert "\r" not in done.stderr and "step" not in done.stderr, done.stderr
    files = [p for p in piped.rglob("*") if p.is_file()]
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith(f"written: {piped}/ (result.json, ") and last.endswith(
        f"; {len(files)} files)"
    ), last
    assert str(piped) not in last[len(f"written: {piped}") :], last  # the folder once
    assert sum("written" in line for line in done.stdout.splitlines()) == 1
    # the home count says when it was taken (not "returned home 0 of 2", read as a failure)
    home = [line for line in done.stdout.splitlines() if line.startswith("at home ")]
    assert len(home) == 1 and home[0].endswith(" of 2 at the last decision step"), home
    assert "returned home" not in done.stdout

    status, _, shown = run_swarmplan_on_terminal(
        ["run", "paper-2uav", "--steps", "20", "--out", str(tmp_path / "tty")], timeout=120
    )
    assert status == 0
    assert "\r" in shown and "paper-2uav seed 1" in shown, shown


def test_summary_of_a_mavlink_result_says_rtl_came_after_the_home_count():
    """The daemon prints its summary right after "RTL sent to every vehicle": the home count is
    the last decision step's, before that RTL, and the line says so."""
    from planner.metrics import format_summary
    from planner.scenario import load_scenario
    from sim_gateway.offline_runner import run_offline

    result = run_offline(load_scenario("paper-2uav"), 1, 3, "hapf-aco")
    offline = format_summary(result).splitlines()
    over_mavlink = format_summary({**result, "source": "mavlink"}).splitlines()
    home = [line for line in over_mavlink if line.startswith("at home ")]
    assert home == [f"at home         {result['returned_count']} of 2 at the last decision step; "
                    "RTL sent after it"]  # fmt: skip
    assert [line for line in offline if line.startswith("at home ")] == [home[0].split(";")[0]]
