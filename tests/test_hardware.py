"""The hardware process on loopback: contact search and force loop against the simulated
world's truth, a force spike over UDP tripping and stopping the arm, a protective stop
with bounded recovery; plus the pieces that need no network (device timebase, resampling)."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from elastoprobe.controller.core.devices import MotionState, WrenchBlock
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.drivers.hardware import DeviceTimebase
from elastoprobe.controller.drivers.ur_link import URLinkConfig
from elastoprobe.sim.servers.world_backend import resample_profile
from test_loopback_rig import make_rig, run_on_a_live_stream, wait_for, wait_motion


def test_device_timebase_undoes_compressed_bursts() -> None:
    tb = DeviceTimebase(1000.0)
    seq = np.arange(100, 110)
    # Ten samples that arrived together 40 ms late: the client clamped them to arrival.
    t_client = np.concatenate([[10.100], 10.140 + np.arange(1, 10) * 1e-5])
    z = np.zeros((10, 3))
    out = tb.retime(WrenchBlock(t_client, seq, z, z, np.zeros(10, np.uint32)))
    assert np.allclose(np.diff(out.t_s), 1e-3)
    # The next block keeps the spacing and never goes back in time.
    out2 = tb.retime(WrenchBlock(np.array([10.2]), np.array([110]), z[:1], z[:1], np.zeros(1, np.uint32)))
    assert out2.t_s[0] > out.t_s[-1]


def test_device_timebase_returns_from_a_late_burst_and_never_goes_back() -> None:
    """After a burst that arrived 250 ms late, on-time samples get their arrival times back
    (within a few hundred ms of sample time), never a time after their arrival, and times
    never decrease on the way."""
    tb = DeviceTimebase(1000.0)
    z = np.zeros((1, 3))
    st = np.zeros(1, np.uint32)
    times, arrivals = [], []
    for seq in range(1, 3001):
        true_t = 100.0 + seq * 1e-3
        # Samples 1000..1249 are held back and arrive together at 1.250 s, compressed by the
        # client to its arrival; the rest arrive on time (the client's anchor is exact then).
        if 1000 <= seq < 1250:
            continue
        if seq == 1250:
            seqs = np.arange(1000, 1251)
            t_client = 100.0 + 1.250 - np.arange(seqs.size)[::-1] * 1e-6      # <= their arrival
            out = tb.retime(WrenchBlock(t_client, seqs, np.zeros((seqs.size, 3)), np.zeros((seqs.size, 3)),
                                        np.zeros(seqs.size, np.uint32)))
            times.extend(out.t_s.tolist())
            arrivals.extend([100.0 + 1.250] * seqs.size)
            continue
        out = tb.retime(WrenchBlock(np.array([true_t]), np.array([seq]), z, z, st))
        times.extend(out.t_s.tolist())
        arrivals.append(true_t)
    t = np.asarray(times)
    assert np.all(np.diff(t) > 0)
    assert np.all(t <= np.asarray(arrivals) + 1e-9)
    # The burst keeps its device spacing; a second after it the times are exact again.
    assert np.allclose(np.diff(t[999:1250]), 1e-3)
    assert np.allclose(t[-1000:], 100.0 + np.arange(2001, 3001) * 1e-3)


def test_resample_keeps_holes_and_interpolates_lines() -> None:
    x = np.linspace(-10, 10, 41)
    z = 100.0 + 0.5 * x
    z[18:23] = np.nan                        # a shadow
    grid = np.linspace(-12, 12, 97)
    out = resample_profile(x, z, grid)
    inside = (np.abs(grid) <= 10) & ~((grid > -1.3) & (grid < 1.3))
    assert np.allclose(out[inside & np.isfinite(out)], 100.0 + 0.5 * grid[inside & np.isfinite(out)])
    assert np.isfinite(out[inside]).mean() > 0.95
    assert np.all(np.isnan(out[np.abs(grid) > 10]))
    assert np.all(np.isnan(out[np.abs(grid) < 1.0]))     # the hole is not bridged


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_contact_force_loop_and_spike_trip_on_loopback() -> None:
    def scenario(rig) -> None:  # noqa: ANN001 — test_loopback_rig.Rig
        arm, ft = rig.hw.arm, rig.hw.ft
        above = rig.go_above_ball()
        time.sleep(0.3)
        ft.tare()
        d = above.rotation[:, 2]                              # tool +z: straight down
        seek = arm.seek_contact(d, 5.0, 0.4, 40.0)
        assert wait_motion(seek, 15.0) == MotionState.CONTACT
        tip_z = arm.status().tcp_pose.position_mm[2]
        # The ball (radius 65 mm, top at 130 mm) touches a 5 mm tip when its centre is near 135 mm.
        assert 133.0 < tip_z < 137.0
        press = arm.regulate_force(d, 5.0, 10.0)
        assert wait_motion(press, 10.0) == MotionState.DONE
        ft.read_block()
        time.sleep(1.0)
        block = ft.read_block()
        measured = np.linalg.norm(block.force_n.mean(axis=0))
        truth = rig.backend.world.contact.force_n         # the simulated world's true contact force
        assert abs(measured - 5.0) < 0.25
        assert abs(truth - 5.0) < 0.6                      # tare left gravity and bias out; drift is small
        assert press.state() == MotionState.DONE           # still holding
        # Unload, then a free move interrupted by a force spike streamed over UDP.
        arm.stop()
        assert wait_motion(arm.move_linear(above, 20.0, 500.0), 10.0) == MotionState.DONE
        far = Pose(above.position_mm + np.array([0.0, 80.0, 0.0]), above.rotation)
        move = arm.move_linear(far, 20.0, 500.0)
        time.sleep(0.8)
        assert move.state() == MotionState.RUNNING
        rig.backend.inject("force_spike", magnitude=80.0, duration_s=0.06)
        assert wait_motion(move, 3.0) == MotionState.TRIPPED
        trip = arm.trip()
        assert trip is not None and trip.kind in ("force", "force_rate", "lateral_force")
        assert trip.raw is not None and len(trip.raw) > 100
        assert wait_for(lambda: not rig.emulator.is_moving(), 1.0)
        stopped_y = rig.emulator.tcp_pose_ur()[1] * 1e3
        assert stopped_y < far.position_mm[1] - 20.0       # stopped well short of the target
        time.sleep(0.3)
        assert abs(rig.emulator.tcp_pose_ur()[1] * 1e3 - stopped_y) < 0.5   # and stays stopped
        assert arm.rearm()                                 # the spike is over: below the hysteresis
        assert arm.trip() is None
        stats = rig.hw.stats()
        assert stats["latency"]["trips"] >= 1

    run_on_a_live_stream(lambda: make_rig(130), scenario)


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_protective_stop_mid_probe_then_bounded_recovery() -> None:
    def scenario(rig) -> None:  # noqa: ANN001 — test_loopback_rig.Rig
        arm = rig.hw.arm
        above = rig.go_above_ball(160.0)
        time.sleep(0.3)
        rig.hw.ft.tare()
        seek = arm.seek_contact(above.rotation[:, 2], 5.0, 0.4, 40.0)
        time.sleep(0.5)
        rig.emulator.inject_protective_stop("test")
        assert wait_motion(seek, 3.0) == MotionState.FAULT
        assert wait_for(lambda: arm.status().protective_stop, 2.0)
        z_stop = arm.status().tcp_pose.position_mm[2]
        assert z_stop > 140.0                               # it never reached the ball
        assert arm.recover_protective_stop()
        status = arm.status()
        assert status.program_running and not status.protective_stop
        # The re-uploaded script started with the robot's installation TCP; the link set the
        # believed tool again, so the probe tip (not the flange) goes where it is sent.
        assert rig.emulator.tcp_offset_ur == pytest.approx(rig.cfg.flange_to_tcp.to_ur(), abs=1e-12)
        # Re-seeded from the measured pose: a new move works.
        assert wait_motion(arm.move_linear(above, 50.0, 500.0), 10.0) == MotionState.DONE
        assert np.linalg.norm(arm.status().tcp_pose.position_mm - above.position_mm) < 1.0
        assert np.linalg.norm(_true_tip_mm(rig) - above.position_mm) < 1.0

    link = URLinkConfig(frequency_hz=125.0, call_timeout_s=3.0, unlock_wait_s=1.2)
    run_on_a_live_stream(lambda: make_rig(140, unlock_delay_s=1.0, link=link), scenario)


def _true_tip_mm(rig) -> np.ndarray:  # noqa: ANN001 — test_loopback_rig.Rig
    """Where the served world's probe tip really is (base frame, mm)."""
    world = rig.backend.world
    with rig.backend.lock:
        return rig.backend.arm._sim_tip_base(world.tip_offset_tcp_mm)


