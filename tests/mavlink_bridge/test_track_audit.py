"""The continuous safety account (mavlink_bridge/safety/track_audit.py) on tracks built by hand:
what happens between two reports is judged, not only the reports themselves."""

from __future__ import annotations

import numpy as np

from mavlink_bridge.safety.track_audit import TrackAudit


def audit(threats=((5.0, 5.0, 1.0),), n=2, **kw) -> TrackAudit:
    t = np.array(threats, float).reshape(-1, 3)
    return TrackAudit(n, t[:, :2], t[:, 2], min_separation_km=1.0, **kw)


def test_head_on_pair_meets_between_reports():
    """Reports 10 s apart show both planes 2 km apart; they passed through each other."""
    a = audit(threats=())
    a.set_phase("mission")
    for t, xa, xb in ((0.0, 0.0, 2.0), (10.0, 2.0, 0.0)):
        a.add(0, t, (xa, 0.0))
        a.add(1, t, (xb, 0.1))
    s = a.summary()
    assert s["all"]["separation_breaches"] == 1
    assert s["all"]["min_separation_km"] < 0.11
    assert s["phases"]["mission"]["closest_pair_uavs"] == [0, 1]


def test_reports_at_other_instants_are_interpolated_on_a_common_time_base():
    """Plane 1 reports at odd seconds, plane 0 at even ones: both fly east 0.5 km apart."""
    a = audit(threats=())
    for k in range(10):
        a.add(0, 2.0 * k, (0.1 * 2 * k, 0.0))
        a.add(1, 2.0 * k + 1, (0.1 * (2 * k + 1), 0.5))
    s = a.summary()
    assert abs(s["all"]["min_separation_km"] - 0.5) < 1e-6
    assert s["all"]["separation_breaches"] == 1  # one episode, not one per interval


def test_segment_through_a_threat_counts_one_entry_and_its_depth():
    a = audit()
    a.set_phase("rtl")
    a.add(0, 0.0, (3.0, 5.0))
    a.add(0, 5.0, (7.0, 5.0))  # both ends 1 km outside the circle; the chord crosses its centre
    a.add(0, 10.0, (9.0, 5.0))
    s = a.summary()
    assert s["phases"]["rtl"]["threat_entries"] == 1
    assert abs(s["phases"]["rtl"]["min_threat_margin_km"] + 1.0) < 1e-9


def test_phases_are_reported_apart_and_failsafe_flag_wins():
    a = audit(threats=((0.0, 10.0, 1.0),))
    a.set_phase("mission")
    a.add(0, 0.0, (0.0, 0.0))
    a.add(0, 5.0, (0.0, 0.5))
    a.add(0, 10.0, (0.0, 8.5), in_failsafe=True)  # into the zone while the link is out
    a.add(0, 15.0, (0.0, 9.5), in_failsafe=True)
    s = a.summary()
    assert s["phases"]["mission"]["threat_entries"] == 0
    assert s["phases"]["failsafe"]["threat_entries"] == 1
    assert s["all"]["threat_entries"] == 1


def test_a_gap_longer_than_the_limit_is_not_interpolated():
    a = audit(threats=(), max_gap_s=10.0)
    a.add(0, 0.0, (0.0, 0.0))
    a.add(1, 0.0, (2.0, 0.0))
    a.add(0, 30.0, (2.0, 0.0))  # 30 s silent: the straight line would cross plane 1
    a.add(1, 30.0, (0.0, 0.0))
    s = a.summary()
    assert s["all"]["separation_breaches"] == 0
    assert s["unobserved_uav_s"] == 60.0


def test_separate_clocks_are_aligned_by_arrival():
    """Vehicle 1 booted 100 s later: its clock reads 100 s less for the same instant."""
    a = audit(threats=())
    for k in range(11):
        wall = float(k)
        a.add(0, wall, (0.2 * k, 0.0), arrival_scaled_s=wall + 0.01)
        a.add(1, wall - 100.0, (2.0 - 0.2 * k, 0.0), arrival_scaled_s=wall + 0.01)
    s = a.summary()
    assert s["clock_offsets_s"][1] - s["clock_offsets_s"][0] == 100.0
    assert s["all"]["min_separation_km"] < 1e-6


def test_clocks_drifting_apart_are_aligned_by_arrival_all_along():
    """Two SITL instances booted together whose clocks drift apart (vehicle 0 starved: 0.8 s of
    its clock per scaled second). They cross the origin on perpendicular lines 200 s apart (2.8 km
    at the closest); both clocks read 800 s there, so aligned by the clocks they would collide
    (as a single offset per vehicle, equal at boot, had them)."""
    a = audit(threats=())
    a.set_phase("mission")
    for k in range(2001):
        wall = float(k)
        a.add(0, 0.8 * wall, (0.0, -20.0 + 0.02 * wall), arrival_scaled_s=wall + 0.01)
        a.add(1, wall, (-16.0 + 0.02 * wall, 0.0), arrival_scaled_s=wall + 0.01)
    s = a.summary()
    assert s["all"]["separation_breaches"] == 0
    assert abs(s["all"]["min_separation_km"] - 4.0 / 2**0.5) < 0.01
    assert abs(s["clock_drift_s"][0] - 400.0) < 10.0 and s["clock_drift_s"][1] == 0.0


def test_a_shared_clock_with_late_reports_gets_no_correction():
    """One simulator's clock for both, reports arriving 0.01-0.5 s late: no offset at all."""
    a = audit(threats=())
    rng = np.random.default_rng(1)
    for k in range(600):
        for uav in (0, 1):
            a.add(uav, float(k), (0.02 * k, 2.0 * uav), arrival_scaled_s=k + rng.uniform(0.01, 0.5))
    s = a.summary()
    assert s["clock_offsets_s"] == [0.0, 0.0] and s["clock_drift_s"] == [0.0, 0.0]
    assert abs(s["all"]["min_separation_km"] - 2.0) < 1e-9


def test_a_report_belongs_to_the_phase_of_its_own_time_not_of_its_arrival():
    """In lockstep a grant's reports arrive whenever the machine gets to them: one stamped
    before the phase changed, taken in after, is still the earlier phase's. The account ends
    with end(): what arrives later (a released simulator running free) is not added."""
    a = audit(threats=(), n=1)
    a.add(0, 0.0, (0.0, 0.0))
    a.add(0, 10.0, (1.0, 0.0))
    a.set_phase("mission")  # at the vehicle's 10 s
    a.add(0, 5.0, (0.5, 0.0))  # late, stamped within the launch
    a.add(0, 20.0, (2.0, 0.0))
    a.end()
    a.add(0, 30.0, (3.0, 0.0))
    s = a.summary()
    assert s["phases"]["launch"]["observed_uav_s"] == 10.0
    assert s["phases"]["mission"]["observed_uav_s"] == 10.0
    assert s["reports"] == 4
