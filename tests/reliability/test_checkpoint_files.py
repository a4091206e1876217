"""Checkpoint files are data (issue 31, finding 1): a crafted file of each kind is refused in one
line before any of it reaches the planner, and never runs code; a signed checkpoint is read only
with its key; a planner resumed from a checkpoint decides as the one that kept flying.

Most files are made here from a real checkpoint of a planner that flew a few steps, changed in
one place and sealed again as an attacker who knows the format would (for the unkeyed files,
with the SHA-256 anyone can compute). Some go through ``swarmplan daemon --checkpoint F
--resume`` as a subprocess: one line on stderr, exit 2, the payload never ran."""

from __future__ import annotations

import hashlib
import io
import json
import pickle
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loopback import run_swarmplan
from reliability_harness import KEY_HEX

from mavlink_bridge.mission.decision_step import LoopState
from mavlink_bridge.results.checkpoint import (
    DAEMON_STATE,
    MAGIC,
    CheckpointError,
    CheckpointWriter,
    load_for_mission,
    mission_fingerprint,
    seal,
)
from mavlink_bridge.results.checkpoint_layout import MISSING, RANGES, range_part
from mavlink_bridge.results.checkpoint_resume import with_derived
from mavlink_bridge.results.mission_result import LinkEvent, MissionAccount
from planner.engagement import EngagementOutcome
from planner.grid import Grid
from planner.hapf_aco import HapfAcoPlanner
from planner.metrics import MissionRecorder
from planner.pursuit_log import PursuitLog
from planner.scenario import load_scenario

SCENARIO, SEED, STEPS = "paper-10uav", 5, 24
KEY = bytes.fromhex(KEY_HEX)
FINGERPRINT = mission_fingerprint(load_scenario(SCENARIO), SEED, 10, STEPS)


# ---------------------------------------------------------------------- a mission's state


def _start() -> tuple[LoopState, Grid]:
    """The loop state a daemon starts this mission with (planner, its pursuit log, recorder)."""
    scenario = load_scenario(SCENARIO)
    starts = scenario.starts_for_seed(SEED)
    cfg = scenario.config
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    planner = HapfAcoPlanner(scenario, starts, SEED)
    PursuitLog().attach(planner)
    recorder = MissionRecorder(scenario, starts)
    return LoopState.start(grid, planner, recorder, starts, [-1] * len(starts)), grid


def _fly(state: LoopState, grid: Grid, steps: int) -> list[tuple[np.ndarray, ...]]:
    """``steps`` decisions, each recorded; the decisions (cells, headings, engage)."""
    decisions = []
    for _ in range(steps):
        d = state.planner.step(state.cells.copy(), state.headings.copy(),
                               [None] * len(state.cells), state.engagements)  # fmt: skip
        state.cells, state.headings = np.asarray(d.next_cells), np.asarray(d.next_headings)
        centres = grid.centre_km(state.cells)
        state.recorder.record_step(centres, planned_km=centres)
        state.recorder.record_modes(d.modes)
        decisions.append((state.cells.copy(), state.headings.copy(), np.asarray(d.engage).copy()))
    return decisions


def _template() -> dict[str, Any]:
    state, _ = _start()
    account = MissionAccount()
    return {**state.checkpoint_view(), "daemon": {n: getattr(account, n) for n in DAEMON_STATE}}


def _flown_state() -> tuple[LoopState, Grid, MissionAccount]:
    """A state 6 steps into the mission, with an engagement, a lost link and a target."""
    state, grid = _start()
    _fly(state, grid, 6)
    state.last_target = [(12.5, 40.25)] + [None] * (len(state.cells) - 1)
    state.engagements[0] = EngagementOutcome(True, 3, 2.0)
    state.engaged_ids = {3}
    state.recorder.record_engagement(5, 0, 3, 2.0)
    account = MissionAccount()
    account.events.append(LinkEvent(4, 2, "lost", 12.5, "silent 3.2 s"))
    return state, grid, account


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """An unkeyed checkpoint of step 6."""
    state, _, account = _flown_state()
    path = tmp_path_factory.mktemp("ckpt") / "good.ckpt"
    CheckpointWriter(path, FINGERPRINT).save(6, account, state.checkpoint_view(), 1.0)
    return path


