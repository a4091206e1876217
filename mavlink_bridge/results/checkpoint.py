"""The daemon's checkpoint: the planner's state and the decision loop's own, written atomically
after every decision step, so a daemon killed mid-mission (``kill -9``, a crash, a power cut)
can be started again with ``--resume`` and carry on from the last step it finished.

A checkpoint is data, never code. File format (version 4): a 64-byte header, then an .npz.

* header: ``MAGIC`` (16 bytes), format version (uint32), flags (uint32: ``KEYED``), payload
  length (uint64), tag (32 bytes): HMAC-SHA256 with the mission's MAVLink signing key over the
  header's first 32 bytes and the payload when the daemon signs, else their SHA-256; all
  little-endian.
* payload: a zip (deflate level 1) of .npy members read with ``allow_pickle=False``: ``state``,
  one JSON text (``checkpoint_codec``: its writer, the daemon or ``node I``, a planner node of
  one UAV, ``swarmplan node``; the planner, its pursuit log, the recorder, the loop
  variables of :data:`LOOP_STATE`, the daemon's counters of :data:`DAEMON_STATE`), and the
  arrays it refers to, ``a0``, ``a1``... What the scenario alone determines (:data:`DERIVED`:
  the planner's safety models, the TPM diffusion's stencil and scratch buffers; cached
  properties) is not written, but taken from the planner the resumed daemon builds.

Measured (after 30 steps, load 7-8; docs/reliability.md): paper-10uav writes 1.46 MB (5.0 MB of
state), 11-16 ms of the decision loop a step and 0.14-0.19 s in the background; paper-20uav
2.90 MB (9.9 MB), 15-24 ms and 0.26-0.36 s. Reading, verifying and checking one to resume takes
70-115 ms and 140-205 ms.

Writing: the state is encoded at once (JSON text and array copies: it changes at the next
step); packing and writing can go to a background thread (``CheckpointWriter(background=True)``,
the daemon's: zlib and the file system release the GIL), one write at a time, the next save (or
``flush``) waiting for the one before. Into ``PATH.tmp`` in the same folder, flushed and
fsync'ed, then ``os.replace`` over ``PATH`` (atomic on POSIX and Windows), then the folder is
fsync'ed: a reader sees the previous checkpoint or the new one, never a mix.

Reading (:func:`load_for_mission`) checks, in order: the file, the magic, the version (the
pickle formats 2 and 3 are refused: written by an older version), the length, the key (a file
written with a key is read only with it, and a daemon that signs reads only keyed files) and the
tag, the .npz and its JSON (only the forms of ``checkpoint_codec``; objects only of the project's
own classes, rebuilt without calling their code), that its writer is this one (the daemon, or
the node of this UAV), that it is this mission's (scenario, seed, vehicle count, steps), and
then every part against the state this daemon builds for the mission (``checkpoint_layout``:
classes, attributes, types, dtypes, shapes, finite values, ranges), all before any of it
reaches the planner. Every failure is one :class:`CheckpointError` line saying what is wrong
and what to do.
"""

from __future__ import annotations

import hashlib
import hmac
import io
import json
import os
import re
import struct
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mavlink_bridge.results.checkpoint_codec import StateError, decode, encode
from mavlink_bridge.results.checkpoint_layout import Mission, check_like, check_ranges
from planner.errors import UserError
from planner.scenario import Scenario