def _tip_off_by_4_mm(spec):  # noqa: ANN001, ANN202 — controller.config.CellSpec
    """The served cell's true tip 4 mm from where its file says (nothing else miscalibrated)."""
    sim = spec.simulation
    mis = sim.miscalibration.model_copy(update={"enabled": True, "tip_mm": 4.0, "payload_mass_rel": 0.0,
                                                "payload_com_mm": 0.0, "scanner_deg": 0.0, "scanner_mm": 0.0})
    return spec.model_copy(update={"simulation": sim.model_copy(update={"miscalibration": mis})})


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_the_believed_tool_s_tip_lands_where_commanded_over_the_real_protocols() -> None:
    """The controller plans and commands TCP poses for the tool it believes in (the cell file
    with its calibration applied). The link sets that TCP on the robot (setTcp) and the
    emulator, as a UR does, moves and reports that TCP: a tool other than the file's nominal
    one (here calibrated: the true tip 4 mm off the file's) puts the true tip at the
    commanded point. Without setTcp the flange would go there (the tip 160 mm off); with a
    robot that kept the file's TCP, the tip would be 4 mm off."""
    def scenario(rig) -> None:  # noqa: ANN001 — test_loopback_rig.Rig
        truth = rig.backend.cell.truth
        assert np.linalg.norm(truth.tip_offset_mm) == pytest.approx(4.0)
        # A perfect tip calibration: the believed TCP is the true tip centre.
        believed = rig.cfg.flange_to_tcp.compose(Pose(truth.tip_offset_mm, np.eye(3)))
        rig.cfg = replace(rig.cfg, flange_to_tcp=believed)
        rig.start_hardware()
        assert rig.emulator.tcp_offset_ur == pytest.approx(believed.to_ur(), abs=1e-12)
        arm = rig.hw.arm
        rot = arm.status().tcp_pose.rotation
        for target_mm in ([400.0, 0.0, 160.0], [380.0, 40.0, 175.0]):
            target = Pose(np.array(target_mm), rot)
            assert wait_motion(arm.move_linear(target, 100.0, 600.0), 15.0) == MotionState.DONE
            time.sleep(0.1)
            assert np.linalg.norm(arm.status().tcp_pose.position_mm - target.position_mm) < 0.05
            assert np.linalg.norm(_true_tip_mm(rig) - target.position_mm) < 0.05

    run_on_a_live_stream(lambda: make_rig(185, start_hardware=False, spec_update=_tip_off_by_4_mm), scenario)
