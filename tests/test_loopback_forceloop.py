"""The force loop and the operator's authority on loopback: the real drivers (the hardware
process, ur_rtde 1.6.5 in its supervised child, the Net F/T client) against the project's UR
emulator made faithful to a real controller (docs/ur_emulation.md: a move while ur_rtde's speed
thread runs halts the program; the input registers outlive a program).

- unload after regulation: the link ends the speed command (speedStop) before its moveL;
- recovery from a protective stop during regulation: the arm does not move until commanded
  (the link clears the command register before it uploads the script again);
- retract after a force trip: the retract is let through the latched trip, a push is not;
- a program stopped from the dashboard: the link reports the operator's stop, restarts
  nothing, and the arm stays where the operator left it until an explicit recovery;
- a failed start (the TCP offset read back wrong) leaves no control script running, and a
  dashboard reply a UR would not give is a device error;
- the hardware process runs the same supervisor (code and gains) as the in-process cell.

Each test runs on its own 127.0.0.x; everything is closed in ``finally``. A pressing test whose
served F/T stream itself stalled past the stale limit runs once more (``run_on_a_live_stream``).
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.errors import DeviceError
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.drivers.ur_link import URLink, URLinkConfig
from elastoprobe.sim.cell import SimCell, params_from_cell
from elastoprobe.sim.servers.ur_backend import KinematicBackend
from elastoprobe.sim.servers.ur_emulator import Cmd, UREmulator
from test_loopback_rig import CELL, dashboard, make_rig, run_on_a_live_stream, wait_for, wait_motion

FAST_RECOVERY = URLinkConfig(frequency_hz=125.0, call_timeout_s=3.0, start_timeout_s=30.0, unlock_wait_s=1.0)


def _pressing(rig, force_n: float = 5.0, rate_n_s: float = 10.0, wait_done: bool = True):
    """Above the ball, tared, in contact, regulating ``force_n``; returns (push direction, motion)."""
    arm = rig.hw.arm
    rig.go_above_ball(150.0)
    time.sleep(0.3)
    rig.hw.ft.tare()
    d = arm.status().tcp_pose.rotation[:, 2]
    seek = arm.seek_contact(d, 5.0, 0.4, 40.0)
    assert wait_motion(seek, 15.0) == MotionState.CONTACT, (seek.note, arm.trip(), rig.emulator.events[-6:])
    motion = arm.regulate_force(d, force_n, rate_n_s)
    if wait_done:
        assert wait_motion(motion, 15.0) == MotionState.DONE, (motion.note, arm.trip(), rig.emulator.events[-6:])
    return d, motion


def _still(rig, seconds: float) -> float:
    """The largest distance (mm) the served arm's TCP moves from where it is over ``seconds``."""
    start = np.asarray(rig.emulator.tcp_pose_ur()[:3]) * 1e3
    worst = 0.0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        worst = max(worst, float(np.linalg.norm(np.asarray(rig.emulator.tcp_pose_ur()[:3]) * 1e3 - start)))
        time.sleep(0.02)
    return worst


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_unload_after_regulation_ends_the_speed_command_first() -> None:
    def scenario(rig) -> None:
        arm = rig.hw.arm
        _pressing(rig)
        time.sleep(0.3)
        seen_before = len(rig.emulator.commands_seen)
        here = arm.status().tcp_pose
        away = Pose(here.position_mm + np.array([0.0, 0.0, 20.0]), here.rotation)
        unload = arm.move_linear(away, 10.0, 500.0)
        assert wait_motion(unload, 15.0) == MotionState.DONE, (unload.note, rig.emulator.events[-5:])
        assert rig.emulator.program_running and not rig.emulator.events_of("runtime_error")
        assert rig.emulator.commands_seen[seen_before:][:2] == [Cmd.SPEED_STOP, Cmd.MOVEL]
        assert np.linalg.norm(arm.status().tcp_pose.position_mm - away.position_mm) < 0.5

    run_on_a_live_stream(lambda: make_rig(200), scenario)


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_recovery_from_a_protective_stop_during_regulation_leaves_the_arm_still() -> None:
    """Stopped mid-ramp (the last speedL pushes into the ball at a few mm/s): after the unlock
    and the new script the arm stays put until it is commanded, then it unloads."""
    def scenario(rig) -> None:
        arm = rig.hw.arm
        _, motion = _pressing(rig, force_n=15.0, rate_n_s=10.0, wait_done=False)
        time.sleep(0.5)
        assert motion.state() == MotionState.RUNNING
        assert rig.emulator._inputs.get("input_int_register_0") == Cmd.SPEEDL
        rig.emulator.inject_protective_stop("test: protective stop mid-ramp")
        assert wait_motion(motion, 5.0) == MotionState.FAULT
        assert wait_for(lambda: arm.status().protective_stop, 5.0)
        assert arm.recover_protective_stop()
        assert rig.emulator.program_running
        # The new program found the command register cleared (it held speedL before).
        assert rig.emulator.events_of("program_started")[-1].detail.endswith("command register 0")
        assert _still(rig, 1.0) < 0.01
        here = arm.status().tcp_pose
        away = Pose(here.position_mm + np.array([0.0, 0.0, 20.0]), here.rotation)
        assert wait_motion(arm.move_linear(away, 10.0, 500.0), 15.0) == MotionState.DONE

    run_on_a_live_stream(lambda: make_rig(210, unlock_delay_s=1.0, link=FAST_RECOVERY), scenario)


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_a_force_trip_lets_its_retract_through_and_stops_a_push() -> None:
    def lower_limit(spec):
        return spec.model_copy(update={"limits": spec.limits.model_copy(update={"max_force_n": 10.0})})

    def scenario(rig) -> None:
        arm = rig.hw.arm
        # A fast ramp: the arm comes to rest well above the limit (the stop's overshoot is what
        # the retract must be let through). At 20 N/s it rested 0.05-0.17 N above, less than
        # the ball's relaxation and noise took off on one CI run (9.97 N at a 10 N limit).
        d, motion = _pressing(rig, force_n=15.0, rate_n_s=120.0, wait_done=False)
        assert wait_motion(motion, 10.0) == MotionState.TRIPPED
        trip = arm.trip()
        assert trip is not None and trip.kind == "force"
        time.sleep(0.2)
        block = rig.hw.ft.read_block()
        assert block.force_magnitude_n()[-50:].mean() > 10.0            # held above the limit
        # Pushing further in is stopped again.
        here = arm.status().tcp_pose
        push = Pose(here.position_mm + d * 2.0, here.rotation)
        assert wait_motion(arm.move_linear(push, 2.0, 500.0), 10.0) == MotionState.TRIPPED
        # Once the arm is at rest (as the session retracts after a fault), the retract goes
        # through, above the limit at first, and the guard re-arms after it.
        assert wait_for(lambda: not arm.status().is_moving, 2.0)
        time.sleep(0.1)
        here = arm.status().tcp_pose
        up = Pose(here.position_mm + np.array([0.0, 0.0, 15.0]), here.rotation)
        retract = arm.move_linear(up, 5.0, 500.0)
        assert wait_motion(retract, 15.0) == MotionState.DONE, (retract.note, rig.emulator.events[-6:],
                                                                rig.hw.stats()["link_faults"])
        sup = rig.hw.stats()["supervisor"]
        assert sup["counts"]["let_through"] > 0 and sup["counts"]["trips"] == 1
        assert arm.rearm()
        assert rig.emulator.program_running and not rig.emulator.events_of("runtime_error")

    run_on_a_live_stream(lambda: make_rig(220, spec_update=lower_limit), scenario)