@pytest.fixture(scope="module")
def template() -> dict[str, Any]:
    return _template()


# ---------------------------------------------------------------------- crafting files


def _open(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The JSON document and arrays of a checkpoint file (read as an attacker would)."""
    npz = np.load(io.BytesIO(path.read_bytes()[64:]), allow_pickle=False)
    arrays = {name: npz[name] for name in npz.files if name != "state"}
    return json.loads(npz["state"].tobytes()), arrays


def _write(path: Path, doc: dict, arrays: dict[str, np.ndarray], key: bytes | None = None):
    buffer = io.BytesIO()
    text = np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)
    np.savez(buffer, state=text, **arrays)  # (allows object arrays: what a crafter may do)
    path.write_bytes(seal(buffer.getvalue(), key))


def _node(doc: dict, path: str) -> dict:
    """The JSON node of ``planner.beliefs.tpm.maps`` (attributes of objects, from a loop
    variable)."""
    root, *names = path.split(".")
    node = doc["loop"][root]
    for name in names:
        node = node["$object"][1][name]
    return node


def _crafted(good: Path, tmp_path: Path, change, key: bytes | None = None) -> Path:
    doc, arrays = _open(good)
    change(doc, arrays)
    path = tmp_path / "crafted.ckpt"
    _write(path, doc, arrays, key)
    return path


def _array(doc: dict, arrays: dict, path: str) -> str:
    return f"a{_node(doc, path)['$array']}"


class _Call:
    """Pickles as ``f(*args)``: the building block of a pickle that runs code when loaded."""

    def __init__(self, f: Any, *args: Any) -> None:
        self.f, self.args = f, args

    def __reduce__(self):
        return (self.f, self.args)

    def __call__(self, *args: Any) -> Any:  # (the pickler wants a callable; never called)
        raise AssertionError("only pickled")


def _eval_pickle(marker: Path) -> bytes:
    """The exploit of issue 31: from a class the old unpickler allowed, ``getattr`` reaches a
    function's ``__globals__``, the builtins, ``eval``; the payload writes ``marker``."""
    method = _Call(getattr, Grid, "centre_km")
    module = _Call(getattr, method, "__globals__")
    builtins = _Call(_Call(getattr, module, "get"), "__builtins__")
    evaluate = _Call(_Call(getattr, builtins, "get"), "eval")
    code = f"__import__('pathlib').Path({str(marker)!r}).write_text('ran')"
    return pickle.dumps(_Call(evaluate, code), protocol=5)


def _old_format_file(path: Path, pickled: bytes) -> None:
    """A file in the format of the pickling daemon (version 3: zlib'd pickle, SHA-256)."""
    payload = zlib.compress(pickled, 1)
    header = struct.pack("<16sIQ32s4x", MAGIC, 3, len(payload), hashlib.sha256(payload).digest())
    path.write_bytes(header + payload)


def _refused(path: Path, match: str, template: dict, key: bytes | None = None) -> str:
    with pytest.raises(CheckpointError, match=match) as info:
        load_for_mission(path, FINGERPRINT, template, key)
    assert "\n" not in str(info.value)
    return str(info.value)


# ---------------------------------------------------------------------- code in a file


def test_the_pickle_eval_exploit_of_the_old_format_is_refused_and_never_runs(tmp_path, template):
    marker = tmp_path / "ran"
    path = tmp_path / "old.ckpt"
    _old_format_file(path, _eval_pickle(marker))
    _refused(path, "written by an older version .* start afresh without --resume", template)
    assert not marker.exists()


def test_a_pickle_sealed_as_the_new_format_is_not_an_npz_and_never_runs(tmp_path, template):
    marker = tmp_path / "ran"
    path = tmp_path / "renamed.ckpt"
    path.write_bytes(seal(_eval_pickle(marker), None))
    _refused(path, "corrupt \\(not an .npz", template)
    assert not marker.exists()


def test_an_object_array_in_the_npz_is_refused_and_never_runs(tmp_path, good, template):
    marker = tmp_path / "ran"

    def change(doc, arrays):
        evil = np.empty(1, dtype=object)
        evil[0] = _Call(eval, f"__import__('pathlib').Path({str(marker)!r}).write_text('r')")
        arrays[_array(doc, arrays, "planner.beliefs.tpm.maps")] = evil

    _refused(_crafted(good, tmp_path, change), "not an array of numbers", template)
    assert not marker.exists()


@pytest.mark.parametrize(
    ("node", "match"),
    [
        ({"$object": ["Popen", {}]}, "'Popen', which is not part of a checkpoint"),
        ({"$object": ["subprocess.Popen", {}]}, "not part of a checkpoint"),
        ({"$eval": "__import__('os')"}, "unknown form '\\$eval'"),
        ({"$method": ["__init__", {"$object": ["PursuitLog", {}]}]}, "method '__init__'"),
        ({"$generator": {"bit_generator": "MT19937", "state": {}}}, "PCG64"),
        ({"$scalar": ["object", 1]}, "not a numpy number"),
        ({"$array": 10_000}, "array 10000, which is missing"),
    ],
)
def test_forms_a_checkpoint_does_not_hold_are_refused(tmp_path, good, template, node, match):
    def change(doc, arrays):
        beliefs = doc["loop"]["planner"]["$object"][1]["beliefs"]
        beliefs["$object"][1]["tpm"] = node

    _refused(_crafted(good, tmp_path, change), f"planner.beliefs.tpm.*{match}", template)


# ---------------------------------------------------------------------- layout and ranges


def _set_attr(path: str, value: Any):
    def change(doc, arrays):
        owner, name = path.rsplit(".", 1)
        _node(doc, owner)["$object"][1][name] = value

    return change


def _drop_attr(path: str):
    def change(doc, arrays):
        owner, name = path.rsplit(".", 1)
        del _node(doc, owner)["$object"][1][name]

    return change


def _edit_array(path: str, edit):
    def change(doc, arrays):
        key = _array(doc, arrays, path)
        arrays[key] = edit(arrays[key].copy())

    return change


def _put(a: np.ndarray, index: Any, value: Any) -> np.ndarray:
    a[index] = value
    return a


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (_set_attr("planner.beliefs.k", "6"), "planner.beliefs.k is a str, this daemon's is a int"),
        (_drop_attr("planner.beliefs.k"), "planner.beliefs has attributes k .*lacks"),
        (_set_attr("planner.backdoor", 1), "planner has attributes backdoor"),
        (
            _set_attr("planner.beliefs.tpm.steps", {"$float": "nan"}),
            "planner.beliefs.tpm.steps is a float",
        ),
        (_set_attr("planner.cfg.p_detect", 1.5), "planner.cfg.p_detect holds 1.5, outside"),
        (_set_attr("planner.cfg.q0", {"$float": "inf"}), "planner.cfg.q0 is inf"),
        (
            _edit_array("planner.beliefs.tpm.maps", lambda a: a[:, :, :50]),
            "planner.beliefs.tpm.maps has shape",
        ),
        (
            _edit_array("planner.beliefs.tpm.maps", lambda a: a.astype(np.float64)),
            "is a float64 array",
        ),
        (_edit_array("planner.beliefs.tpm.maps", lambda a: np.asfortranarray(a)), "C order"),
        (_edit_array("planner.beliefs.tpm.maps", lambda a: _put(a, (0, 0, 5, 5), np.nan)), "NaN"),
        (_edit_array("planner.beliefs.tpm.maps", lambda a: a * 1e4), "probability of .* above 1"),
        (_edit_array("planner.beliefs.tpm.maps", lambda a: -a), "planner.beliefs.tpm.maps holds -"),
        (_edit_array("planner.pheromone.tau", lambda a: _put(a, 0, np.inf)), "infinite"),
        (_edit_array("planner.pheromone.tau", lambda a: a * 5), "tau .*outside \\[0.1, 1\\]"),
        (_edit_array("planner.beliefs.cells", lambda a: _put(a, 0, (150, 3))), "cell \\(150, 3\\)"),
        (
            _edit_array("planner.beliefs.track", lambda a: _put(a, 1, (4, -3))),
            "planner.beliefs.track holds cell",
        ),
        (
            _edit_array("planner.beliefs.headings", lambda a: _put(a, 2, 9)),
            "planner.beliefs.headings holds 9",
        ),
        (_edit_array("planner.beliefs.home_flat", lambda a: _put(a, 0, -5)), "home_flat holds -5"),
    ],
)
def test_a_part_unlike_this_missions_is_named_in_one_line(tmp_path, good, template, change, match):
    _refused(_crafted(good, tmp_path, change), f"does not fit this mission: .*{match}", template)


