"""The planes' telemetry radio in the simulator: the swarm link between the planner nodes
(docs/onboard.md, "The radio in the simulator").

A node talks to its own vehicle's endpoint, as a companion computer on a serial port of its
autopilot. A TUNNEL frame of the swarm payload type (``mavlink_wire.swarm_wire``) that vehicle i
receives from its node is broadcast on one radio channel shared by the whole swarm and reaches
the node of every other vehicle j (sent from vehicle j's socket to its ground-station address,
``--per-vehicle-ports`` giving each node its own) that is:

* within ``range_km`` of i (straight-line distance between the planes, altitude included, when
  the frame is sent), else it is lost to range;
* not lost: each receiver in range loses it independently with probability ``loss`` (drawn
  from a random stream of its own, seeded from the simulator's seed: the same seed loses the
  same frames of the same traffic, and the world's randomness is untouched);
* and only once the channel carried it: with ``kbps`` set, frames go out one after another at
  that rate (``len * 8 / kbps`` ms each, the channel shared by all vehicles); a frame that would
  wait more than one decision period (``step_s``) behind the queue is dropped for bandwidth.
  It arrives ``latency_ms`` after it left the channel.

Time is the simulator's: a frame due later than now is delivered at the first physics tick at
or after its due time (in lockstep, once the ground station grants time on). With no latency
and no bandwidth limit a frame is passed on at once, in the same loop pass it arrived in.
Frames are passed on byte for byte (a signed frame keeps its signature: the receiving node
checks it, as a radio cannot sign). Defaults: unlimited range, no loss, no latency, no
bandwidth limit.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np

from mavlink_wire.protocol import mavlink
from mavlink_wire.swarm_wire import SWARM_PAYLOAD_TYPE
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.mavlink_endpoint import VehicleSocket
from sim_gateway.sim_options import RadioOptions

#: the radio's own random stream: SeedSequence([seed, RADIO_STREAM]) (not the world's)
RADIO_STREAM = 0x52414449


@dataclass
class RadioStats:
    """What the radio carried: frames sent by the nodes, deliveries to receivers, and why the
    others were not (per receiver for range and loss, per frame for bandwidth); bytes per
    vehicle."""

    frames_sent: int = 0
    delivered: int = 0
    lost_to_range: int = 0
    lost_to_loss: int = 0
    dropped_for_bandwidth: int = 0
    unrouted: int = 0  # fed in directly from a system that is none of the vehicles
    bytes_sent: list[int] = field(default_factory=list)
    bytes_received: list[int] = field(default_factory=list)

    def summary(self) -> dict[str, object]:
        return {
            "frames_sent": self.frames_sent,
            "delivered": self.delivered,
            "lost_to_range": self.lost_to_range,
            "lost_to_loss": self.lost_to_loss,
            "dropped_for_bandwidth": self.dropped_for_bandwidth,
            "unrouted": self.unrouted,
            "bytes_sent": list(self.bytes_sent),
            "bytes_received": list(self.bytes_received),
        }


def is_swarm_frame(message: mavlink.MAVLink_message) -> bool:
    """A TUNNEL message of the swarm link's payload type."""
    return message.get_type() == "TUNNEL" and message.payload_type == SWARM_PAYLOAD_TYPE


class SwarmRadio:
    """The radio between a simulator's vehicles: ``sockets[i]`` is vehicle i's (what it sends
    reaches its node), ``fleet`` gives the planes' positions (``x_m``, ``y_m``, ``alt_m``)."""

    def __init__(
        self, options: RadioOptions, sockets: list[VehicleSocket], fleet: FleetKinematics, seed: int
    ) -> None:
        options.validate()
        self.options = options
        self.sockets = sockets
        self.fleet = fleet
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, RADIO_STREAM]))
        #: a frame that would wait longer than this behind the channel's queue is dropped (the
        #: simulator sets one decision period)
        self.backlog_limit_s = 10.0
        n = len(sockets)
        self.stats = RadioStats(bytes_sent=[0] * n, bytes_received=[0] * n)
        self.channel_free_s = 0.0
        self.queue: list[tuple[float, int, int, bytes]] = []  # (due s, order, receiver, frame)
        self.order = 0

    def on_frame(
        self, message: mavlink.MAVLink_message, sock: VehicleSocket | None, now_s: float
    ) -> None:
        """A swarm-link frame that came in on ``sock`` (from the node of that socket's vehicle;
        fed in directly: the vehicle of its source system), at simulated ``now_s``."""
        sender = next((i for i, s in enumerate(self.sockets) if s is sock), None)
        if sender is None:
            system = message.get_srcSystem()
            if not 1 <= system <= len(self.sockets):
                self.stats.unrouted += 1
                return
            sender = system - 1
        fleet = self.fleet
        positions = np.column_stack([fleet.x_m, fleet.y_m, fleet.alt_m])
        frame = bytes(message.get_msgbuf())
        self._send(self.transmit(sender, frame, positions, now_s))

    def deliver_due(self, now_s: float) -> None:
        """Pass on the queued frames due by simulated ``now_s`` (called every physics tick)."""
        if self.queue:
            self._send(self.due(now_s))

    def _send(self, deliveries: list[tuple[int, bytes]]) -> None:
        for receiver, frame in deliveries:
            self.sockets[receiver].send(frame)

    def transmit(
        self, sender: int, frame: bytes, positions_m: np.ndarray, now_s: float
    ) -> list[tuple[int, bytes]]:
        """Vehicle ``sender`` got ``frame`` from its node at simulated ``now_s``: the
        deliveries due now ``(receiver, frame)``; later ones are queued (:meth:`due`)."""
        opts, stats = self.options, self.stats
        stats.frames_sent += 1
        stats.bytes_sent[sender] += len(frame)
        leaves_s = now_s
        if math.isfinite(opts.kbps):
            start = max(now_s, self.channel_free_s)
            if start - now_s > self.backlog_limit_s:
                stats.dropped_for_bandwidth += 1
                return []
            leaves_s = self.channel_free_s = start + len(frame) * 8 / (opts.kbps * 1000.0)
        due_s = leaves_s + opts.latency_ms / 1000.0
        distance = np.linalg.norm(positions_m - positions_m[sender], axis=1) / 1000.0
        now: list[tuple[int, bytes]] = []
        for receiver in range(len(positions_m)):
            if receiver == sender:
                continue
            if not distance[receiver] <= opts.range_km:  # (NaN: a plane not located yet)
                stats.lost_to_range += 1
                continue
            if opts.loss > 0 and self.rng.random() < opts.loss:
                stats.lost_to_loss += 1
                continue
            if due_s <= now_s:
                now.append((receiver, frame))
            else:
                heapq.heappush(self.queue, (due_s, self.order, receiver, frame))
                self.order += 1
        self._count(now)
        return now

    def due(self, now_s: float) -> list[tuple[int, bytes]]:
        """Queued deliveries due by simulated ``now_s``, in order."""
        out = []
        while self.queue and self.queue[0][0] <= now_s + 1e-9:
            _, _, receiver, frame = heapq.heappop(self.queue)
            out.append((receiver, frame))
        self._count(out)
        return out

    def _count(self, deliveries: list[tuple[int, bytes]]) -> None:
        for receiver, frame in deliveries:
            self.stats.delivered += 1
            self.stats.bytes_received[receiver] += len(frame)
