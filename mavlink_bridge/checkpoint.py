"""The daemon's checkpoint: the planner's state and the decision loop's own, written atomically
after every decision step, so a daemon killed mid-mission (``kill -9``, a crash, a power cut)
can be started again with ``--resume`` and carry on from the last step it finished.

File format (version 3): a 64-byte header, then a pickle (protocol 5) of a :class:`Checkpoint`,
compressed with zlib at its fastest level (version 2, the same uncompressed, is still read).

* header: ``MAGIC`` (16 bytes), format version (uint32), payload length (uint64), the SHA-256
  of the payload as stored (32 bytes), 4 reserved bytes; all little-endian.
* payload: the planner object (``HapfAcoPlanner``: TPMs, pheromone maps, coverage, tracks, its
  random generator...) without what the scenario alone determines (:data:`DERIVED`: the safety
  models it caches, the TPM diffusion's stencil and scratch buffers, half the bytes, taken
  from the planner the resumed daemon builds), the recorder, and the loop variables of
  ``MissionDaemon._decision_loop`` named in :data:`LOOP_STATE`. A 10-UAV checkpoint pickles to
  about 5 MB (10-15 MB before: issue 12, finding 9) and compresses to about 1.7 MB (zlib level
  1, ~80 ms on this machine); the TPMs, most of it, change everywhere at every step, so a
  delta would not be smaller.

Writing: the state is pickled at once (it changes at the next step); compressing and writing
can go to a background thread (``CheckpointWriter(background=True)``, the daemon's: zlib and
the file system release the GIL, so the decision loop does not wait), one write at a time, the
next save (or ``flush``) waiting for the one before. Into ``PATH.tmp`` in the same folder,
flushed and fsync'ed, then ``os.replace`` over ``PATH`` (atomic on POSIX and Windows), then the
folder is fsync'ed: a reader sees the previous checkpoint or the new one, never a mix, whenever
the writer dies.

Reading checks, in order: the file exists and is readable, the magic, the version, the length
and the digest (a torn or corrupted file), and that it belongs to this mission (scenario name and
content, seed, vehicle count, steps). Unpickling is restricted to the classes a checkpoint holds
(numpy arrays and generators, the planner's own classes, plain containers): a checkpoint file is
data, and a crafted one must not run code. Every failure is one :class:`CheckpointError` line
saying what is wrong and what to do.
"""

from __future__ import annotations

import copy
import hashlib
import io
import os
import pickle
import struct
import threading
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planner.errors import UserError
from planner.scenario import Scenario

MAGIC = b"SWARMPLAN-CKPT\x00\x01"
VERSION = 3  # zlib-compressed pickle
_UNCOMPRESSED_VERSION = 2  # a plain pickle, still read
#: planner attributes (``owner.attribute`` paths from the planner) determined by the scenario
#: alone: not written; a resumed daemon takes them from the planner it builds for the mission
DERIVED = (
    "beliefs._safety",
    "beliefs.tpm.stencil",
    "beliefs.tpm.work",
    "beliefs.tpm.wiener_work",
    "beliefs.tpm.ratio_lookup",
    "beliefs.tpm.drift_layers",
)
_HEADER = struct.Struct("<16sIQ32s4x")  # 64 bytes

#: The decision loop's variables a checkpoint holds (see MissionDaemon._decision_loop).
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

#: The daemon's own counters carried across a restart.
DAEMON_STATE = ("overrides", "refused_commands", "looks_missed", "late_steps", "events")


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
    notes: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------- writing


def write_checkpoint(path: str | Path, checkpoint: Checkpoint) -> int:
    """Write ``checkpoint`` to ``path`` atomically; returns the bytes written."""
    return write_pickled(path, pickle.dumps(checkpoint, protocol=5))


