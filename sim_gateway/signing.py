"""MAVLink 2 message signing of the simulated vehicles, as ArduPilot does it once a key is set.

With a key (``swarmplan sim --signing-key-file PATH`` or ``$SWARMPLAN_SIGNING_KEY``; 32 raw bytes
or 64 hex characters, never a command-line value), every vehicle:

* signs everything it sends (each component its own stream, timestamps from the wall clock);
* refuses every frame that is unsigned, wrongly signed, or a replay (a timestamp not newer than
  the last accepted one of its stream ``(link id, system, component)``, or a new stream more
  than a minute behind the clock). Refused frames are counted (``unsigned_refused``,
  ``bad_signatures``, ``replays_refused``) and never reach a handler: a spoofed DO_REPOSITION or
  SET_MODE changes nothing and gets no ACK.
* accepts unsigned only RADIO_STATUS and RADIO, like ArduPilot's ``accept_unsigned_callback``
  (a telemetry radio cannot sign). An unsigned HEARTBEAT is refused too, so a stranger cannot
  hold off the GCS failsafe. ArduPilot also accepts everything on its USB port (channel 0);
  the simulator has no such port.

The signature is checked before the stream timestamp is recorded (pymavlink's own check records
it first, so one forged frame with a far-future timestamp would lock out the real sender).
``sim_gateway`` and ``mavlink_bridge`` never import each other, so the daemon's side lives in
``mavlink_bridge/signing.py``; both follow the MAVLink signing spec and are tested against each
other.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from planner.errors import UserError

if TYPE_CHECKING:
    from sim_gateway.simulator import Simulator

KEY_ENV = "SWARMPLAN_SIGNING_KEY"
EPOCH_2015 = 1420070400
NEW_STREAM_WINDOW = 60 * 100_000  # 10 us units: one minute
UNSIGNED_ALLOWED = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_RADIO})


class SigningKeyError(UserError):
    """The signing key cannot be read or is not a 32-byte key."""


def parse_key(raw: bytes, where: str) -> bytes:
    text = raw.strip()
    if re.fullmatch(rb"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text.decode("ascii"))
    if len(raw) == 32:
        return bytes(raw)
    raise SigningKeyError(
        f"{where} is not a MAVLink signing key: give 64 hex characters or 32 raw bytes "
        f"(got {len(raw)} bytes)"
    )


def load_signing_key(
    path: str | Path | None, environ: dict[str, str] | None = None
) -> bytes | None:
    """The key from ``path`` if given, else from ``$SWARMPLAN_SIGNING_KEY``, else None."""
    if path is not None:
        try:
            raw = Path(path).read_bytes()
        except OSError as exc:
            raise SigningKeyError(
                f"cannot read signing key file {path} ({exc.strerror}); check the path"
            ) from None
        return parse_key(raw, f"signing key file {path}")
    value = (os.environ if environ is None else environ).get(KEY_ENV)
    return parse_key(value.encode("utf-8", "replace"), f"${KEY_ENV}") if value else None


def signing_clock() -> int:
    """Now in MAVLink signing units (10 us since 2015-01-01)."""
    return int((max(time.time(), EPOCH_2015) - EPOCH_2015) * 100_000)


@dataclass
class SignatureCheck:
    """The receiving half: accept a frame or count why not."""

    key: bytes
    streams: dict[tuple[int, int, int], int] = field(default_factory=dict)
    unsigned_refused: int = 0
    bad_signatures: int = 0
    replays: int = 0

    def accept(self, frame: bytes, msg_id: int) -> bool:
        if frame[0] != mavlink.PROTOCOL_MARKER_V2 or not frame[2] & mavlink.MAVLINK_IFLAG_SIGNED:
            if msg_id in UNSIGNED_ALLOWED:
                return True
            self.unsigned_refused += 1
            return False
        digest = hashlib.sha256(self.key + frame[:-6]).digest()[:6]
        if not hmac.compare_digest(digest, frame[-6:]):
            self.bad_signatures += 1
            return False
        low, high = struct.unpack("<IH", frame[-12:-6])
        timestamp = low | (high << 32)
        stream = (frame[-13], frame[5], frame[6])
        last = self.streams.get(stream)
        fresh = (
            timestamp + NEW_STREAM_WINDOW >= signing_clock() if last is None else timestamp > last
        )
        if not fresh:
            self.replays += 1
            return False
        self.streams[stream] = timestamp
        return True


def enable_signing(sim: Simulator, key: bytes) -> SignatureCheck:
    """Make every vehicle of ``sim`` sign what it sends and refuse what is not signed."""
    check = SignatureCheck(key)
    sim.parser.signature_check = check
    now = signing_clock()
    for vehicle in sim.vehicles:
        for sender in (vehicle.autopilot, vehicle.camera):
            sender.mav.signing.secret_key = key
            sender.mav.signing.link_id = 0
            sender.mav.signing.timestamp = now
            sender.mav.signing.sign_outgoing = True
    return check
