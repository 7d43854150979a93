"""Trips and injected faults, each observed only through the device interfaces."""
from __future__ import annotations

import numpy as np
import pytest

from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.errors import DeviceError
from elastoprobe.sim.faults import FaultPlan

from test_sim_helpers import Log, burst, hold, make_cell, press, standoff_pose, go_to, tick, wait


def _seeking(cell):
    """Start a slow seek downward in free air (tared), so the arm is moving."""
    hold(cell, 0.1)
    cell.ft.tare()
    hold(cell, 0.05)
    return cell.arm.seek_contact(np.array([0.0, 0.0, -1.0]), 5.0, 0.4, 40.0)


def test_force_spike_trips_and_the_arm_stops_at_that_instant():
    cell = make_cell()
    motion = _seeking(cell)
    hold(cell, 0.2)
    before = cell.arm.status()
    cell.faults.inject("force_spike", delay_s=0.0123)
    while cell.arm.trip() is None and cell.clock.now_s() < before.t_s + 1.0:
        tick(cell)
    trip = cell.arm.trip()
    assert trip is not None and trip.kind in ("force", "force_rate")
    spike_at = cell.faults.injected[-1][1]
    assert spike_at <= trip.t_s <= spike_at + 0.005            # the crossing sample's instant
    assert motion.state() == MotionState.TRIPPED
    assert trip.raw is not None and trip.raw.t_s[-1] <= trip.t_s + 1e-9
    stop = cell.arm.status().tcp_pose.position_mm
    hold(cell, 0.5)
    assert np.allclose(cell.arm.status().tcp_pose.position_mm, stop)        # stopped
    # It moved no further than the seek speed up to the trip plus its stopping distance.
    travelled = float(np.linalg.norm(stop - before.tcp_pose.position_mm))
    assert travelled <= 5.0 * (trip.t_s - before.t_s) + 5.0 ** 2 / (2 * 2500.0) + 1e-3
    # A spike is not a force: the guard re-arms once the reading is back down.
    assert cell.arm.rearm() and cell.arm.trip() is None


def test_force_limit_trip_overshoot_is_physical_and_small():
    cell = make_cell()
    d, p, n, t = press(cell, (0.0, 0.0, 130.0), (0.0, 0.0, 1.0), 90.0, 30.0, settle_s=0.2)
    log = Log()
    motion = cell.arm.regulate_force(d, 60.0, 100.0)       # the cell's limit is 45 N
    wait(cell, motion, log)
    hold(cell, 0.3, log)
    trip = cell.arm.trip()
    assert motion.state() == MotionState.TRIPPED and trip is not None and trip.kind == "force"
    f = np.linalg.norm(log.forces(), axis=1)
    overshoot_n = float(f.max() - trip.limit)
    print(f"force-limit trip: overshoot {overshoot_n:.3f} N over {trip.limit} N at 100 N/s")
    assert 0.0 < overshoot_n < 2.0
    # Above the hysteresis level the guard refuses to re-arm.
    assert not cell.arm.rearm()
    # Unloading along the normal is not stopped again by the same, still-latched crossing.
    pose = cell.arm.status().tcp_pose
    from elastoprobe.controller.core.geometry import Pose
    assert wait(cell, cell.arm.move_linear(Pose(pose.position_mm + n * 20.0, pose.rotation), 10.0, 500.0)) \
        == MotionState.DONE
    assert cell.world.contact is None and cell.arm.rearm()


def test_stalled_stream_is_missing_data_and_trips_stale():
    cell = make_cell()
    motion = _seeking(cell)
    hold(cell, 0.1)
    cell.faults.inject("ft_stall", duration_s=0.2)
    empty_polls = 0
    for _ in range(10):
        cell.clock.sleep_s(0.01)
        empty_polls += len(cell.ft.read_block()) == 0
    assert empty_polls >= 5
    assert cell.arm.trip() is not None and cell.arm.trip().kind == "stale"
    assert motion.state() == MotionState.TRIPPED
    hold(cell, 0.3)
    cell.clock.sleep_s(0.05)
    block = cell.ft.read_block()
    assert len(block) == 50 and np.all(np.diff(block.seq) == 1)      # flowing again


def test_frozen_stream_repeats_values_and_trips_frozen():
    cell = make_cell()
    _seeking(cell)
    cell.faults.inject("ft_frozen", duration_s=0.2)
    log = Log()
    hold(cell, 0.15, log)
    f = log.forces()
    assert np.any(np.all(f[1:] == f[:-1], axis=1))
    assert cell.arm.trip() is not None and cell.arm.trip().kind == "frozen"


def test_scanner_timeout_and_short_burst_show_as_missing_profiles():
    cell = make_cell()
    cell.faults.inject("scanner_timeout", duration_s=1.0)
    scans, _ = burst(cell, 10)
    assert scans == []
    hold(cell, 1.0)
    cell.faults.inject("scanner_short_burst", duration_s=1.0, magnitude=0.5)
    scans, _ = burst(cell, 10)
    assert len(scans) == 5
    hold(cell, 1.0)
    scans, _ = burst(cell, 10)
    assert len(scans) == 10