def write_pickled(path: str | Path, pickled: bytes) -> int:
    """Compress a pickled :class:`Checkpoint` and write it to ``path`` atomically; returns the
    bytes written."""
    path = Path(path)
    payload = zlib.compress(pickled, 1)
    header = _HEADER.pack(MAGIC, VERSION, len(payload), hashlib.sha256(payload).digest())
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        raise CheckpointError(
            f"cannot write checkpoint {path} ({exc.strerror or exc}); choose another "
            f"--checkpoint path with free space"
        ) from None
    return len(header) + len(payload)


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
    """Writes the loop state after every step; counts the writes. ``background``: compress and
    write in a thread, one write at a time (``flush`` waits for it; an error in it is raised
    by the next ``save`` or ``flush``)."""

    def __init__(self, path: str | Path, fingerprint: str, background: bool = False) -> None:
        self.path = Path(path)
        self.fingerprint = fingerprint
        self.background = background
        self.writes = 0
        self.bytes = 0
        self._thread: threading.Thread | None = None
        self._error: CheckpointError | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CheckpointError(
                f"cannot create the folder of checkpoint {self.path} ({exc.strerror})"
            ) from None

    def save(self, step: int, daemon: Any, loop: dict[str, Any], wall_time_s: float) -> None:
        import time

        missing = [name for name in LOOP_STATE if name not in loop]
        if missing:
            raise ValueError(f"checkpoint of step {step} lacks {', '.join(missing)}")
        state = {name: getattr(daemon, name) for name in DAEMON_STATE}
        loop = dict(loop, planner=without_derived(loop["planner"]))
        checkpoint = Checkpoint(self.fingerprint, step, loop, state, wall_time_s, time.time())
        pickled = pickle.dumps(checkpoint, protocol=5)  # now: the state changes at the next step
        self.flush()
        if not self.background:
            self._write(pickled)
            self.flush()
            return
        self._thread = threading.Thread(
            target=self._write, args=(pickled,), name="checkpoint", daemon=False
        )
        self._thread.start()

    def _write(self, pickled: bytes) -> None:
        try:
            self.bytes = write_pickled(self.path, pickled)
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

#: numpy names a checkpoint may contain (arrays, scalars, dtypes, random generators).
_NUMPY_NAMES = {
    "_reconstruct",
    "scalar",
    "ndarray",
    "dtype",
    "_frombuffer",
    "__generator_ctor",
    "__bit_generator_ctor",
    "__randomstate_ctor",
    "Generator",
    "PCG64",
    "SeedSequence",
    "_unpickle",
    "__pyx_unpickle_SeedSequence",
}
#: scipy.sparse matrices (the planner keeps some operators sparse).
_SPARSE_NAMES = {"csr_matrix", "csc_matrix", "coo_matrix", "csr_array", "csc_array", "coo_array"}
_BUILTINS = {
    "set",
    "frozenset",
    "complex",
    "slice",
    "range",
    "tuple",
    "list",
    "dict",
    "bytearray",
    "bytes",
    "float",
    "int",
    "bool",
    "str",
    "getattr",
}
_MODULE_PREFIXES = ("planner.", "mavlink_bridge.checkpoint", "mavlink_bridge.daemon")