@pytest.mark.loopback
@pytest.mark.timeout(120)
@pytest.mark.parametrize("command, reply, state", [("stop", "Stopped", "STOPPED"),
                                                   ("pause", "Pausing program", "PAUSED")])
def test_a_dashboard_stop_leaves_the_arm_to_the_operator_until_recovery(command: str, reply: str, state: str) -> None:
    def scenario(rig) -> None:
        arm = rig.hw.arm
        _, motion = _pressing(rig)
        programs = len(rig.emulator.programs_received)
        assert dashboard(rig.emulator.host, command) == [reply]
        assert wait_for(lambda: arm.status().operator_stop, 5.0)
        status = arm.status()
        assert not status.program_running and not status.protective_stop and status.connected
        assert "pendant or the dashboard" in status.stop_reason and state in status.stop_reason
        assert wait_motion(motion, 2.0) == MotionState.FAULT
        # Nothing uploaded, nothing restarted, nothing moved: the operator has the arm.
        assert _still(rig, 2.0) < 0.01
        assert len(rig.emulator.programs_received) == programs
        assert not rig.emulator.program_running
        stats = rig.hw.stats()
        assert stats["link_restarts"] == 0
        assert any(f.startswith("operator_stop") for f in stats["link_faults"])
        here = status.tcp_pose
        with pytest.raises(DeviceError):
            arm.move_linear(Pose(here.position_mm + np.array([0.0, 0.0, 10.0]), here.rotation), 10.0, 500.0)
        # An explicit recovery (resume) starts a new script: the arm still does not move by itself.
        assert arm.recover_protective_stop()
        assert len(rig.emulator.programs_received) == programs + 1
        assert not arm.status().operator_stop
        assert _still(rig, 0.5) < 0.01

    run_on_a_live_stream(lambda: make_rig(230, unlock_delay_s=1.0, link=FAST_RECOVERY), scenario)