@pytest.mark.parametrize(
    ("root", "edit", "match"),
    [
        ("cells", lambda n: _put(n, 0, -1), "cells holds cell"),
        ("positions", lambda n: _put(n, 0, np.nan), "positions holds NaN"),
        ("commanded_headings", lambda n: _put(n, 0, 8), "commanded_headings holds 8"),
        ("flown_km", lambda n: _put(n, 0, -1.0), "flown_km holds -1"),
    ],
)
def test_a_loop_variable_out_of_range_is_named(tmp_path, good, template, root, edit, match):
    def change(doc, arrays):
        key = f"a{doc['loop'][root]['$array']}"
        arrays[key] = edit(arrays[key].copy())

    _refused(_crafted(good, tmp_path, change), match, template)


@pytest.mark.parametrize(
    ("where", "value", "match"),
    [
        (("loop", "last_target"), [[1.0, 2.0]] * 10, "last_target\\[0\\] is not a tuple"),
        (("loop", "engaged_ids"), {"$set": [1.5]}, "engaged_ids: holds items"),
        (
            ("loop", "engagements"),
            [{"$object": ["LinkEvent", {}]}] + [None] * 9,
            "engagements\\[0\\] is a LinkEvent, not a EngagementOutcome",
        ),
        (("loop", "consumed"), [0] * 9, "consumed has 9 items, this daemon's has 10"),
        (("daemon", "overrides"), {"$dict": [["area", 0]]}, "daemon.overrides has keys"),
        (("daemon", "events"), [{"$object": ["LinkEvent", {"step": 1}]}], "fields of a LinkEvent"),
    ],
)
def test_a_loop_variable_or_counter_of_the_wrong_kind_is_named(
    tmp_path, good, template, where, value, match
):
    def change(doc, arrays):
        doc[where[0]][where[1]] = value

    _refused(_crafted(good, tmp_path, change), match, template)