MAGIC = b"SWARMPLAN-CKPT\x00\x01"
VERSION = 4  # JSON and numpy arrays in an .npz; 2 and 3 (pickles) are refused
_PICKLE_VERSIONS = (2, 3)
KEYED = 1  # header flag: the tag is an HMAC-SHA256 with the mission's signing key
#: planner attributes (``owner.attribute`` paths from the planner) determined by the scenario
#: alone: not written; a resumed daemon takes them from the planner it builds for the mission
DERIVED = tuple(
    f"{beliefs}.{part}"
    for beliefs in ("beliefs", "node.planner.beliefs")  # the daemon's planner's, a node's
    for part in (
        "_safety",
        "tpm.stencil",
        "tpm.work",
        "tpm.wiener_work",
        "tpm.ratio_lookup",
        "tpm.drift_layers",
    )
)
_NOT_WRITTEN = frozenset(f"planner.{path}" for path in DERIVED)
_HEADER = struct.Struct("<16sIIQ32s")  # 64 bytes; the tag covers the first 32 and the payload
_TAGGED = 32
#: a state this large (uncompressed) is not a checkpoint (paper-20uav: 16 MB)
MAX_STATE_BYTES = 1 << 30
_HINT = "delete it to start the mission afresh, or give another --checkpoint"

#: The decision loop's variables a checkpoint holds (``mission.decision_loop``).
LOOP_STATE = (
    "planner",
    "recorder",
    "starts",
    "home_km",
    "cells",
    "headings",
    "commanded_cells",
    "commanded_headings",
    "last_target",
    "consumed",
    "flown_km",
    "engagements",
    "engage_seq",
    "pending_engage",
    "refusals",
    "observed",
    "engaged_ids",
    "engaged_value",
    "positions",
    "previous_centres",
)

#: The mission's counters carried across a restart: attributes of its
#: ``mission_result.MissionAccount``, saved from it and restored into it by these names (under
#: ``daemon`` in the file).
DAEMON_STATE = ("overrides", "refused_commands", "looks_missed", "late_steps", "events")


#: the role of a checkpoint the daemon writes (a planner node's: ``node I``, its UAV)
DAEMON = "daemon"


def role_text(role: str) -> str:
    """A checkpoint's writer, for a line: "the daemon" or "the node of UAV I"."""
    return "the daemon" if role == DAEMON else f"the {role.replace('node', 'node of UAV')}"


class CheckpointError(UserError):
    """A checkpoint cannot be written, read, or used for this mission."""


def mission_fingerprint(scenario: Scenario, seed: int, vehicles: int, steps: int) -> str:
    """What makes a checkpoint belong to one mission: the scenario (name and content), the
    planner seed, the vehicle count and the planned steps."""
    text = repr((scenario, seed, vehicles, steps))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass
class Checkpoint:
    """The state after decision step ``step`` (0 = the start) of one mission."""

    fingerprint: str
    step: int
    loop: dict[str, Any]
    daemon: dict[str, Any]
    wall_time_s: float = 0.0  # mission wall time so far (for the result)
    saved_unix_s: float = 0.0
    role: str = DAEMON  # who wrote it: the daemon (the whole fleet), or ``node I``


@dataclass
class EncodedCheckpoint:
    """A checkpoint as it goes into a file: its JSON text and its arrays (copies)."""

    text: bytes
    arrays: list[np.ndarray]


def encode_checkpoint(checkpoint: Checkpoint) -> EncodedCheckpoint:
    """The checkpoint as data, at once (its state changes at the next step); the planner's
    :data:`DERIVED` parts are written as None."""
    arrays: list[np.ndarray] = []
    doc = {
        "fingerprint": checkpoint.fingerprint,
        "step": int(checkpoint.step),
        "wall_time_s": float(checkpoint.wall_time_s),
        "saved_unix_s": float(checkpoint.saved_unix_s),
        "role": checkpoint.role,
        "loop": {k: encode(v, arrays, k, _NOT_WRITTEN) for k, v in checkpoint.loop.items()},
        "daemon": {k: encode(v, arrays, f"daemon.{k}", _NOT_WRITTEN)
                   for k, v in checkpoint.daemon.items()},
    }  # fmt: skip
    text = json.dumps(doc, allow_nan=False, separators=(",", ":")).encode("utf-8")
    return EncodedCheckpoint(text, arrays)


# ---------------------------------------------------------------------------- writing


def write_checkpoint(path: str | Path, checkpoint: Checkpoint, key: bytes | None = None) -> int:
    """Write ``checkpoint`` to ``path`` atomically; returns the bytes written."""
    return write_encoded(path, encode_checkpoint(checkpoint), key)


