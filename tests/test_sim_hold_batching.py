"""Batched holds (SimWorld._hold_span): a sleep of several force-loop periods while the arm
holds a regulated force is one scalar recurrence and one block of samples instead of one
sub-chunk per 10 ms period. It must be the same physics and the same noise as the sub-chunk
path (to float rounding), deterministic, and stop at the same sample when anything could
end the hold (it hands such spans back to the sub-chunk path)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from elastoprobe.controller.core.devices import MotionState

from test_sim_helpers import Log, digest, make_cell, press, tick, wait

UP = (0.0, 0.0, 1.0)
POINTS = {"rubber_ball": (0.0, 0.0, 130.0), "composite": (130.0, 0.0, 80.0)}


def _hold_and_scan(cell, log: Log, hold_s: float, scans: int, poll_s: float = 0.1) -> list:
    """The controller's hold: settle, then a scan burst, polling every ``poll_s``."""
    end = cell.clock.now_s() + hold_s
    while cell.clock.now_s() < end - 1e-9:
        tick(cell, log, min(poll_s, end - cell.clock.now_s()))
    cell.scanner.read_scans()
    cell.scanner.start_burst(scans)
    got: list = []
    deadline = cell.clock.now_s() + 3.0
    while len(got) < scans and cell.clock.now_s() < deadline:
        tick(cell, log, poll_s)
        got.extend(cell.scanner.read_scans())
    return got


def _run(obj: str, batching: bool, force_n: float = 12.0, angle_deg: float = 90.0, seed: int = 4):
    cell = make_cell(obj=obj, seed=seed)
    cell.world.hold_batching = batching
    cell.begin_step((seed, 1, 0))
    press(cell, POINTS[obj], UP, angle_deg, force_n, settle_s=0.2)
    log = Log()
    scans = _hold_and_scan(cell, log, 2.0, 20)
    return cell, log, scans


@pytest.mark.parametrize("obj, angle_deg", [("rubber_ball", 90.0), ("rubber_ball", 45.0), ("composite", 90.0)])
def test_batched_hold_matches_the_sub_chunk_path(obj, angle_deg):
    fast, log_f, scans_f = _run(obj, True, angle_deg=angle_deg)
    slow, log_s, scans_s = _run(obj, False, angle_deg=angle_deg)
    # The batch was really taken (otherwise this compares the sub-chunk path with itself).
    assert fast.world.stats["hold_periods"] >= 200 and fast.world.stats["hold_fallbacks"] == 0
    assert slow.world.stats["hold_periods"] == 0
    assert np.array_equal(log_f.times(), log_s.times())
    # Same physics and noise, another float order: agreement far below the 0.04 N noise.
    np.testing.assert_allclose(log_f.forces(), log_s.forces(), rtol=0, atol=1e-9)
    assert [s.exposure_t_s for s in scans_f] == [s.exposure_t_s for s in scans_s]
    zf, zs = np.array([s.z_mm for s in scans_f]), np.array([s.z_mm for s in scans_s])
    assert np.array_equal(np.isnan(zf), np.isnan(zs))
    np.testing.assert_allclose(zf[~np.isnan(zf)], zs[~np.isnan(zs)], rtol=0, atol=1e-9)
    cf, cs = fast.world.contact, slow.world.contact
    assert abs(cf.push_mm - cs.push_mm) < 1e-9 and abs(cf.creep_c - cs.creep_c) < 1e-12
    assert abs(fast.arm._u - slow.arm._u) < 1e-9
    assert fast.arm._regulator.in_band == slow.arm._regulator.in_band
    if obj == "composite":
        # The foam creeps: the batched loop keeps pushing as the sub-chunk loop does.
        assert cf.creep_c < 1.0


def test_batched_hold_is_deterministic():
    a = _run("rubber_ball", True)
    b = _run("rubber_ball", True)
    assert digest(a[1], a[2]) == digest(b[1], b[2])


def test_the_batch_ends_on_time_whatever_the_sleep():
    # A sleep that is not a whole number of loop periods: the rest is a sub-chunk.
    cell = make_cell(seed=2)
    cell.begin_step((2, 1, 0))
    press(cell, POINTS["rubber_ball"], UP, 90.0, 8.0, settle_s=0.2)
    log = Log()
    t0 = cell.world.now_us
    tick(cell, log, 0.137)
    assert cell.world.now_us == t0 + 136_000           # floored onto the 2 ms control grid
    assert cell.world.stats["hold_spans"] == 1
    t = log.times()
    assert t.size == 136 and np.allclose(np.diff(t), 1e-3)