def test_a_recorder_curve_out_of_range_is_named(tmp_path, good, template):
    def change(doc, arrays):
        curve = _node(doc, "recorder.coverage_curve")
        curve[-1] = {"$scalar": ["float64", 1.5]}

    _refused(_crafted(good, tmp_path, change), "recorder.coverage_curve\\[5\\] is 1.5", template)


def test_a_random_generator_state_out_of_range_is_named(tmp_path, good, template):
    def change(doc, arrays):
        _node(doc, "planner.rng")["$generator"]["state"]["inc"] = 2**130

    _refused(_crafted(good, tmp_path, change), "planner.rng", template)


# ---------------------------------------------------------------------- the file and its key


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b[:30], "truncated"),
        (lambda b: b[:300] + bytes([b[300] ^ 1]) + b[301:], "checksum mismatch"),
        (lambda b: b[:40] + bytes([b[40] ^ 1]) + b[41:], "checksum mismatch"),  # the tag
    ],
)
def test_a_damaged_unkeyed_file_is_refused(tmp_path, good, template, damage, match):
    path = tmp_path / "damaged.ckpt"
    path.write_bytes(damage(good.read_bytes()))
    _refused(path, match, template)


def test_a_signed_checkpoint_needs_its_key(tmp_path, template):
    state, _, account = _flown_state()
    path = tmp_path / "signed.ckpt"
    CheckpointWriter(path, FINGERPRINT, key=KEY).save(6, account, state.checkpoint_view(), 1.0)
    assert load_for_mission(path, FINGERPRINT, template, KEY).step == 6
    _refused(path, "written with a signing key; give the mission's --signing-key-file", template)
    _refused(path, "does not match this signing key", template, bytes(32))
    data = path.read_bytes()
    path.write_bytes(data[:500] + bytes([data[500] ^ 0x10]) + data[501:])
    _refused(path, "does not match this signing key", template, KEY)
    # an attacker without the key can only write an unkeyed file: a signing daemon refuses it
    unkeyed = tmp_path / "unkeyed.ckpt"
    CheckpointWriter(unkeyed, FINGERPRINT).save(6, account, state.checkpoint_view(), 1.0)
    _refused(unkeyed, "written without a signing key", template, KEY)


