"""The onboard swarm against the central planner, offline: paper-10uav over seeds, the central
HAPF-ACO run beside the node swarm (``planner.swarm_bus.NodeSwarmPlanner``, one ``UavNode`` per
UAV on the in-process bus) under a link model of radio loss x range; prints a markdown table
(docs/onboard.md, "Onboard against central, offline").

python benchmarks/onboard_table.py [--seeds 1-10] [--steps 250] [--jobs 2]
                                   [--losses 0 10 30] [--ranges 10 20 50]

Each run flies ``sim_gateway.offline_runner.run_offline``: the planner's grid world, not the
simulator, so the violations are the offline recorder's (threat / separation / turn / range at
the decision steps and on the straight legs between them). Every broadcast of a node is encoded
as the swarm link would carry it (``mavlink_wire.node_wire`` report, ``mavlink_wire.swarm_wire``
TUNNEL frames, MAVLink 2, signed) and its bytes are counted against the sender and step, heard
or not. The perfect link (unlimited range, no loss) is run too, as a check: it must fly exactly
the central run's tracks and engagements.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import dataclass  # noqa: E402

from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from mavlink_wire.node_wire import NodeWire  # noqa: E402
from mavlink_wire.signing import mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_wire import SwarmSender  # noqa: E402
from planner.registry import register  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from planner.swarm_bus import LinkModel, NodeSwarmPlanner, SwarmBus  # noqa: E402
from sim_gateway.offline_runner import run_offline  # noqa: E402

SCENARIO = "paper-10uav"


@dataclass(frozen=True)
class Condition:
    """Central (``range_km`` None) or the node swarm on a link of ``range_km`` (inf: any) and
    ``loss`` (0..1)."""

    range_km: float | None
    loss: float = 0.0

    @property
    def label(self) -> str:
        if self.range_km is None:
            return "central (hapf-aco)"
        reach = "unlimited" if math.isinf(self.range_km) else f"{self.range_km:g} km"
        return f"nodes, {reach}, loss {self.loss * 100:g} %"


class CountingBus(SwarmBus):
    """The in-process bus; every broadcast is also packed into signed TUNNEL frames, whose bytes
    are added to ``sent_bytes[(sender, step)]``."""

    wire: NodeWire
    sent_bytes: dict[tuple[int, int], int]

    def attach(self, wire: NodeWire) -> CountingBus:
        self.wire, self.sent_bytes, key = wire, {}, mission_key()
        self.senders = [SwarmSender(i) for i in range(len(self.nodes))]
        self.encoders = []
        for i in range(len(self.nodes)):
            mav = ml.MAVLink(None, srcSystem=i + 1, srcComponent=191)
            sign_outgoing(mav, key, link_id=i)
            self.encoders.append(mav)
        return self

    def send(self, sender, messages, positions_km):
        if messages:
            step = messages[0].step
            report = self.wire.report(sender, step, messages)
            frames = self.senders[sender].frames(report, self.encoders[sender])
            key = (sender, step)
            self.sent_bytes[key] = self.sent_bytes.get(key, 0) + sum(len(f) for f in frames)
        return super().send(sender, messages, positions_km)


def _fingerprint(result: dict) -> str:
    """A digest of the tracks and engagements (equal digests: the same flight)."""
    flown = [[u["track_km"] for u in result["uavs"]], result["engagements"]]
    return hashlib.sha256(json.dumps(flown).encode()).hexdigest()[:16]


def run_one(seed: int, steps: int, condition: Condition) -> dict:
    """One mission of ``condition``: the table's figures for it."""
    scenario = load_scenario(SCENARIO)
    built: list[NodeSwarmPlanner] = []
    if condition.range_km is None:
        algorithm = "hapf-aco"
    else:
        link = LinkModel(condition.range_km, condition.loss, seed)

        def factory(scenario_, starts, seed_):
            planner = NodeSwarmPlanner(scenario_, starts, seed_, link)
            planner.bus = CountingBus(planner.nodes, link).attach(NodeWire.for_scenario(scenario_))
            built.append(planner)
            return planner

        algorithm = "nodes-table"
        register(algorithm, factory)
    started = time.perf_counter()
    result = run_offline(scenario, seed, steps, algorithm, account=False)
    row = {
        "seed": seed,
        "coverage": 100 * result["coverage"],
        "engaged": result["engaged_count"],
        "home": result["returned_count"],
        "uavs": result["uav_count"],
        "violations": result["violations"],
        "min_separation_km": result["min_separation_km"],
        "fingerprint": _fingerprint(result),
        "wall_s": time.perf_counter() - started,
    }
    if built:
        planner = built[-1]
        n = len(planner.nodes)
        per_step = [planner.bus.sent_bytes.get((i, k), 0) for i in range(n) for k in range(steps)]
        row["bytes_mean"] = statistics.fmean(per_step)
        row["bytes_max"] = max(per_step)
        row["claims"] = vars(planner.claim_stats()).copy()
        link = planner.bus.stats
        pairs = link.delivered + link.lost + link.out_of_range
        row["heard_pct"] = 100 * link.delivered / pairs if pairs else 0.0
    return row