def pack(encoded: EncodedCheckpoint) -> bytes:
    """The payload: an .npz (zip, deflate level 1) of ``state`` (the JSON text as uint8) and
    the arrays ``a0``, ``a1``...; written without pickles (``allow_pickle=False``)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        members = [("state", np.frombuffer(encoded.text, dtype=np.uint8))]
        members += [(f"a{i}", a) for i, a in enumerate(encoded.arrays)]
        for name, array in members:
            with archive.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, array, allow_pickle=False)
    return buffer.getvalue()


def seal(payload: bytes, key: bytes | None) -> bytes:
    """Header and payload: the tag is HMAC-SHA256(key) over the header's first 32 bytes and
    the payload, or their SHA-256 without a key."""
    start = _HEADER.pack(MAGIC, VERSION, KEYED if key else 0, len(payload), b"")[:_TAGGED]
    return _HEADER.pack(MAGIC, VERSION, KEYED if key else 0, len(payload),
                        _tag(start, payload, key)) + payload  # fmt: skip


def _tag(start: bytes, payload: bytes, key: bytes | None) -> bytes:
    if key:
        mac = hmac.new(key, start, hashlib.sha256)
        mac.update(payload)
        return mac.digest()
    return hashlib.sha256(start + payload).digest()


def write_encoded(path: str | Path, encoded: EncodedCheckpoint, key: bytes | None = None) -> int:
    """Pack, seal and write an encoded checkpoint to ``path`` atomically; returns the bytes
    written."""
    path = Path(path)
    data = seal(pack(encoded), key)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        raise CheckpointError(
            f"cannot write checkpoint {path} ({exc.strerror or exc}); choose another "
            f"--checkpoint path with free space"
        ) from None
    return len(data)


def _fsync_dir(folder: Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class CheckpointWriter:
    """Writes the loop state after every step; counts the writes. ``background``: pack and
    write in a thread, one write at a time (``flush`` waits for it; an error in it is raised
    by the next ``save`` or ``flush``). ``key``: the mission's signing key (HMAC), or None."""

    def __init__(
        self,
        path: str | Path,
        fingerprint: str,
        background: bool = False,
        key: bytes | None = None,
        role: str = DAEMON,
    ) -> None:
        self.path = Path(path)
        self.role = role
        self.fingerprint = fingerprint
        self.background = background
        self.key = key
        self.writes = 0
        self.bytes = 0
        self.announced = False  # the daemon said at start how it writes (unkeyed: once)
        self._thread: threading.Thread | None = None
        self._error: CheckpointError | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CheckpointError(
                f"cannot create the folder of checkpoint {self.path} ({exc.strerror})"
            ) from None

    def save(self, step: int, counters: Any, loop: dict[str, Any], wall_time_s: float) -> None:
        """Write the checkpoint of ``step``: the mission's ``counters`` (a ``MissionAccount``,
        :data:`DAEMON_STATE`) and the loop's variables (``loop``, :data:`LOOP_STATE`)."""
        missing = [name for name in LOOP_STATE if name not in loop]
        if missing:
            raise ValueError(f"checkpoint of step {step} lacks {', '.join(missing)}")
        state = {name: getattr(counters, name) for name in DAEMON_STATE}
        loop = {name: loop[name] for name in LOOP_STATE}
        checkpoint = Checkpoint(
            self.fingerprint, step, loop, state, wall_time_s, time.time(), self.role
        )
        encoded = encode_checkpoint(checkpoint)  # now: the state changes at the next step
        self.flush()
        if not self.background:
            self._write(encoded)
            self.flush()
            return
        self._thread = threading.Thread(
            target=self._write, args=(encoded,), name="checkpoint", daemon=False
        )
        self._thread.start()

    def _write(self, encoded: EncodedCheckpoint) -> None:
        try:
            self.bytes = write_encoded(self.path, encoded, self.key)
            self.writes += 1
        except CheckpointError as exc:
            self._error = exc

    def flush(self) -> None:
        """Wait for the write in flight; raise the error of a failed one."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error


# ---------------------------------------------------------------------------- reading


def read_checkpoint(path: str | Path, key: bytes | None = None) -> Checkpoint:
    """Read and verify a checkpoint file: format, version, length, tag (an HMAC with ``key``,
    which must be the key it was written with, or none for a file written without one), then
    its state decoded (not yet checked against a mission: :func:`load_for_mission`)."""
    path = Path(path)
    payload = _verified_payload(path, _read_bytes(path), key)
    try:
        npz = np.load(io.BytesIO(payload), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - whatever the parser says, it is a bad file
        raise CheckpointError(
            f"checkpoint {path} is corrupt (not an .npz of arrays: {_short(exc)}); {_HINT}"
        ) from None
    try:
        with npz:
            return _decode_payload(path, npz)
    except StateError as exc:
        raise CheckpointError(f"checkpoint {path} is corrupt ({exc}); {_HINT}") from None
    except (RecursionError, zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise CheckpointError(f"checkpoint {path} is corrupt ({_short(exc)}); {_HINT}") from None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(
            f"no checkpoint at {path} to resume from; run without --resume to start the mission"
        ) from None
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint {path} ({exc.strerror})") from None


def _verified_payload(path: Path, data: bytes, key: bytes | None) -> bytes:
    """The payload, once the header says it is a checkpoint of this format, whole, written
    with ``key`` (or without one, as this daemon reads it) and unchanged since."""
    if len(data) < _HEADER.size:
        raise CheckpointError(f"checkpoint {path} is truncated ({len(data)} bytes); {_HINT}")
    magic, version, flags, length, tag = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise CheckpointError(f"{path} is not a swarmplan checkpoint (bad magic); {_HINT}")
    if version in _PICKLE_VERSIONS:
        raise CheckpointError(
            f"checkpoint {path} was written by an older version (format {version}, a pickle, "
            f"no longer read); start afresh without --resume"
        )
    if version != VERSION:
        raise CheckpointError(
            f"checkpoint {path} has format version {version}, this daemon reads {VERSION}; {_HINT}"
        )
    payload = data[_HEADER.size :]
    if len(payload) != length:
        raise CheckpointError(
            f"checkpoint {path} is truncated ({len(payload)} of {length} payload bytes); {_HINT}"
        )
    if flags & ~KEYED:
        raise CheckpointError(f"checkpoint {path} is corrupt (unknown flags {flags}); {_HINT}")
    if flags & KEYED and not key:
        raise CheckpointError(
            f"checkpoint {path} was written with a signing key; give the mission's "
            f"--signing-key-file to resume from it, or start afresh without --resume"
        )
    if key and not flags & KEYED:
        raise CheckpointError(
            f"checkpoint {path} was written without a signing key, so this daemon (signing) "
            f"cannot tell it from a forged one; start afresh without --resume"
        )
    if not hmac.compare_digest(_tag(data[:_TAGGED], payload, key), tag):
        if key:
            raise CheckpointError(
                f"checkpoint {path} does not match this signing key (written with another "
                f"key, or altered since); give the mission's --signing-key-file, or start "
                f"afresh without --resume"
            )
        raise CheckpointError(f"checkpoint {path} is corrupt (checksum mismatch); {_HINT}")
    return payload


def _decode_payload(path: Path, npz: Any) -> Checkpoint:
    """The checkpoint an .npz holds: its JSON (``state``) decoded, each array read once."""
    if sum(info.file_size for info in npz.zip.infolist()) > MAX_STATE_BYTES:
        raise StateError("state", f"is larger than {MAX_STATE_BYTES >> 20} MB")
    names = set(npz.files)
    if "state" not in names:
        raise StateError("state", "is missing")
    text = npz["state"]
    if text.dtype != np.uint8 or text.ndim != 1:
        raise StateError("state", "is not a JSON text")
    doc = json.loads(text.tobytes().decode("utf-8"), parse_constant=_no_constant)
    expected = {"fingerprint", "step", "wall_time_s", "saved_unix_s", "loop", "daemon"}
    if not isinstance(doc, dict) or set(doc) - {"role"} != expected:
        raise StateError("state", "does not hold a checkpoint's fields")
    role = doc.get("role", DAEMON)  # (a daemon's of an earlier version has none)
    if not isinstance(role, str) or not re.fullmatch(r"daemon|node \d{1,6}", role):
        raise StateError("state", "has no daemon or node as its writer")
    if set(doc["loop"]) != set(LOOP_STATE) or set(doc["daemon"]) != set(DAEMON_STATE):
        raise StateError("state", "does not hold the decision loop's variables")
    if not isinstance(doc["fingerprint"], str) or type(doc["step"]) is not int:
        raise StateError("state", "has no mission fingerprint or step")
    used: set[int] = set()

    def array(k: int, where: str) -> np.ndarray:
        if k in used or f"a{k}" not in names:
            raise StateError(where, f"refers to array {k}, which is missing or used twice")
        used.add(k)
        try:
            value = npz[f"a{k}"]
        except ValueError as exc:  # an object array (pickled Python objects)
            raise StateError(where, f"is not an array of numbers ({_short(exc)})") from None
        if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
            raise StateError(where, "is not an array of numbers")
        return value

    loop = {k: decode(v, array, k) for k, v in doc["loop"].items()}
    daemon = {k: decode(v, array, f"daemon.{k}") for k, v in doc["daemon"].items()}
    if len(used) != len(names) - 1:
        raise StateError("state", "holds arrays that are not part of it")
    return Checkpoint(doc["fingerprint"], doc["step"], loop, daemon,
                      float(doc["wall_time_s"]), float(doc["saved_unix_s"]), role)  # fmt: skip


def _no_constant(name: str) -> Any:
    raise StateError("state", f"holds {name}, which is not JSON")


def _short(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:120] or type(exc).__name__


def load_for_mission(
    path: str | Path,
    fingerprint: str,
    template: dict[str, Any],
    key: bytes | None = None,
    role: str = DAEMON,
) -> Checkpoint:
    """A checkpoint of this very mission written by ``role`` (the daemon, or the node of one
    UAV), every part checked against ``template`` (the loop variables and, under ``daemon``,
    the counters this daemon starts the mission with: see ``checkpoint_layout``); else one
    :class:`CheckpointError` line."""
    checkpoint = read_checkpoint(path, key)
    if checkpoint.role != role:
        raise CheckpointError(
            f"checkpoint {path} was written by {role_text(checkpoint.role)}, not by "
            f"{role_text(role)}; give the --checkpoint this {role.split()[0]} wrote, or start "
            f"afresh without --resume"
        )
    if checkpoint.fingerprint != fingerprint:
        raise CheckpointError(
            f"checkpoint {path} belongs to another mission (scenario, seed, vehicle count or "
            f"steps differ); resume with the same options, or start afresh without --resume"
        )
    planner = template["planner"]
    mission = Mission(planner.grid.nx, planner.grid.ny, planner.n,
                      planner.cfg.tau_min, planner.cfg.tau_max)  # fmt: skip
    try:
        for name in LOOP_STATE:
            check_like(checkpoint.loop[name], template[name], name, mission, _NOT_WRITTEN)
        for name in DAEMON_STATE:
            check_like(checkpoint.daemon[name], template["daemon"][name], f"daemon.{name}",
                       mission, _NOT_WRITTEN)  # fmt: skip
        check_ranges(checkpoint.loop, mission)
    except StateError as exc:
        raise CheckpointError(
            f"checkpoint {path} does not fit this mission: {exc.path} {exc.problem} (written "
            f"by another version, or altered); start afresh without --resume"
        ) from None
    return checkpoint