def test_connection_loss_raises_from_commands_then_recovers():
    cell = make_cell()
    cell.faults.inject("connection_loss", duration_s=0.5)
    tick(cell)
    status = cell.arm.status()
    assert not status.connected and not status.program_running
    with pytest.raises(DeviceError):
        cell.arm.move_linear(cell.home_pose(), 10.0, 100.0)
    hold(cell, 0.6)
    assert cell.arm.status().connected


def test_object_moved_changes_when_contact_comes():
    travelled = []
    for faults in ([], [FaultPlan("object_moved", step=7, delay_s=0.0, magnitude=12.0)]):
        cell = make_cell(seed=4, faults=faults)
        normal = np.array([20.0, 0.0, 60.0]) / np.linalg.norm([20.0, 0.0, 60.0])
        point = np.array([0.0, 0.0, 65.0]) + 65.0 * normal          # on the ball, off its top
        standoff, p, n, t = standoff_pose(cell, point, normal, 90.0)
        go_to(cell, standoff, 250.0)
        cell.begin_step((4, 7, 0))
        hold(cell, 0.2)
        cell.ft.tare()
        start = cell.arm.status().tcp_pose.position_mm
        state = wait(cell, cell.arm.seek_contact(standoff.rotation[:, 2], 5.0, 0.4, 45.0))
        travelled.append((state, float(np.linalg.norm(cell.arm.status().tcp_pose.position_mm - start))))
    (s0, d0), (s1, d1) = travelled
    assert s0 == MotionState.CONTACT
    assert s1 == MotionState.NO_CONTACT or abs(d1 - d0) > 1.0


def test_slip_fault_trips_the_slip_monitor():
    cell = make_cell()
    press(cell, (0.0, 0.0, 130.0), (0.0, 0.0, 1.0), 45.0, 5.0, settle_s=0.2)
    assert cell.arm.trip() is None
    cell.faults.inject("slip", magnitude=20.0)
    hold(cell, 1.0)
    trip = cell.arm.trip()
    assert trip is not None and trip.kind == "slip" and trip.value > cell.params.limits.slip_mm


def test_step_rate_and_time_schedules_are_keyed():
    plans = [FaultPlan("protective_stop", step=3), FaultPlan("force_spike", rate_per_100_steps=30.0)]

    def fired(seed: int) -> list[tuple[int, int, str]]:
        cell = make_cell(seed=seed, faults=plans)
        out = []
        for step in range(20):
            for attempt in (0, 1):
                cell.begin_step((seed, step, attempt))
                n_before = len(cell.faults.injected)
                hold(cell, 2.2)
                out += [(step, attempt, k) for k, _ in cell.faults.injected[n_before:]]
                if cell.arm.status().protective_stop:
                    cell.arm.recover_protective_stop()
                cell.arm.rearm()
        return out

    a = fired(11)
    assert (3, 0, "protective_stop") in a and (3, 1, "protective_stop") not in a   # first attempt only
    spikes = [x for x in a if x[2] == "force_spike"]
    assert 3 <= len(spikes) <= 22                                                  # ~30 % of 40 attempts
    assert fired(11) == a                                                          # keyed: reproducible
    cell = make_cell(faults=[FaultPlan("emergency_stop", at_t_s=0.5, clear_after_s=1.0)])
    hold(cell, 0.6)
    assert cell.arm.status().emergency_stop
    hold(cell, 1.0)
    assert not cell.arm.status().emergency_stop


def test_follow_up_faults_come_while_the_first_is_handled(tmp_path, monkeypatch):
    """A follow-up plan fires 0.3-3 s after another fault (the controller is still stopping
    and retracting then), keyed by the step: a resumed process draws the same; it has no
    follow-ups of its own, and the durable record says what it followed."""
    import json

    log = tmp_path / "faults.jsonl"
    monkeypatch.setenv("ELASTOPROBE_SIM_FAULT_LOG", str(log))
    plans = [FaultPlan("protective_stop", step=2, delay_s=0.5),
             FaultPlan("connection_loss", rate_per_100_faults=100.0)]

    def fired() -> list[tuple[str, float]]:
        cell = make_cell(faults=plans)
        for step in range(4):
            cell.begin_step((1, step, 0))
            hold(cell, 4.0)
        return cell.faults.injected

    got = fired()
    kinds = [k for k, _ in got]
    assert kinds == ["protective_stop", "connection_loss"]          # one follow-up, none of its own
    assert 0.3 <= got[1][1] - got[0][1] <= 3.0 + 1e-3
    assert fired() == got                                            # keyed: reproducible
    records = [json.loads(line) for line in log.read_text().splitlines()]
    follow = [r for r in records if r["kind"] == "connection_loss"]
    assert follow and follow[0]["follows"] == "protective_stop" and follow[0]["key"] == [1, 2, 0]
    with pytest.raises(ValueError, match="follow-up"):
        FaultPlan("disk_error", rate_per_100_faults=5.0)


def test_devices_expose_no_fault_side_channel():
    cell = make_cell()
    for device in (cell.arm, cell.ft, cell.scanner):
        public = [name for name in dir(device) if not name.startswith("_")]
        assert not [name for name in public if "fault" in name.lower() or "inject" in name.lower()], public
