"""MAVLink 2 message signing for the daemon: the key, signing what it sends, checking what it
hears.

The key is 32 bytes shared with every vehicle. It comes from a file (``--signing-key-file PATH``:
32 raw bytes, or 64 hex characters) or from the environment (``SWARMPLAN_SIGNING_KEY``, 64 hex
characters), never from a command-line value (the process list and shell history show those).
Where the project runs both ends it makes the key for the mission (:func:`mission_key`): the
simulator writes it to its key file if that does not exist yet (:func:`load_or_create_key_file`,
mode 0600), and ``swarmplan demo`` hands it to the simulator it starts in the environment.
``sha256(passphrase)`` is the key MAVProxy's ``signing setup PASSPHRASE`` derives, so
``python -c "import hashlib; print(hashlib.sha256(b'PASSPHRASE').hexdigest())" > key.hex``
gives the key an ArduPilot set up from MAVProxy uses (docs/reliability.md).

Sending: every frame to vehicle ``s`` is signed by that vehicle's encoder with link id ``s``
(one signing stream per vehicle, so each vehicle sees timestamps that only grow) and a
timestamp that starts at the wall clock (10 us units since 2015-01-01, as the MAVLink spec and
ArduPilot use), so a restarted daemon is never taken for a replay.

Receiving: :class:`SignatureCheck` accepts a frame only if its signature matches *and* its
timestamp is newer than the last accepted one of its stream ``(link id, system, component)``.
It checks the signature before it records the timestamp: pymavlink's own check records the
timestamp of a frame whose signature then fails, so one forged frame with a far-future timestamp
would make every genuine frame after it look like a replay. Unsigned frames are refused except
RADIO_STATUS / RADIO (what ArduPilot accepts unsigned: telemetry radios cannot sign).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import secrets
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

from mavlink_wire.protocol import mavlink
from planner.errors import UserError

KEY_ENV = "SWARMPLAN_SIGNING_KEY"
KEY_BYTES = 32
EPOCH_2015 = 1420070400  # signing timestamps count 10 us units since 2015-01-01 00:00 UTC
NEW_STREAM_WINDOW = 60 * 100_000  # a new stream may start at most one minute behind our clock
SIGNATURE_BLOCK = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN  # 13: link id, 6-byte timestamp, 6-byte sig
#: Messages accepted unsigned while signing is on (ArduPilot's accept list: radios cannot sign).
UNSIGNED_ALLOWED = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_RADIO})


class SigningKeyError(UserError):
    """The signing key cannot be read or is not a 32-byte key."""


def parse_key(raw: bytes, where: str) -> bytes:
    """32 raw bytes, or 64 hex characters (surrounding whitespace ignored)."""
    text = raw.strip()
    if re.fullmatch(rb"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text.decode("ascii"))
    if len(raw) == KEY_BYTES:
        return bytes(raw)
    raise SigningKeyError(
        f"{where} is not a MAVLink signing key: give 64 hex characters or 32 raw bytes "
        f'(got {len(raw)} bytes); e.g. python -c "import secrets; print(secrets.token_hex(32))"'
    )


def load_signing_key(
    path: str | Path | None, environ: dict[str, str] | None = None
) -> bytes | None:
    """The key from ``path`` if given, else ``$SWARMPLAN_SIGNING_KEY``, else None (unsigned)."""
    if path is not None:
        try:
            raw = Path(path).read_bytes()
        except OSError as exc:
            raise SigningKeyError(
                f"cannot read signing key file {path} ({exc.strerror}); check the path "
                "(`swarmplan sim --signing-key-file PATH` makes one for its vehicles)"
            ) from None
        return parse_key(raw, f"signing key file {path}")
    env = os.environ if environ is None else environ
    value = env.get(KEY_ENV)
    if value is None or value == "":
        return None
    return parse_key(value.encode("utf-8", "replace"), f"${KEY_ENV}")


def mission_key() -> bytes:
    """A new random 32-byte key for one mission."""
    return secrets.token_bytes(KEY_BYTES)


def load_or_create_key_file(path: str | Path) -> tuple[bytes, bool]:
    """The key in ``path``, or a new one written there (64 hex characters, mode 0600) when the
    file does not exist; and whether it was made now. The file appears whole or not at all (a
    private temporary file hard-linked into place), and an existing one is never replaced."""
    path = Path(path)
    if path.exists():
        return load_signing_key(path), False
    key = mission_key()
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as sink:
            sink.write(key.hex() + "\n")
        try:
            os.link(partial, path)
        except FileExistsError:  # made meanwhile by another process: that one is the key
            return load_signing_key(path), False
        finally:
            partial.unlink(missing_ok=True)
    except OSError as exc:
        raise SigningKeyError(
            f"cannot create signing key file {path} ({exc.strerror}); choose a writable "
            "--signing-key-file path"
        ) from None
    return key, True


def key_environment(key: bytes | None, environ: dict[str, str] | None = None) -> dict[str, str]:
    """The environment for a child process (the demo's simulator) that signs with ``key``, or
    unsigned when None: a caller's ``$SWARMPLAN_SIGNING_KEY`` never leaks into an unsigned one."""
    out = dict(os.environ if environ is None else environ)
    out.pop(KEY_ENV, None)
    if key is not None:
        out[KEY_ENV] = key.hex()
    return out


def unsigned_warning(fix: str) -> str:
    """The one line said at the start of a mission flown without signing; ``fix`` says how to
    sign (it differs between the daemon and the demo)."""
    return (
        "flying unsigned: any host that can reach the vehicles' links can command them "
        f"(arm, disarm, change mode); {fix} (docs/reliability.md, MAVLink 2 signing)"
    )


def signing_clock() -> int:
    """Now as a MAVLink signing timestamp (10 us units since 2015-01-01)."""
    return int((max(time.time(), EPOCH_2015) - EPOCH_2015) * 100_000)


class WallClockSigning(mavlink.MAVLinkSigning):
    """pymavlink's signing state with a timestamp that never falls behind the wall clock.
    pymavlink adds one (10 us) per frame it signs and nothing else, so an encoder set up long
    before it first speaks to a new receiver (a neighbour only now in range, a ground station
    that starts listening mid-mission, a swarm whose start took minutes on a busy machine)
    would stamp its frames minutes in the past, and that receiver refuses a new stream more
    than ``NEW_STREAM_WINDOW`` behind its clock as a replay (ArduPilot too). As ArduPilot moves
    its own timestamp up to its clock, each frame here is stamped ``max(last + 1, now)``."""

    @property  # type: ignore[override]
    def timestamp(self) -> int:
        return max(self._timestamp, signing_clock())

    @timestamp.setter
    def timestamp(self, value: int) -> None:
        self._timestamp = int(value)


def sign_outgoing(mav: mavlink.MAVLink, key: bytes, link_id: int) -> None:
    """Make encoder ``mav`` sign every frame it packs (timestamps kept up with the wall clock:
    :class:`WallClockSigning`)."""
    if not isinstance(mav.signing, WallClockSigning):
        state = WallClockSigning()
        for name, value in vars(mav.signing).items():
            setattr(state, name, value)
        mav.signing = state
    mav.signing.secret_key = key
    mav.signing.link_id = link_id & 0xFF
    mav.signing.sign_outgoing = True


def is_signed(frame: bytes | bytearray) -> bool:
    """A MAVLink 2 frame carrying a signature block (checked or not: see SignatureCheck)."""
    return bool(
        len(frame) > SIGNATURE_BLOCK
        and frame[0] == mavlink.PROTOCOL_MARKER_V2
        and (frame[2] & mavlink.MAVLINK_IFLAG_SIGNED)
    )


@dataclass
class SignatureCheck:
    """Accepts correctly signed, fresh frames (and RADIO_STATUS unsigned); counts the rest."""

    key: bytes
    streams: dict[tuple[int, int, int], int] = field(default_factory=dict)
    accepted: int = 0
    unsigned_refused: int = 0
    bad_signatures: int = 0
    replays: int = 0

    def accept(self, frame: bytes | bytearray, msg_id: int) -> bool:
        frame = bytes(frame)
        if not is_signed(frame):
            if msg_id in UNSIGNED_ALLOWED:
                return True
            self.unsigned_refused += 1
            return False
        digest = hashlib.sha256(self.key + frame[:-6]).digest()[:6]
        if not hmac.compare_digest(digest, frame[-6:]):
            self.bad_signatures += 1
            return False
        link_id = frame[-13]
        low, high = struct.unpack("<IH", frame[-12:-6])
        timestamp = low | (high << 32)
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        if last is None:
            if timestamp + NEW_STREAM_WINDOW < signing_clock():
                self.replays += 1
                return False
        elif timestamp <= last:
            self.replays += 1
            return False
        self.streams[stream] = timestamp
        self.accepted += 1
        return True

    def accept_message(self, msg: mavlink.MAVLink_message) -> bool:
        return self.accept(msg.get_msgbuf(), msg.get_msgId())

    def counters(self) -> dict[str, int]:
        return {
            "signed_accepted": self.accepted,
            "unsigned_refused": self.unsigned_refused,
            "bad_signatures": self.bad_signatures,
            "replays_refused": self.replays,
        }