def _force_trip_run(batching: bool):
    cell = make_cell(seed=9)
    cell.params.limits = replace(cell.params.limits, max_force_n=20.1)
    cell.world.limits = cell.world.guard.limits = cell.params.limits
    cell.world._screen_force_limit = min(20.1, cell.world.limits.max_lateral_force_n)
    cell.world.hold_batching = batching
    cell.begin_step((9, 1, 0))
    d, _, _, _ = press(cell, POINTS["rubber_ball"], UP, 90.0, 12.0, settle_s=0.2)
    log = Log()
    _hold_and_scan(cell, log, 1.0, 0)                 # batched spans at 12 N
    # Held at 19.97 N, the noise crosses 20.1 N now and then (seed 9: ~8 s into the hold).
    motion = cell.arm.regulate_force(d, 19.97, 10.0)
    assert wait(cell, motion, log) == MotionState.DONE
    end = cell.clock.now_s() + 10.0
    while cell.arm.trip() is None and cell.clock.now_s() < end:
        tick(cell, log, 0.1)
    return cell, log


def test_a_crossing_in_a_batched_hold_stops_at_the_same_sample():
    fast, log_f = _force_trip_run(True)
    slow, log_s = _force_trip_run(False)
    trip_f, trip_s = fast.arm.trip(), slow.arm.trip()
    assert trip_f is not None and trip_s is not None
    assert trip_f.kind == trip_s.kind == "force"
    assert trip_f.t_s == trip_s.t_s
    assert abs(trip_f.value - trip_s.value) < 1e-9
    # Batches were committed before, and a span the screen could not clear was handed back.
    assert fast.world.stats["hold_spans"] > 0 and fast.world.stats["hold_fallbacks"] > 0
    # The arm stopped: nothing after the crossing is regulated any more.
    assert fast.arm._regulator is None
    assert np.array_equal(log_f.times(), log_s.times())


def test_a_fault_inside_a_hold_starts_at_its_sample():
    def run(batching: bool):
        cell = make_cell(seed=3)
        cell.world.hold_batching = batching
        cell.begin_step((3, 1, 0))
        press(cell, POINTS["rubber_ball"], UP, 90.0, 5.0, settle_s=0.2)
        log = Log()
        _hold_and_scan(cell, log, 0.6, 0)              # batched
        cell.faults.inject("force_spike", delay_s=0.373)
        _hold_and_scan(cell, log, 0.8, 0)
        return cell, log

    (fast, log_f), (slow, log_s) = run(True), run(False)
    assert fast.world.stats["hold_spans"] > 0
    trip_f, trip_s = fast.arm.trip(), slow.arm.trip()
    assert trip_f is not None and trip_s is not None
    assert trip_f.kind == trip_s.kind and trip_f.t_s == trip_s.t_s
    assert fast.arm.status().is_moving is False or fast.arm._regulator is None
    np.testing.assert_allclose(log_f.forces(), log_s.forces(), rtol=0, atol=1e-9)


def test_no_batch_while_the_force_ramps():
    cell = make_cell(seed=6)
    cell.begin_step((6, 1, 0))
    d, _, _, _ = press(cell, POINTS["rubber_ball"], UP, 90.0, 5.0, settle_s=0.2)
    motion = cell.arm.regulate_force(d, 15.0, 10.0)
    spans = cell.world.stats["hold_spans"]
    tick(cell, None, 0.5)                               # a long sleep while RUNNING
    assert motion.state() == MotionState.RUNNING
    assert cell.world.stats["hold_spans"] == spans


def test_a_protective_stop_due_at_a_loop_update_ends_the_hold_without_a_batch():
    """The fault fires as the batch starts and is over at once (a protective stop halts the
    arm in that instant): the batch must see the hold has ended (a soak night died here)."""
    cell = make_cell(seed=3)
    cell.begin_step((3, 1, 0))
    press(cell, POINTS["rubber_ball"], UP, 90.0, 5.0, settle_s=0.2)
    log = Log()
    _hold_and_scan(cell, log, 0.6, 0)                  # batched
    due_us = cell.arm._next_update_us + 5 * cell.arm.loop_period_us
    cell.faults.inject("protective_stop", delay_s=(due_us - cell.world.now_us) / 1e6)
    _hold_and_scan(cell, log, 0.8, 0)
    assert cell.arm.supervisor.regulation is None and cell.arm._protective_since_us == due_us