def _ms(values: list[float], digits: int = 1) -> str:
    """Mean ± sd."""
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.fmean(values):.{digits}f} ± {sd:.{digits}f}"


def table(conditions: list[Condition], rows: dict[Condition, list[dict]]) -> list[str]:
    """The markdown table: one line per condition, mean ± sd over the seeds."""
    central = {r["seed"]: r["fingerprint"] for r in rows[conditions[0]]}
    out = [
        "| condition | coverage % | engaged | home | violations (threat/sep/turn/range) "
        "| min sep km | heard % | bytes/UAV/step mean | max | claims missed | moved clear "
        "| held | squeezed | swaps unanswered | same as central |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in conditions:
        rs = rows[c]
        v = [sum(r["violations"][k] for r in rs) for k in ("threat", "separation", "turn", "range")]
        home = f"{_ms([r['home'] for r in rs])} / {rs[0]['uavs']}"
        same = sum(central[r["seed"]] == r["fingerprint"] for r in rs)
        closest = min(r["min_separation_km"] for r in rs)
        cells = [c.label, _ms([r["coverage"] for r in rs]), _ms([r["engaged"] for r in rs]), home,
                 "/".join(map(str, v)), f"{closest:.2f}"]  # fmt: skip
        if "claims" in rs[0]:
            claims = [_ms([r["claims"][k] for r in rs]) for k in
                      ("missed", "avoided", "held", "squeezed", "swaps_failed")]  # fmt: skip
            cells += [_ms([r["heard_pct"] for r in rs]), _ms([r["bytes_mean"] for r in rs], 0),
                      str(max(r["bytes_max"] for r in rs)), *claims]  # fmt: skip
        else:
            cells += ["-"] * 8
        cells.append(f"{same}/{len(rs)}" if c.range_km is not None else "-")
        out.append("| " + " | ".join(cells) + " |")
    return out


def _seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=_seeds, default=_seeds("1-10"), help="e.g. 1-10")
    parser.add_argument("--steps", type=int, default=250)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--losses", type=float, nargs="+", default=[0, 10, 30], help="%%")
    parser.add_argument("--ranges", type=float, nargs="+", default=[10, 20, 50], help="km")
    args = parser.parse_args()
    conditions = [Condition(None), Condition(math.inf)] + [
        Condition(r, loss / 100) for loss in args.losses for r in args.ranges
    ]
    started = time.perf_counter()
    rows: dict[Condition, list[dict]] = {c: [] for c in conditions}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        jobs = {pool.submit(run_one, s, args.steps, c): c for c in conditions for s in args.seeds}
        for done, (job, c) in enumerate(jobs.items(), 1):
            rows[c].append(job.result())
            print(
                f"{done}/{len(jobs)} runs, {time.perf_counter() - started:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    for c in conditions:
        rows[c].sort(key=lambda r: r["seed"])
    wall = time.perf_counter() - started
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"{SCENARIO}, seeds {args.seeds[0]}-{args.seeds[-1]}, {args.steps} steps, offline; "
          f"{len(jobs)} runs in {wall:.0f} s wall on {os.cpu_count()} cores, --jobs {args.jobs} "
          f"({platform.processor() or platform.machine()}, Python "
          f"{platform.python_version()}, load average {load})")  # fmt: skip
    print()
    print("\n".join(table(conditions, rows)))


if __name__ == "__main__":
    main()