class _RestrictedUnpickler(pickle.Unpickler):
    """Only the classes a checkpoint is made of; anything else is a corrupt (or crafted) file."""

    def find_class(self, module: str, name: str) -> Any:
        allowed = (
            (module == "builtins" and name in _BUILTINS)
            or (module.split(".")[0] == "numpy" and name in _NUMPY_NAMES)
            or (module.startswith("scipy.sparse") and name in _SPARSE_NAMES)
            or (module == "collections" and name in ("deque", "OrderedDict"))
            or (module == "copyreg" and name == "_reconstructor")
            or (
                (module.startswith(_MODULE_PREFIXES) or module in ("planner",))
                and not name.startswith("_")
            )
        )
        if not allowed:
            raise pickle.UnpicklingError(f"{module}.{name} is not part of a checkpoint")
        value = super().find_class(module, name)
        if module.startswith(_MODULE_PREFIXES) and not isinstance(value, type):
            raise pickle.UnpicklingError(f"{module}.{name} is not a class")
        return value


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read and verify a checkpoint file (format, version, digest); any problem is one line."""
    path = Path(path)
    hint = "delete it to start the mission afresh, or give another --checkpoint"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(
            f"no checkpoint at {path} to resume from; run without --resume to start the mission"
        ) from None
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint {path} ({exc.strerror})") from None
    if len(data) < _HEADER.size:
        raise CheckpointError(f"checkpoint {path} is truncated ({len(data)} bytes); {hint}")
    magic, version, length, digest = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise CheckpointError(f"{path} is not a swarmplan checkpoint (bad magic); {hint}")
    if version not in (VERSION, _UNCOMPRESSED_VERSION):
        raise CheckpointError(
            f"checkpoint {path} has format version {version}, this daemon reads "
            f"{_UNCOMPRESSED_VERSION} and {VERSION}; {hint}"
        )
    payload = data[_HEADER.size :]
    if len(payload) != length:
        raise CheckpointError(
            f"checkpoint {path} is truncated ({len(payload)} of {length} payload bytes); {hint}"
        )
    if hashlib.sha256(payload).digest() != digest:
        raise CheckpointError(f"checkpoint {path} is corrupt (checksum mismatch); {hint}")
    if version == VERSION:
        try:
            payload = zlib.decompress(payload)
        except zlib.error as exc:
            raise CheckpointError(f"checkpoint {path} is corrupt ({exc}); {hint}") from None
    try:
        checkpoint = _RestrictedUnpickler(io.BytesIO(payload)).load()
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise CheckpointError(
            f"checkpoint {path} cannot be loaded ({type(exc).__name__}: {exc}); {hint}"
        ) from None
    if not isinstance(checkpoint, Checkpoint):
        raise CheckpointError(f"checkpoint {path} holds no mission state; {hint}")
    missing = [n for n in LOOP_STATE if n not in checkpoint.loop]
    missing += [n for n in DAEMON_STATE if n not in checkpoint.daemon]
    if missing:
        raise CheckpointError(
            f"checkpoint {path} lacks {', '.join(missing)} (written by another version); {hint}"
        )
    return checkpoint


def load_for_mission(path: str | Path, fingerprint: str, planner_cls: type) -> Checkpoint:
    """A checkpoint of this very mission whose planner is ``planner_cls``; else CheckpointError."""
    checkpoint = read_checkpoint(path)
    if checkpoint.fingerprint != fingerprint:
        raise CheckpointError(
            f"checkpoint {path} belongs to another mission (scenario, seed, vehicle count or "
            f"steps differ); resume with the same options, or start afresh without --resume"
        )
    planner = checkpoint.loop["planner"]
    if type(planner) is not planner_cls:
        raise CheckpointError(
            f"checkpoint {path} holds a {type(planner).__name__}, not a {planner_cls.__name__}"
        )
    return checkpoint


def _split(path: str) -> tuple[list[str], str]:
    *owners, name = path.split(".")
    return owners, name


def without_derived(planner: Any) -> Any:
    """A shallow copy of ``planner`` whose :data:`DERIVED` attributes are None (the live planner
    and its parts are untouched: every object on a path to one is copied, nothing else)."""
    lean = copy.copy(planner)
    for path in DERIVED:
        owners, name = _split(path)
        obj = lean
        for owner in owners:
            if not hasattr(obj, owner):
                break
            part = copy.copy(getattr(obj, owner))
            setattr(obj, owner, part)
            obj = part
        else:
            if hasattr(obj, name):
                setattr(obj, name, None)
    return lean


def with_derived(restored: Any, fresh: Any) -> None:
    """Put the :data:`DERIVED` attributes of ``fresh`` (built for this mission) into
    ``restored``."""
    for path in DERIVED:
        owners, name = _split(path)
        src, dst = fresh, restored
        for owner in owners:
            src, dst = getattr(src, owner, None), getattr(dst, owner, None)
        if hasattr(src, name) and dst is not None:
            setattr(dst, name, getattr(src, name))


def restore_daemon_state(daemon: Any, checkpoint: Checkpoint) -> dict[str, Any]:
    """Put the daemon's counters back; returns the loop variables (by LOOP_STATE name)."""
    for name in DAEMON_STATE:
        setattr(daemon, name, checkpoint.daemon[name])
    return checkpoint.loop


def check_planner_layout(restored: Any, fresh: Any, path: str | Path) -> None:
    """The restored planner has the attributes this code's planner has (same planner version)."""
    old, new = set(vars(restored)), set(vars(fresh))
    if old != new:
        diff = sorted(old ^ new)[:4]
        raise CheckpointError(
            f"checkpoint {path} was written by another planner version (state differs in "
            f"{', '.join(diff)}); start the mission afresh without --resume"
        )


def resume_loop_state(daemon: Any, checkpoint: Checkpoint, fresh_planner: Any) -> dict[str, Any]:
    """The decision loop's variables from ``checkpoint``, with the daemon's counters restored.

    ``fresh_planner`` is the planner this code builds for the mission: the restored one must
    have the same layout (a checkpoint of another planner version is refused)."""
    check_planner_layout(checkpoint.loop["planner"], fresh_planner, daemon.options.checkpoint_path)
    with_derived(checkpoint.loop["planner"], fresh_planner)
    break_measured_legs(checkpoint.loop["recorder"])
    daemon.say(
        f"resuming from the checkpoint of step {checkpoint.step} ({daemon.options.checkpoint_path})"
    )
    return restore_daemon_state(daemon, checkpoint)


def break_measured_legs(recorder: Any) -> None:
    """The outage is not a leg: while the daemon was down the autopilots' failsafe flew the
    vehicles (loitering, circling), so the straight chord from the last position before the
    crash to the first one after it, and the turns at its ends, say nothing about the
    planner's path. The recorder starts each UAV's leg chain afresh after a restart (threat
    and separation are still judged at every recorded position; the distance flown during the
    outage is not in the recorder's total, while the safety envelope's range account, between
    measured cells, includes it)."""
    recorder.break_legs()