# ---------------------------------------------------------------------- resuming


def test_a_resumed_planner_decides_bit_identically(tmp_path, template):
    """Written signed at step 6, read back, checked against this mission and completed with
    the parts the scenario determines: the next 8 decisions equal those of the planner that
    kept flying, and its pursuit log and recorder carry on from where they were."""
    state, grid = _start()
    _fly(state, grid, 6)
    path = tmp_path / "c.ckpt"
    CheckpointWriter(path, FINGERPRINT, key=KEY).save(
        6, MissionAccount(), state.checkpoint_view(), 1.0
    )
    fresh, _ = _start()
    resumed = LoopState.from_checkpoint(load_for_mission(path, FINGERPRINT, template, KEY).loop)
    with_derived(resumed.planner, fresh.planner)
    assert PursuitLog.of(resumed.planner).tracks == PursuitLog.of(state.planner).tracks
    kept, again = _fly(state, grid, 8), _fly(resumed, grid, 8)
    for a, b in zip(kept, again, strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert resumed.recorder.result(SEED, "hapf-aco", 0.0) == state.recorder.result(
        SEED, "hapf-aco", 0.0
    )


# ---------------------------------------------------------------------- the command line


def _resume(tmp_path: Path, ckpt: Path, *extra: str):
    return run_swarmplan(
        ["daemon", "--connect", "udpin:127.0.0.1:0", "--scenario", SCENARIO, "--seed",
         str(SEED), "--steps", str(STEPS), "--out", str(tmp_path / "out"), "--timeout", "1",
         "--checkpoint", str(ckpt), *extra],
        timeout=60,
    )  # fmt: skip


def _one_line_exit_2(proc, match: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert match in proc.stderr, proc.stderr


def test_swarmplan_daemon_resume_refuses_crafted_files_in_one_line(tmp_path, good):
    marker = tmp_path / "ran"
    old = tmp_path / "old.ckpt"
    _old_format_file(old, _eval_pickle(marker))
    renamed = tmp_path / "renamed.ckpt"
    renamed.write_bytes(seal(_eval_pickle(marker), None))
    (tmp_path / "shape").mkdir()
    shape = _crafted(good, tmp_path / "shape",
                     _edit_array("planner.beliefs.tpm.maps", lambda a: a[:, :5]))  # fmt: skip
    for ckpt, match in [
        (old, "written by an older version"),
        (renamed, "not an .npz"),
        (shape, "planner.beliefs.tpm.maps has shape"),
    ]:
        _one_line_exit_2(_resume(tmp_path, ckpt, "--resume"), match)
        assert not marker.exists()
    key_file = tmp_path / "other.key"
    key_file.write_text("11" * 32)
    _one_line_exit_2(
        _resume(tmp_path, good, "--resume", "--signing-key-file", str(key_file)),
        "written without a signing key",
    )


def test_swarmplan_daemon_says_when_its_checkpoint_is_not_authenticated(tmp_path):
    ckpt = tmp_path / "d.ckpt"
    unkeyed = _resume(tmp_path, ckpt)
    assert unkeyed.returncode == 2  # no vehicle within --timeout
    notes = [line for line in unkeyed.stderr.splitlines() if "not authenticated" in line]
    assert len(notes) == 1, unkeyed.stderr
    key_file = tmp_path / "mission.key"
    key_file.write_text(KEY_HEX)
    keyed = _resume(tmp_path, ckpt, "--signing-key-file", str(key_file))
    assert keyed.returncode == 2 and "not authenticated" not in keyed.stderr, keyed.stderr


def test_every_range_check_names_a_part_of_the_daemons_state():
    """A range check whose path names nothing would be skipped in silence (a part renamed or
    moved): every path of RANGES reaches a value in a flown mission's state."""
    state, _, _ = _flown_state()
    view = state.checkpoint_view()
    for path in RANGES:
        part = range_part(view, path)
        assert part is not None and part is not MISSING, f"RANGES names {path}: nothing there"
