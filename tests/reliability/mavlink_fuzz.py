"""Seeded MAVLink fuzz input: random bytes, mutated valid frames, and well-formed frames (good
CRC) of the messages a vehicle or a daemon handles, with hostile field values (NaN, infinities,
extremes, random enums and ids)."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import math  # noqa: E402
import random  # noqa: E402
import struct  # noqa: E402

from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

_HOSTILE_FLOATS = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1e38, -1e38, 1e-45, 1.0, -1.0)
_INT_RANGES = {
    "int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-32768, 32767),
    "uint16_t": (0, 65535), "int32_t": (-(2**31), 2**31 - 1), "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1), "uint64_t": (0, 2**64 - 1), "char": (0, 255),
}  # fmt: skip
#: Commands worth hitting often (the ones with handlers), besides random ids.
_COMMANDS = (
    16, 20, 21, 22, 176, 178, 179, 192, 224, 300, 400, 510, 511, 512, 520, 2000, 5004,
)  # fmt: skip


def _field_value(rng: random.Random, kind: str, length: int, name: str):
    base = kind.split("[")[0]
    if base in ("float", "double"):
        one = lambda: rng.choice(_HOSTILE_FLOATS) if rng.random() < 0.4 else rng.uniform(-1e4, 1e4)  # noqa: E731
    elif base == "char":
        if rng.random() < 0.5:
            alphabet = b"look:+0123456789,;-x\x00\xff"
            return bytes(rng.choice(alphabet) for _ in range(rng.randint(0, length or 1)))
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, length or 1)))
    else:
        lo, hi = _INT_RANGES[base]

        def one():
            if name == "command":
                return rng.choice(_COMMANDS) if rng.random() < 0.7 else rng.randint(lo, hi)
            if name in ("target_system",):
                return rng.choice((0, 1, 2, 3, 255, rng.randint(lo, hi)))
            if name in ("target_component",):
                return rng.choice((0, 1, 100, 190, rng.randint(lo, hi)))
            r = rng.random()
            if r < 0.3:
                return rng.choice((lo, hi, 0, 1, -1 if lo < 0 else 2))
            if r < 0.6:
                return rng.randint(max(lo, -100), min(hi, 100))
            return rng.randint(lo, hi)

    if length > 1 and base != "char":
        return [one() for _ in range(length)]
    return one()


def well_formed(rng: random.Random, classes: list[type], sysid: int, compid: int) -> bytes:
    """A frame with a good CRC of a random class from ``classes``, hostile field values."""
    cls = rng.choice(classes)
    args = []
    for name, kind, length in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths, strict=True):
        args.append(_field_value(rng, kind, length, name))
    msg = cls(*args)
    mav = ml.MAVLink(None, sysid, compid)
    mav.seq = rng.randrange(256)
    try:
        return bytes(msg.pack(mav))
    except (struct.error, OverflowError, ValueError, TypeError):
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))


def mutated(rng: random.Random, frame: bytes) -> bytes:
    """``frame`` with bytes flipped, cut, repeated or spliced with junk."""
    data = bytearray(frame)
    for _ in range(rng.randint(1, 4)):
        op = rng.random()
        if op < 0.4 and data:
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        elif op < 0.55 and data:
            del data[rng.randrange(len(data)) :]
        elif op < 0.7:
            spliced = bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))
            data[rng.randrange(len(data) + 1) : 0] = spliced
        elif op < 0.85:
            data += frame
        elif data:
            data[rng.randrange(len(data))] = rng.choice((0xFD, 0xFE, 0x00, 0xFF))
    return bytes(data)


def junk(rng: random.Random) -> bytes:
    out = bytearray(rng.randrange(256) for _ in range(rng.randint(0, 300)))
    for _ in range(rng.randint(0, 3)):
        if out:
            out[rng.randrange(len(out))] = rng.choice((0xFD, 0xFE))
    return bytes(out)


class Fuzzer:
    """Yields datagrams: a third junk, a third mutated valid frames, a third well-formed hostile
    frames (sometimes several frames in one datagram)."""

    def __init__(self, seed: int, classes: list[type], senders: list[tuple[int, int]]) -> None:
        self.rng = random.Random(seed)
        self.classes = classes
        self.senders = senders
        self.corpus = [self._valid() for _ in range(64)]

    def _valid(self) -> bytes:
        sysid, compid = self.rng.choice(self.senders)
        return well_formed(self.rng, self.classes, sysid, compid)

    def datagram(self) -> bytes:
        r = self.rng.random()
        if r < 0.33:
            return junk(self.rng)
        if r < 0.66:
            return mutated(self.rng, self.rng.choice(self.corpus))
        frames = [self._valid() for _ in range(1 if self.rng.random() < 0.8 else 3)]
        return b"".join(frames)


def classes_named(names) -> list[type]:
    by_name = {cls.msgname: cls for cls in ml.mavlink_map.values()}
    return [by_name[n] for n in names if n in by_name]
