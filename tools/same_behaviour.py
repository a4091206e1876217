"""Record what the planner and the daemon decide, and show that a change of the code's shape
left it unchanged: the result of offline runs (seeds 1-3 of every paper scenario) and of the
lockstep demo (seeds 1-3 of paper-10uav) is compared key by key with a recording.

    python tools/same_behaviour.py record runs/behaviour.json   # before the change
    python tools/same_behaviour.py compare runs/behaviour.json  # after it: exit 1 on a difference

What is compared: every field of each run's result.json (tracks, engagements, coverage and
engagement curves, decision modes, violations, the track account and the simulator's truth of a
demo...), except the few that measure the machine rather than the mission (:data:`MACHINE`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

PAPER = ("paper-2uav", "paper-10uav", "paper-20uav")
ROOT = Path(__file__).resolve().parent.parent
OFFLINE = [(name, seed) for name in PAPER for seed in (1, 2, 3)]
DEMO = [("paper-10uav", seed) for seed in (1, 2, 3)]
#: fields that depend on the machine, the ports or the folder, not on what was decided (the
#: demo signs by default: its signing counts are frame counts, as frames_received is)
MACHINE = {"wall_time_s", "endpoints", "tlog", "frames_received", "signing"}


def _run(kind: str, scenario: str, seed: int, folder: Path) -> dict:
    out = folder / f"{kind}-{scenario}-{seed}"
    # this checkout's code, whatever swarmplan is installed: ``-m`` from the project's root
    command = [sys.executable, "-m", "swarmplan", kind, scenario, "--seed", str(seed)]
    command += ["--out", str(out)]
    if kind == "demo":
        command.append("--no-view")
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    if done.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    result = json.loads((out / "result.json").read_text())
    return {key: value for key, value in result.items() if key not in MACHINE}


def record_all(offline_only: bool = False) -> dict[str, dict]:
    runs: dict[str, dict] = {}
    kinds = (("run", OFFLINE),) if offline_only else (("run", OFFLINE), ("demo", DEMO))
    with tempfile.TemporaryDirectory() as tmp:
        for kind, cases in kinds:
            for scenario, seed in cases:
                name = f"{kind} {scenario} seed {seed}"
                print(name, flush=True)
                runs[name] = _run(kind, scenario, seed, Path(tmp))
    return runs


def differences(before: object, after: object, where: str = "") -> list[str]:
    """Where ``after`` differs from ``before`` (paths into the JSON)."""
    if isinstance(before, dict) and isinstance(after, dict):
        found = [f"{where}.{k}: only before" for k in before.keys() - after.keys()]
        found += [f"{where}.{k}: only after" for k in after.keys() - before.keys()]
        for key in before.keys() & after.keys():
            found += differences(before[key], after[key], f"{where}.{key}")
        return found
    if isinstance(before, list) and isinstance(after, list) and len(before) == len(after):
        found = []
        for i, (b, a) in enumerate(zip(before, after, strict=True)):
            found += differences(b, a, f"{where}[{i}]")
        return found
    return [] if before == after else [f"{where}: {str(before)[:60]} -> {str(after)[:60]}"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("record", "compare"))
    parser.add_argument("file", type=Path)
    parser.add_argument("--offline-only", action="store_true", help="skip the demos")
    args = parser.parse_args()
    runs = record_all(args.offline_only)
    if args.action == "record":
        args.file.parent.mkdir(parents=True, exist_ok=True)
        args.file.write_text(json.dumps(runs))
        print(f"recorded {len(runs)} runs in {args.file}")
        return 0
    before = json.loads(args.file.read_text())
    changed = 0
    for name in runs:
        recorded = {key: value for key, value in before[name].items() if key not in MACHINE}
        found = differences(recorded, runs[name])
        changed += bool(found)
        print(f"{name}: {'identical' if not found else f'{len(found)} differences'}")
        for line in found[:5]:
            print(f"    {line}")
    print("all identical" if not changed else f"{changed} of {len(runs)} runs differ")
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())
