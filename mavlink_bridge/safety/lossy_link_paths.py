"""The paths a plane may fly when a lossy link delivers its guided commands late or not at all.

The flight-path layer (``flight_envelope.py``) judges each candidate target also on these
variants of its predicted path: its DO_CHANGE_SPEED lost (the plane keeps the airspeed it flies
now: at 150 m/s it turns on a 2.29 km radius, not the 1.02 km of 100 m/s), and, in paced time,
its DO_REPOSITION arriving ``command_delay_s`` late, after the plane flew on to its previous
target meanwhile (each with and without the new airspeed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavlink_bridge.vehicles.flight_prediction import PlaneModel, predict_paths


@dataclass
class LossyLinkPaths:
    """Candidates' paths as a lossy link may deliver their commands (V variants, M candidates,
    one sample a second; :func:`lossy_link_paths`)."""

    from_command: np.ndarray  # (V, M, S + 1, 2) from where the command takes hold
    #: (V, M, S + 1, 2) from now, the same instants as the prediction; None without a command
    #: delay (lockstep: separation is judged on the prediction alone)
    from_now: np.ndarray | None


def lossy_link_paths(
    model: PlaneModel,
    horizon_s: float,
    command_delay_s: float,
    positions_km: np.ndarray,
    courses_rad: np.ndarray,
    speeds_mps: np.ndarray,
    previous_aims_km: np.ndarray,
    row_uav: np.ndarray,
    aims_km: np.ndarray,
    commanded_mps: np.ndarray,
) -> LossyLinkPaths:
    """Each candidate's path (row ``r`` of ``aims_km``, flown by UAV ``row_uav[r]``) as a lossy
    link may deliver its commands (see the module docstring). Predicted every second to
    ``horizon_s`` from where the command takes hold (``from_command``: what the threat clearance
    judges; the stretch flown to the previous target before a late command is not counted, no
    choice of this step changes it) and from now, that stretch first (``from_now``: the
    instants separation is judged at)."""
    held = np.asarray(speeds_mps, dtype=float)[row_uav]
    starts = np.asarray(positions_km, dtype=float)[row_uav].reshape(-1, 2)
    courses = np.asarray(courses_rad, dtype=float)[row_uav]
    variants = [(starts, courses, held, held)]
    delay_s = round(command_delay_s)
    on_way = None
    if delay_s >= 1:
        on_way, late_known, late_starts, late_courses = _late_starts(
            model,
            delay_s,
            positions_km,
            courses_rad,
            speeds_mps,
            previous_aims_km,
            row_uav,
            starts,
            courses,
        )
        variants += [
            (late_starts, late_courses, held, commanded_mps),
            (late_starts, late_courses, held, held),
        ]
    m = len(aims_km)
    flown = predict_paths(
        model,
        np.concatenate([v[0] for v in variants]),
        np.concatenate([v[1] for v in variants]),
        np.tile(aims_km, (len(variants), 1)),
        horizon_s,
        dt_s=0.5,  # a clearance check: 2.8 deg of turn a step at 100 m/s is fine enough
        speed_mps=np.concatenate([v[2] for v in variants]),
        commanded_mps=np.concatenate([v[3] for v in variants]),
    ).reshape(len(variants), m, -1, 2)
    from_now = None
    if on_way is not None:  # the late ones: the stretch to the previous target first
        from_now = flown.copy()
        samples = flown.shape[2]
        late = np.concatenate([np.broadcast_to(on_way, (2, *on_way.shape)), flown[1:, :, 1:]],
                              axis=2)[:, :, :samples]  # fmt: skip
        from_now[1:, late_known] = late[:, late_known]  # no previous target: from now
    return LossyLinkPaths(from_command=flown, from_now=from_now)


def _late_starts(
    model: PlaneModel,
    delay_s: int,
    positions_km: np.ndarray,
    courses_rad: np.ndarray,
    speeds_mps: np.ndarray,
    previous_aims_km: np.ndarray,
    row_uav: np.ndarray,
    starts: np.ndarray,
    courses: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where each row's plane is, and on what course, when a command ``delay_s`` late takes
    hold: it flew on to its previous target meanwhile (a plane with none is where it is now).
    Returns the stretch flown meanwhile (rows, every 0.5 s), which rows have a previous target,
    and the late starts and courses."""
    previous = np.asarray(previous_aims_km, dtype=float)
    known = np.all(np.isfinite(previous), axis=1)
    on_way = predict_paths(
        model, positions_km, courses_rad, np.where(known[:, None], previous,
        np.asarray(positions_km, dtype=float)), delay_s, dt_s=0.5, speed_mps=speeds_mps,
    )[row_uav]  # fmt: skip
    late_xy = on_way[:, -1]
    move = on_way[:, -1] - on_way[:, -2]
    late_course = np.where(
        np.hypot(move[:, 0], move[:, 1]) > 0, np.arctan2(move[:, 1], move[:, 0]), courses
    )
    late_known = known[row_uav]
    late_starts = np.where(late_known[:, None], late_xy, starts)
    late_courses = np.where(late_known, late_course, courses)
    return on_way, late_known, late_starts, late_courses
