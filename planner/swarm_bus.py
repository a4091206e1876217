"""An in-process bus between the N planners of a swarm without a centre
(``planner.uav_node.UavNode``): it carries their messages (``planner.swarm_messages``) through a
link model (range in km between the UAVs, loss probability, seeded) and drives the step's four
exchanges. ``NodeSwarmPlanner`` is the whole swarm on such a bus as a
``planner.planner_interface.SwarmPlanner``: on a lossless link of unlimited range it decides what
the batched ``planner.hapf_aco.HapfAcoPlanner`` decides, bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from planner.engagement import EngagementOutcome
from planner.grid import Grid
from planner.planner_interface import StepDecision
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport
from planner.swarm_messages import CellClaim, Message
from planner.uav_node import ClaimStats, UavNode


@dataclass(frozen=True)
class LinkModel:
    """The radio between the UAVs: a broadcast reaches the UAVs within ``range_km`` (inf:
    everyone), each of them missing it with probability ``loss`` (0..1), drawn from ``seed``."""

    range_km: float = math.inf
    loss: float = 0.0
    seed: int = 0

    @property
    def perfect(self) -> bool:
        return math.isinf(self.range_km) and self.loss == 0.0


@dataclass
class LinkStats:
    """What the link carried over a mission (one broadcast: one sender's messages of one
    exchange)."""

    broadcasts: int = 0
    messages: int = 0
    delivered: int = 0  # (broadcast, receiver) pairs that arrived
    out_of_range: int = 0
    lost: int = 0


@dataclass
class SwarmBus:
    """The nodes and the link between them (see the module's docstring)."""

    nodes: list[UavNode]
    link: LinkModel = field(default_factory=LinkModel)
    stats: LinkStats = field(default_factory=LinkStats)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng([self.link.seed, 0xB05])

    def send(self, sender: int, messages: Sequence[Message], positions_km: np.ndarray) -> set[int]:
        """Broadcast ``messages`` of UAV ``sender``; returns the UAVs that heard them."""
        if not messages:
            return set()
        self.stats.broadcasts += 1
        self.stats.messages += len(messages)
        heard: set[int] = set()
        gaps = np.hypot(*(positions_km - positions_km[sender]).T)
        for j, node in enumerate(self.nodes):
            if j == sender:
                continue
            if gaps[j] > self.link.range_km:
                self.stats.out_of_range += 1
                continue
            if self.link.loss > 0 and self.rng.random() < self.link.loss:
                self.stats.lost += 1
                continue
            self.stats.delivered += 1
            heard.add(j)
            for message in messages:
                node.receive(message)
        return heard

    def step(
        self, cells: np.ndarray, headings: np.ndarray, reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None, active: np.ndarray,
        positions_km: np.ndarray, measured_km: np.ndarray | None = None,
    ) -> StepDecision:  # fmt: skip
        """One decision step of every node; ``positions_km``: where the UAVs are (the link's
        range); ``measured_km``: where they measure themselves (None: their cells' centres)."""
        nodes, n = self.nodes, len(self.nodes)
        outcomes = [None] * n if engagements is None else list(engagements)
        sent = [
            node.begin(cells[i], int(headings[i]), reports[i], outcomes[i], bool(active[i]),
                       None if measured_km is None else measured_km[i])
            for i, node in enumerate(nodes)
        ]
        for i in range(n):
            self.send(i, sent[i], positions_km)
        sent = [node.hear() for node in nodes]
        for i in range(n):
            self.send(i, sent[i], positions_km)
        for node in nodes:
            node.rank()
        for i in sorted(range(n), key=lambda i: nodes[i].priority):
            self._claim(i, positions_km)
        rows = [node.finish() for node in nodes]
        return StepDecision(*(np.concatenate([getattr(r, f) for r in rows]) for f in (
            "next_cells", "next_headings", "engage", "done", "modes")))  # fmt: skip

    def _claim(self, i: int, positions_km: np.ndarray) -> None:
        """Node ``i``'s turn in C_c's order; a request to a blocker to step aside is answered
        before the next node's turn (the deadline), and ``i`` says how it ended, as on the
        radio: its claim is final (answered), or it holds."""
        claims = self.nodes[i].claim()
        heard = self.send(i, claims, positions_km)
        for claim in claims:
            if not isinstance(claim, CellClaim) or claim.displace is None:
                continue
            j = claim.displace[0]
            answer = self.nodes[j].answer(claim) if j in heard else []
            answered = i in self.send(j, answer, positions_km)
            self.nodes[i].displaced(answered)
            end = dataclasses.replace(claim, displace=None) if answered else None
            self.send(i, [end or self.nodes[i].hold_claim()], positions_km)


class NodeSwarmPlanner:
    """The swarm as N ``UavNode`` on a ``SwarmBus`` (``planner.planner_interface.SwarmPlanner``):
    ``NodeSwarmPlanner(scenario, starts, seed, link)``."""

    algorithm = "hapf-aco-nodes"

    def __init__(
        self, scenario: Scenario, starts: Sequence[UavStart], seed: int,
        link: LinkModel | None = None,
    ) -> None:  # fmt: skip
        self.n = len(starts)
        cfg = scenario.config
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        nodes = [UavNode(scenario, starts, seed, i) for i in range(self.n)]
        # C_t's models depend on the scenario and the threats known alone: in one process the
        # nodes share them (each of N companion computers would build its own)
        for node in nodes[1:]:
            node.beliefs.share_safety_models(nodes[0].beliefs)
        self.bus = SwarmBus(nodes, link or LinkModel())

    @property
    def nodes(self) -> list[UavNode]:
        return self.bus.nodes

    def claim_stats(self) -> ClaimStats:
        """C_c's deadlines over the swarm, summed."""
        total = ClaimStats()
        for node in self.nodes:
            for name in vars(total):
                setattr(total, name, getattr(total, name) + getattr(node.stats, name))
        return total

    def step(
        self, cells: np.ndarray, headings: np.ndarray, reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None = None,
        active: np.ndarray | None = None, positions_km: np.ndarray | None = None,
    ) -> StepDecision:  # fmt: skip
        cells = np.asarray(cells, dtype=np.int64).reshape(self.n, 2)
        active = np.ones(self.n, dtype=bool) if active is None else np.asarray(active, bool)
        where = self.grid.centre_km(cells) if positions_km is None else np.asarray(positions_km)
        return self.bus.step(
            cells, np.asarray(headings), reports, engagements, active, where, positions_km
        )