class _MisreadTcp(UREmulator):
    """A controller whose getTCPOffset reads back 1 mm off what setTcp set."""

    def _execute(self, cmd: int, now: float) -> None:
        super()._execute(cmd, now)
        if cmd == Cmd.GET_TCP_OFFSET:
            self._out_double[self._reg_offset + 2] += 0.001


def _emulator(cls, first_octet: int, **kwargs):
    last: OSError | None = None
    for octet in range(first_octet, first_octet + 8):
        emu = cls(f"127.0.0.{octet}", KinematicBackend((0.4, -0.1, 0.3, 0.0, math.pi, 0.0), t0_s=time.monotonic()),
                  **kwargs)
        try:
            return emu.start()
        except OSError as exc:
            last = exc
    raise RuntimeError(f"no free loopback address from 127.0.0.{first_octet}: {last}")


@pytest.mark.loopback
@pytest.mark.timeout(90)
def test_a_failed_start_leaves_no_control_script_running() -> None:
    emu = _emulator(_MisreadTcp, 240)
    try:
        link = URLink(emu.host, URLinkConfig(frequency_hz=125.0, start_timeout_s=20.0, max_restarts=0,
                                             tcp_offset_ur=(0.0, 0.0, 0.16, 0.0, 0.0, 0.0)))
        with pytest.raises(DeviceError, match="TCP offset"):
            link.start()
        link.close()
        assert emu.programs_received, "the script was uploaded"
        assert wait_for(lambda: not emu.program_running, 2.0)
        assert emu.events_of("program_stopped")[-1].detail == "stop_script"
    finally:
        emu.stop()


@pytest.mark.loopback
@pytest.mark.timeout(90)
@pytest.mark.parametrize("query, reply", [
    ("get robot model", "could not understand: 'get robot model'"),
    ("get robot model", ""),
])
def test_a_dashboard_reply_a_ur_would_not_give_is_a_device_error(query: str, reply: str) -> None:
    emu = _emulator(UREmulator, 250, dashboard_replies={query: reply})
    try:
        link = URLink(emu.host, URLinkConfig(frequency_hz=125.0, start_timeout_s=20.0, max_restarts=0))
        with pytest.raises(DeviceError) as info:
            link.start()
        link.close()
        assert "dashboard" in str(info.value) and repr(reply)[:20] in str(info.value)
        assert wait_for(lambda: not emu.program_running, 2.0)
    finally:
        emu.stop()


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_the_hardware_process_runs_the_in_process_cell_s_supervisor() -> None:
    """One loop: the real cell's hardware process and the simulated cell built from the same
    cell file run the same supervisor code with the same gains, and on both it is the
    supervisor that found the contact and held the force."""
    spec, _ = load_cell(CELL)
    in_process = SimCell(params_from_cell(spec, CELL.parent / spec.object.file, seed=1))

    def scenario(rig) -> None:
        loop = rig.hw.arm.identity().extra["force_loop"]
        assert loop == in_process.arm.identity().extra["force_loop"]
        assert loop["module"] == "elastoprobe.controller.core.forceloop" and loop["class"] == "ForceSupervisor"
        _pressing(rig)
        counts = rig.hw.stats()["supervisor"]["counts"]
        assert counts["contacts"] == 1 and counts["settled"] == 1 and counts["updates"] >= 20

    run_on_a_live_stream(lambda: make_rig(226), scenario)

