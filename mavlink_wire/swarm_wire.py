"""The swarm link's wire format (docs/onboard.md, "The swarm link"): what one UAV's planner node
tells its neighbours each decision step, carried in MAVLink TUNNEL messages (id 385) of the
project's payload type :data:`SWARM_PAYLOAD_TYPE`, sent to target 0/0 (broadcast) so that
ArduPilot routes them between its links and a telemetry radio carries them to the other planes.

A :class:`SwarmReport` (plain Python values: ints, floats, bools and tuples) is encoded as one
message body (:func:`encode_report`), split into fragments of at most
:data:`FRAGMENT_DATA_BYTES` bytes, each behind an 8-byte fragment header, one fragment per TUNNEL
payload (:class:`SwarmSender`). :class:`SwarmReassembler` puts the fragments back together,
checks the message's CRC and decodes it; a fragment or message that is short, foreign,
inconsistent, incomplete or malformed is dropped and counted (:class:`SwarmWireStats`), never
raised: the bytes come from a radio.

Signing is the MAVLink link's: a sender's encoder signs every TUNNEL frame once
``mavlink_wire.signing.sign_outgoing`` set it up with the mission key, and a receiver given a
:class:`~mavlink_wire.signing.SignatureCheck` refuses what is unsigned, wrongly signed or replayed.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections import OrderedDict, deque
from dataclasses import dataclass, field, replace

from mavlink_wire.protocol import mavlink
from mavlink_wire.signing import SignatureCheck
from mavlink_wire.swarm_records import (  # the records a report carries (re-exported here)
    Claim,
    Engagement,
    Intent,
    Look,
    MoveClaim,
    NodeState,
    SwarmReport,
    ThreatReport,
)

#: TUNNEL.payload_type of the swarm link: MAVLink leaves codes above 32767 to private use
#: ("local experiments", common.xml TUNNEL.payload_type); 0xA557 is the project's.
SWARM_PAYLOAD_TYPE = 0xA557
TUNNEL_PAYLOAD_BYTES = 128
#: 2: the cells of a claim signed (a cell off the area is a claim too); 3: the state's measured
#: course and ground speed (a flight section), for the neighbours' flight envelopes
WIRE_VERSION = 3
#: version u8, sender u8, message sequence u16, fragment index u8, fragment count u8, CRC u16
FRAGMENT_HEADER = struct.Struct("<BBHBBH")
FRAGMENT_DATA_BYTES = TUNNEL_PAYLOAD_BYTES - FRAGMENT_HEADER.size  # 120
MAX_FRAGMENTS = 255
MAX_MESSAGE_BYTES = MAX_FRAGMENTS * FRAGMENT_DATA_BYTES
#: a TUNNEL frame on the wire: MAVLink 2 header 10 + payload 5 + 128 + CRC 2 (+ signature 13);
#: MAVLink 2 trims the payload's trailing zero bytes, so a short last fragment is shorter
TUNNEL_FRAME_BYTES = 10 + 5 + TUNNEL_PAYLOAD_BYTES + 2
SIGNATURE_BYTES = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN  # 13

BODY_HEADER = struct.Struct("<BH")  # sender u8, decision step u16
SECTION_HEADER = struct.Struct("<BB")  # kind u8, record count u8
STATE = struct.Struct("<HHBiid")  # cell x, y u16; heading u8; x, y m i32; coop radius km f64
LOOK_HEAD = struct.Struct("<BHHHB")  # uav u8, step u16, cell x, y u16, footprint bits u8
ENGAGEMENT = struct.Struct("<HHHHB")  # target u16, cell x, y u16, step u16, flags u8
SERVICED = struct.Struct("<H")  # target u16
CLAIM = struct.Struct("<HHB")  # cell x, y u16, claim round u8
THREAT = struct.Struct("<iiI")  # x, y m i32, radius m u32
INTENT = struct.Struct("<HHH")  # track cell x, y u16 (0xFFFF: none); C_c priority u16
#: cell x, y i16 (signed: a UAV with no allowed move may claim a cell off the area); heading u8;
#: alternatives u8; blocker u8 (255: none); cell asked of it x, y i16
MOVE_HEAD = struct.Struct("<hhBBBhh")
CELL = struct.Struct("<hh")  # one alternative cell x, y i16
SERVICED_AT = struct.Struct("<HHH")  # target u16, cell x, y u16
#: the state's flight: course over ground u16 in 1/100 degree counter-clockwise from east
#: (0-35999), ground speed u16 in cm/s
FLIGHT = struct.Struct("<HH")
KIND_STATE, KIND_LOOK, KIND_ENGAGEMENT, KIND_SERVICED, KIND_CLAIM, KIND_THREAT = range(1, 7)
KIND_INTENT, KIND_MOVE, KIND_SERVICED_AT, KIND_FLIGHT = range(7, 11)
NO_CELL_WIRE = (0xFFFF, 0xFFFF)  # an intent's track cell (-1, -1): none
NOT_FLYING = 0x80  # the state's heading byte: bit 7 set, the UAV is done (home) or unreachable
NO_BLOCKER = 0xFF
MAX_RECORDS = 255  # per section; more records of a kind go into further sections


class WireError(ValueError):
    """A body that cannot be decoded (the receiver counts it), or a value the format cannot
    carry (the sender's bug: a cell beyond 65535, a footprint of more than 255 cells...)."""


# ---------------------------------------------------------------------- body encoding


def _metres(km: float) -> int:
    return int(round(km * 1000.0))


def _look_bytes(look: Look) -> bytes:
    bits = len(look.detected)
    if bits > 255:
        raise WireError(f"a look carries at most 255 footprint cells, got {bits}")
    mask = sum(1 << k for k, hit in enumerate(look.detected) if hit)
    head = LOOK_HEAD.pack(look.uav, look.step & 0xFFFF, *look.cell, bits)
    return head + mask.to_bytes((bits + 7) // 8, "little")


def _records(report: SwarmReport) -> list[tuple[int, list[bytes]]]:
    """Each section kind with its records' bytes."""
    state = report.state
    if state is not None and not 0 <= state.heading <= 7:
        raise WireError(f"heading must be 0-7 (the grid's), got {state.heading}")
    states = (
        []
        if state is None
        else [
            STATE.pack(
                *state.cell, state.heading | (0 if state.flying else NOT_FLYING),
                _metres(state.x_km), _metres(state.y_km), state.coop_radius_km,
            )
        ]
    )  # fmt: skip
    intents = (
        [] if report.intent is None else [INTENT.pack(*report.intent.track, report.intent.priority)]
    )
    return [
        (KIND_STATE, states),
        (KIND_FLIGHT, _flight_bytes(state)),
        (KIND_LOOK, [_look_bytes(look) for look in report.looks]),
        (
            KIND_ENGAGEMENT,
            [
                ENGAGEMENT.pack(e.target_id, *e.cell, e.step & 0xFFFF, int(bool(e.success)))
                for e in report.engagements
            ],
        ),
        (KIND_SERVICED, [SERVICED.pack(t) for t in report.serviced]),
        (KIND_CLAIM, [CLAIM.pack(*c.cell, c.round) for c in report.claims]),
        (
            KIND_THREAT,
            [
                THREAT.pack(_metres(t.x_km), _metres(t.y_km), _metres(t.radius_km))
                for t in report.threats
            ],
        ),
        (KIND_INTENT, intents),
        (KIND_MOVE, [_move_bytes(m) for m in report.moves]),
        (KIND_SERVICED_AT, [SERVICED_AT.pack(t, *cell) for t, cell in report.serviced_at]),
    ]


def _flight_bytes(state: NodeState | None) -> list[bytes]:
    """The state's flight record (none without a state, or without a measured course)."""
    if state is None or state.course_rad is None or state.speed_mps is None:
        return []
    centideg = int(round(math.degrees(state.course_rad) * 100.0)) % 36000
    return [FLIGHT.pack(centideg, min(0xFFFF, max(0, int(round(state.speed_mps * 100.0)))))]


def _move_bytes(move: MoveClaim) -> bytes:
    if not 0 <= move.heading <= 7 or len(move.alternatives) > 255:
        raise WireError(f"a claim's heading must be 0-7 and its alternatives at most 255, got "
                        f"{move.heading} and {len(move.alternatives)}")  # fmt: skip
    # (with no blocker the cell asked of it is never read)
    blocker, asked = (NO_BLOCKER, (0, 0)) if move.displace is None else move.displace
    head = MOVE_HEAD.pack(*move.cell, move.heading, len(move.alternatives), blocker, *asked)
    return head + b"".join(CELL.pack(*cell) for cell in move.alternatives)


def _decode_move(body: bytes, pos: int) -> tuple[MoveClaim, int]:
    x, y, heading, count, blocker, ax, ay = MOVE_HEAD.unpack_from(body, pos)
    pos += MOVE_HEAD.size
    if heading > 7:
        raise WireError("a claim's heading beyond 7")
    cells = tuple(CELL.unpack_from(body, pos + k * CELL.size) for k in range(count))
    displace = None if blocker == NO_BLOCKER else (blocker, (ax, ay))
    return MoveClaim((x, y), heading, cells, displace), pos + count * CELL.size


def encode_report(report: SwarmReport) -> bytes:
    """The message body of ``report``: sender and step, then one section per kind present."""
    try:
        out = [BODY_HEADER.pack(report.uav, report.step & 0xFFFF)]
        for kind, records in _records(report):
            for start in range(0, len(records), MAX_RECORDS):
                chunk = records[start : start + MAX_RECORDS]
                out.append(SECTION_HEADER.pack(kind, len(chunk)))
                out.extend(chunk)
    except struct.error as exc:
        raise WireError(
            f"a value of UAV {report.uav}'s report does not fit the wire: {exc}"
        ) from None
    body = b"".join(out)
    if len(body) > MAX_MESSAGE_BYTES:
        raise WireError(f"a report of {len(body)} bytes exceeds {MAX_MESSAGE_BYTES}")
    return body


def _decode_look(body: bytes, pos: int) -> tuple[Look, int]:
    uav, step, x, y, bits = LOOK_HEAD.unpack_from(body, pos)
    pos += LOOK_HEAD.size
    size = (bits + 7) // 8
    if pos + size > len(body):
        raise WireError("look bits run past the end")
    mask = int.from_bytes(body[pos : pos + size], "little")
    return Look(uav, step, (x, y), tuple(bool(mask >> k & 1) for k in range(bits))), pos + size


def _decode_record(kind: int, body: bytes, pos: int, parts: dict) -> int:
    """Decode one record of ``kind`` at ``pos`` into ``parts``; the position after it."""
    if kind == KIND_LOOK:
        look, pos = _decode_look(body, pos)
        parts["looks"].append(look)
        return pos
    if kind == KIND_STATE:
        x, y, flags, xm, ym, radius = STATE.unpack_from(body, pos)
        heading = flags & ~NOT_FLYING
        if parts["state"] is not None or heading > 7:
            raise WireError("a second state, or a heading beyond 7")
        flying = not flags & NOT_FLYING
        parts["state"] = NodeState((x, y), heading, xm / 1000.0, ym / 1000.0, radius, flying)
        return pos + STATE.size
    if kind == KIND_FLIGHT:
        centideg, cms = FLIGHT.unpack_from(body, pos)
        if parts["state"] is None or parts["state"].course_rad is not None or centideg >= 36000:
            raise WireError("a flight without its state, a second one, or a course of 360 deg")
        course = math.radians(centideg / 100.0)
        parts["state"] = replace(parts["state"], course_rad=course, speed_mps=cms / 100.0)
        return pos + FLIGHT.size
    if kind == KIND_INTENT:
        x, y, priority = INTENT.unpack_from(body, pos)
        if parts["intent"] is not None:
            raise WireError("a second track intent")
        parts["intent"] = Intent((x, y), priority)
        return pos + INTENT.size
    if kind == KIND_MOVE:
        move, pos = _decode_move(body, pos)
        parts["moves"].append(move)
        return pos
    if kind == KIND_SERVICED_AT:
        target, x, y = SERVICED_AT.unpack_from(body, pos)
        parts["serviced_at"].append((target, (x, y)))
        return pos + SERVICED_AT.size
    if kind == KIND_ENGAGEMENT:
        target, x, y, step, flags = ENGAGEMENT.unpack_from(body, pos)
        parts["engagements"].append(Engagement(target, (x, y), step, bool(flags & 1)))
        return pos + ENGAGEMENT.size
    if kind == KIND_SERVICED:
        parts["serviced"].append(SERVICED.unpack_from(body, pos)[0])
        return pos + SERVICED.size
    if kind == KIND_CLAIM:
        x, y, claim_round = CLAIM.unpack_from(body, pos)
        parts["claims"].append(Claim((x, y), claim_round))
        return pos + CLAIM.size
    if kind == KIND_THREAT:
        xm, ym, rm = THREAT.unpack_from(body, pos)
        parts["threats"].append(ThreatReport(xm / 1000.0, ym / 1000.0, rm / 1000.0))
        return pos + THREAT.size
    raise WireError(f"unknown section kind {kind}")


def decode_report(body: bytes) -> SwarmReport:
    """The report in a message body; :class:`WireError` for anything malformed."""
    try:
        uav, step = BODY_HEADER.unpack_from(body, 0)
        pos = BODY_HEADER.size
        parts: dict = {
            "state": None, "looks": [], "engagements": [], "serviced": [], "claims": [],
            "threats": [], "intent": None, "moves": [], "serviced_at": [],
        }  # fmt: skip
        while pos < len(body):
            kind, count = SECTION_HEADER.unpack_from(body, pos)
            pos += SECTION_HEADER.size
            for _ in range(count):
                pos = _decode_record(kind, body, pos, parts)
    except struct.error:
        raise WireError("a record runs past the end of the message") from None
    return SwarmReport(
        uav, step, parts["state"], tuple(parts["looks"]), tuple(parts["engagements"]),
        tuple(parts["serviced"]), tuple(parts["claims"]), tuple(parts["threats"]),
        parts["intent"], tuple(parts["moves"]), tuple(parts["serviced_at"]),
    )  # fmt: skip


# ---------------------------------------------------------------------- fragments


def fragment_payloads(body: bytes, sender: int, sequence: int) -> list[bytes]:
    """The TUNNEL payloads (each at most 128 bytes) of one message body."""
    chunks = [
        body[k : k + FRAGMENT_DATA_BYTES] for k in range(0, len(body), FRAGMENT_DATA_BYTES)
    ] or [b""]
    if len(chunks) > MAX_FRAGMENTS:
        raise WireError(f"a message of {len(body)} bytes needs more than {MAX_FRAGMENTS} frames")
    crc = binascii.crc_hqx(body, 0xFFFF)
    return [
        FRAGMENT_HEADER.pack(WIRE_VERSION, sender, sequence & 0xFFFF, k, len(chunks), crc) + chunk
        for k, chunk in enumerate(chunks)
    ]


def tunnel_message(payload: bytes) -> mavlink.MAVLink_tunnel_message:
    """A broadcast TUNNEL message (target 0/0) of the swarm payload type carrying ``payload``."""
    data = list(payload) + [0] * (TUNNEL_PAYLOAD_BYTES - len(payload))
    return mavlink.MAVLink_tunnel_message(0, 0, SWARM_PAYLOAD_TYPE, len(payload), data)


@dataclass
class SwarmSender:
    """One node's side of the link: numbers its messages and cuts them into TUNNEL messages."""

    uav: int
    sequence: int = 0

    def messages(self, report: SwarmReport) -> list[mavlink.MAVLink_tunnel_message]:
        payloads = fragment_payloads(encode_report(report), self.uav, self.sequence)
        self.sequence = (self.sequence + 1) & 0xFFFF
        return [tunnel_message(p) for p in payloads]

    def frames(self, report: SwarmReport, mav: mavlink.MAVLink) -> list[bytes]:
        """The packed frames of ``report`` from encoder ``mav`` (signed if it signs)."""
        return [bytes(m.pack(mav)) for m in self.messages(report)]


@dataclass
class SwarmWireStats:
    """What a receiver made of the TUNNEL frames it was given."""

    frames: int = 0  # swarm-link fragments accepted into reassembly
    foreign: int = 0  # TUNNEL frames of another payload type, or not TUNNEL at all
    unsigned_or_forged: int = 0  # refused by the signature check
    bad_fragments: int = 0  # short, wrong version, bad index/count
    duplicates: int = 0  # a fragment already held, or of a message already complete
    inconsistent: int = 0  # messages whose fragments disagree (count, CRC, data) or fail the CRC
    incomplete: int = 0  # messages given up with fragments missing (timeout or crowding)
    malformed: int = 0  # messages that pass the CRC but do not decode
    messages: int = 0  # reports delivered


@dataclass
class _Partial:
    count: int
    crc: int
    first_s: float
    parts: dict[int, bytes] = field(default_factory=dict)


@dataclass
class SwarmReassembler:
    """Turns swarm-link TUNNEL frames back into reports. ``accept_*`` return a report when a
    message completes, else None; they never raise on what arrives. A message still missing
    fragments ``timeout_s`` after its first (caller's clock), or pushed out by more than
    ``max_pending`` newer partial messages, is dropped as incomplete."""

    timeout_s: float = 5.0
    max_pending: int = 64
    signature: SignatureCheck | None = None
    stats: SwarmWireStats = field(default_factory=SwarmWireStats)
    _pending: OrderedDict = field(default_factory=OrderedDict)
    _done: deque = field(default_factory=lambda: deque(maxlen=1024))

    def accept_message(self, msg: mavlink.MAVLink_message, now_s: float) -> SwarmReport | None:
        """A received MAVLink message (anything: only swarm TUNNEL frames are used)."""
        try:
            if msg.get_type() != "TUNNEL" or msg.payload_type != SWARM_PAYLOAD_TYPE:
                self.stats.foreign += 1
                return None
            if self.signature is not None and not self.signature.accept_message(msg):
                self.stats.unsigned_or_forged += 1
                return None
            length = int(msg.payload_length)
            if not 0 <= length <= TUNNEL_PAYLOAD_BYTES:
                self.stats.bad_fragments += 1
                return None
            payload = bytes(int(b) & 0xFF for b in msg.payload[:length])
        except (AttributeError, TypeError, ValueError):
            self.stats.bad_fragments += 1
            return None
        return self.accept_payload(payload, now_s)

    def accept_payload(self, payload: bytes, now_s: float) -> SwarmReport | None:
        """One TUNNEL payload (``payload_length`` bytes) of the swarm payload type."""
        self._expire(now_s)
        if len(payload) < FRAGMENT_HEADER.size:
            self.stats.bad_fragments += 1
            return None
        version, sender, seq, index, count, crc = FRAGMENT_HEADER.unpack_from(payload, 0)
        if version != WIRE_VERSION or count == 0 or index >= count:
            self.stats.bad_fragments += 1
            return None
        key = (sender, seq)
        if (sender, seq, crc) in self._done:
            self.stats.duplicates += 1
            return None
        self.stats.frames += 1
        partial = self._pending.get(key)
        if partial is None:
            partial = self._pending[key] = _Partial(count, crc, now_s)
            while len(self._pending) > self.max_pending:
                self._pending.popitem(last=False)
                self.stats.incomplete += 1
        elif partial.count != count or partial.crc != crc:
            return self._give_up(key)
        data = payload[FRAGMENT_HEADER.size :]
        held = partial.parts.get(index)
        if held is not None:
            if held != data:
                return self._give_up(key)
            self.stats.duplicates += 1
            return None
        partial.parts[index] = data
        if len(partial.parts) < count:
            return None
        return self._complete(key, partial)

    def _complete(self, key: tuple[int, int], partial: _Partial) -> SwarmReport | None:
        del self._pending[key]
        self._done.append((*key, partial.crc))
        body = b"".join(partial.parts[k] for k in range(partial.count))
        if binascii.crc_hqx(body, 0xFFFF) != partial.crc:
            self.stats.inconsistent += 1
            return None
        try:
            report = decode_report(body)
        except WireError:
            self.stats.malformed += 1
            return None
        if report.uav != key[0]:
            self.stats.inconsistent += 1
            return None
        self.stats.messages += 1
        return report

    def _give_up(self, key: tuple[int, int]) -> None:
        del self._pending[key]
        self.stats.inconsistent += 1
        return None

    def _expire(self, now_s: float) -> None:
        while self._pending:
            key, partial = next(iter(self._pending.items()))
            if now_s - partial.first_s < self.timeout_s:
                break
            del self._pending[key]
            self.stats.incomplete += 1
