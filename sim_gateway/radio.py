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

A ground station may listen on the same channel (:class:`GroundRadio`, ``swarmplan sim
--radio-ground-port``): a radio on the ground at a position of the mission frame that hears each
frame under the same rules as a vehicle (range from its antenna, on the ground, to the sender;
its own loss draw, from a stream of its own so that the vehicles' draws are those without it;
the same latency) and passes it to its port. It only listens: it takes no share of the channel
and sends nothing, so the nodes' link is the same with it or without it.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np

from mavlink_wire.protocol import mavlink
from mavlink_wire.swarm_wire import SWARM_PAYLOAD_TYPE
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.mavlink_endpoint import LinkStats, VehicleSocket
from sim_gateway.sim_options import RadioOptions, SimulatorError

#: the radio's own random stream: SeedSequence([seed, RADIO_STREAM]) (not the world's)
RADIO_STREAM = 0x52414449
#: the ground station's loss draws: SeedSequence([seed, RADIO_STREAM, GROUND_STREAM])
GROUND_STREAM = 0x47
#: the receiver index of the ground station in the radio's queue
GROUND = -1


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


@dataclass
class GroundRadio:
    """A ground station's radio on the swarm's channel: at ``x_m``, ``y_m`` of the mission frame
    on the ground (altitude 0, the planes' altitudes being above home), it passes each frame it
    hears to ``sock``'s destination (the coordinator's port). Counts what it heard and why it
    missed the rest."""

    sock: VehicleSocket
    x_m: float
    y_m: float
    rng: np.random.Generator
    delivered: int = 0
    lost_to_range: int = 0
    lost_to_loss: int = 0
    bytes_received: int = 0

    def summary(self) -> dict[str, object]:
        return {
            "position_km": [round(self.x_m / 1000.0, 3), round(self.y_m / 1000.0, 3)],
            "delivered": self.delivered,
            "lost_to_range": self.lost_to_range,
            "lost_to_loss": self.lost_to_loss,
            "bytes_received": self.bytes_received,
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
        self.seed = seed
        #: a ground station listening on the channel (:meth:`listen_on_ground`), or None
        self.ground: GroundRadio | None = None

    def listen_on_ground(
        self, bind_host: str, destination: tuple[str, int], at_km: tuple[float, float]
    ) -> None:
        """A ground station at ``at_km`` hears the channel and passes it on to ``destination``
        (``--radio-ground-port``) from a UDP socket of its own: never read, its sends not
        counted as the vehicles'."""
        try:
            sock = VehicleSocket(bind_host, 0, destination, LinkStats())
        except OSError as exc:
            raise SimulatorError(
                f"cannot open the ground radio's UDP socket on {bind_host} ({exc.strerror}); "
                "choose another --bind-host"
            ) from None
        stream = np.random.SeedSequence([self.seed, RADIO_STREAM, GROUND_STREAM])
        rng = np.random.default_rng(stream)
        self.ground = GroundRadio(sock, at_km[0] * 1000.0, at_km[1] * 1000.0, rng)

    def close(self) -> None:
        """Close the ground station's socket, if one listens."""
        if self.ground is not None:
            self.ground.sock.close()

    def summary(self) -> dict[str, object]:
        """What the radio carried, with the ground station's reception when one listens."""
        out = self.stats.summary()
        if self.ground is not None:
            out["ground"] = self.ground.summary()
        return out

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
            if receiver == GROUND:
                if self.ground is not None:
                    self.ground.sock.send(frame)
            else:
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
            now += self._queue(receiver, frame, due_s, now_s)
        if self.ground is not None:
            now += self._to_ground(sender, frame, positions_m, due_s, now_s)
        self._count(now)
        return now

    def _queue(self, receiver: int, frame: bytes, due_s: float, now_s: float) -> list:
        """``[(receiver, frame)]`` when it is due now, else ``[]`` with the frame queued."""
        if due_s <= now_s:
            return [(receiver, frame)]
        heapq.heappush(self.queue, (due_s, self.order, receiver, frame))
        self.order += 1
        return []

    def _to_ground(
        self, sender: int, frame: bytes, positions_m: np.ndarray, due_s: float, now_s: float
    ) -> list[tuple[int, bytes]]:
        """The ground station's reception of ``frame``: range from its antenna, its own loss."""
        ground = self.ground
        assert ground is not None
        antenna = np.array([ground.x_m, ground.y_m, 0.0])
        distance_km = float(np.linalg.norm(positions_m[sender] - antenna)) / 1000.0
        if not distance_km <= self.options.range_km:
            ground.lost_to_range += 1
            return []
        if self.options.loss > 0 and ground.rng.random() < self.options.loss:
            ground.lost_to_loss += 1
            return []
        return self._queue(GROUND, frame, due_s, now_s)

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
            if receiver == GROUND:
                if self.ground is not None:
                    self.ground.delivered += 1
                    self.ground.bytes_received += len(frame)
                continue
            self.stats.delivered += 1
            self.stats.bytes_received[receiver] += len(frame)
