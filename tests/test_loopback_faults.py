"""Faults on loopback, with the real drivers against the served simulated world: the
controller killed mid-press, an RTDE connection dropped mid-move, a hung ur_rtde call, and a
scanner sending a corrupted or truncated frame or going silent. Each test runs on its own
127.0.0.x; every server, process and port is closed in ``finally``."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.errors import DeviceError, DeviceTimeout
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.drivers.line_scanner import SerialLineScanner
from test_loopback_rig import make_rig, run_on_a_live_stream, wait_for, wait_motion

TESTS = Path(__file__).resolve().parent

CONTROLLER = textwrap.dedent("""
    import sys, time, json
    sys.path.insert(0, {tests!r})
    import numpy as np
    from dataclasses import replace
    from elastoprobe.controller.core.devices import MotionState
    from elastoprobe.controller.core.geometry import Pose
    from elastoprobe.controller.drivers.hardware import HardwareProcess
    from elastoprobe.controller.drivers.real_cell import hardware_config
    from elastoprobe.controller.drivers.ur_link import URLinkConfig
    from test_loopback_rig import cell_on, wait_motion

    if __name__ == "__main__":
        spec = cell_on({host!r})
        cfg = hardware_config(spec, spec.limits.safety(), rdt_port={rdt}, calinfo_port={cal},
                              link=URLinkConfig(frequency_hz=125.0))
        hw = HardwareProcess(cfg).start()
        arm = hw.arm
        rot = arm.status().tcp_pose.rotation
        assert wait_motion(arm.move_linear(Pose(np.array([400.0, 0.0, 150.0]), rot), 150.0, 600.0), 15) == MotionState.DONE
        time.sleep(0.3)
        hw.ft.tare()
        d = rot[:, 2]
        assert wait_motion(arm.seek_contact(d, 5.0, 0.4, 40.0), 15) == MotionState.CONTACT
        assert wait_motion(arm.regulate_force(d, 5.0, 10.0), 15) == MotionState.DONE
        print(json.dumps({{"hw_pid": hw.pid, "link_pid": hw.stats()["link_child_pid"]}}), flush=True)
        time.sleep(60)
""")


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as f:
            return any(line.startswith("State:") and "Z" in line for line in f)
    except FileNotFoundError:
        return True


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_controller_sigkilled_mid_press_the_arm_stops_within_the_watchdog_period() -> None:
    rig = make_rig(150, start_hardware=False)
    proc = None
    try:
        st = rig.served.state
        code = CONTROLLER.format(tests=str(TESTS), host=st["robot_host"], rdt=st["rdt_port"], cal=st["calinfo_port"])
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        line = proc.stdout.readline()
        assert line.startswith("{"), proc.stderr.read()[-2000:] if proc.poll() is not None else line
        import json
        pids = json.loads(line)
        emu = rig.emulator
        assert emu.program_running
        force_before = rig.backend.world.contact.force_n
        assert 4.0 < force_before < 6.5
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        assert wait_for(lambda: not emu.program_running, 2.0)
        stopped = emu.events_of("program_stopped")
        assert stopped and stopped[-1].detail == "watchdog"
        # Kicks stop when the hardware process and its link child die with the controller;
        # the emulator's watchdog (10 Hz minimum: 0.1 s) then stops the program.
        assert stopped[-1].t_s - t_kill < 0.1 + 0.4
        assert wait_for(lambda: not emu.is_moving(), 1.0)
        assert wait_for(lambda: _gone(pids["hw_pid"]) and _gone(pids["link_pid"]), 5.0)
        time.sleep(0.5)
        assert rig.backend.world.contact is None or rig.backend.world.contact.force_n < force_before + 1.0
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait(5)
            proc.stdout.close()
            proc.stderr.close()
        rig.close()


def _start_slow_move(rig, dy_mm: float = 80.0) -> tuple[object, Pose]:
    above = rig.go_above_ball(170.0)
    far = Pose(above.position_mm + np.array([0.0, dy_mm, 0.0]), above.rotation)
    move = rig.hw.arm.move_linear(far, 20.0, 500.0)
    time.sleep(0.8)
    assert move.state() == MotionState.RUNNING
    return move, far


def _device_error_seen(arm, timeout_s: float) -> str | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            arm.status()
        except DeviceError as exc:
            return str(exc)
        time.sleep(0.02)
    return None


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_rtde_connection_dropped_mid_move_stops_the_arm_and_the_link_comes_back() -> None:
    def scenario(rig) -> None:  # noqa: ANN001 — test_loopback_rig.Rig
        arm = rig.hw.arm
        move, far = _start_slow_move(rig)
        rig.emulator.drop_connections()
        assert wait_motion(move, 10.0) == MotionState.FAULT
        message = _device_error_seen(arm, 10.0) or move.note
        assert "connection" in message.lower() or "link" in message.lower()
        assert wait_for(lambda: not rig.emulator.is_moving(), 2.0)
        assert rig.emulator.tcp_pose_ur()[1] * 1e3 < far.position_mm[1] - 20.0
        # The link restarted its ur_rtde child: the arm answers and moves again.
        assert wait_for(lambda: _status_ok(arm), 20.0)
        # The watchdog and the new child's upload only stop and replace the program: the
        # link's restart makes no protective stop of its own (the session journals one found
        # while recovering from a lost connection as a fault of its own, docs/design.md "Faults").
        assert not arm.status().protective_stop
        assert wait_motion(arm.move_linear(far, 100.0, 500.0), 10.0) == MotionState.DONE
        assert rig.hw.stats()["link_restarts"] >= 1

    run_on_a_live_stream(lambda: make_rig(160), scenario)


def _status_ok(arm) -> bool:
    try:
        st = arm.status()
    except DeviceError:
        return False
    return st.connected and st.program_running


@pytest.mark.loopback
@pytest.mark.timeout(120)
def test_hung_driver_call_the_arm_stops_the_controller_sees_a_device_error() -> None:
    def scenario(rig) -> None:  # noqa: ANN001 — test_loopback_rig.Rig
        arm = rig.hw.arm
        link_pid = rig.hw.stats()["link_child_pid"]
        move, far = _start_slow_move(rig)
        os.kill(link_pid, signal.SIGSTOP)                  # ur_rtde hangs: no answers, no kicks
        try:
            t_hang = time.monotonic()
            assert wait_for(lambda: not rig.emulator.program_running, 2.0)
            assert rig.emulator.events_of("program_stopped")[-1].detail == "watchdog"
            assert rig.emulator.events_of("program_stopped")[-1].t_s - t_hang < 1.0
            assert wait_for(lambda: not rig.emulator.is_moving(), 1.0)
            message = _device_error_seen(arm, 15.0)
            assert message is not None and ("hung" in message or "answer" in message or "time" in message), message
            assert wait_motion(move, 5.0) == MotionState.FAULT
            assert _gone(link_pid) or wait_for(lambda: _gone(link_pid), 3.0)   # killed by the link's supervisor
            assert wait_for(lambda: _status_ok(arm), 20.0)
            assert wait_motion(arm.move_linear(far, 100.0, 500.0), 10.0) == MotionState.DONE
        finally:
            try:
                os.kill(link_pid, signal.SIGCONT)
            except ProcessLookupError:
                pass

    run_on_a_live_stream(lambda: make_rig(170), scenario)


@pytest.mark.loopback
@pytest.mark.timeout(90)
def test_scanner_bad_frames_and_silence_end_in_clear_device_errors() -> None:
    rig = make_rig(180, start_hardware=False)
    scanner = None
    try:
        server = rig.served.scanner
        scanner = SerialLineScanner(rig.served.state["scanner_url"], timeout_s=0.5)
        rig.extra.append(scanner)
        assert scanner.samples_per_profile == rig.spec.scanner.samples_per_profile

        def burst(count: int, timeout_s: float = 5.0) -> list:
            scanner.start_burst(count)
            got: list = []
            deadline = time.monotonic() + timeout_s
            while len(got) < count and time.monotonic() < deadline:
                got.extend(scanner.read_scans())
                time.sleep(0.01)
            return got

        # Put the simulated arm above the ball (straight through the backend: no arm driver here).
        # The backend's poses are its tool point's (the cell's TCP); the emulator would report
        # the flange, since no program here set a TCP (setTcp).
        rot = Pose.from_ur(rig.backend.tcp_pose_ur()).rotation
        rig.backend.move_linear(np.array(Pose(np.array([400.0, 0.0, 180.0]), rot).to_ur()), 0.3, 1.0)
        assert wait_for(lambda: not rig.backend.is_moving(), 10.0)
        good = burst(4)
        assert len(good) == 4
        # Judged against the truth: every served point lies on the ball (radius 65 mm, centre
        # (400, 0, 65) mm in the base frame) or on the table, through the pose and the mount.
        base_scanner = Pose.from_ur(rig.backend.tcp_pose_ur()).compose(rig.spec.tool.tcp_to_scanner.pose())
        for scan in good:
            ok = np.isfinite(scan.z_mm)
            assert ok.sum() > 100
            pts = base_scanner.apply(np.column_stack([scan.x_mm[ok], np.zeros(ok.sum()), scan.z_mm[ok]]))
            on_ball = np.abs(np.linalg.norm(pts - np.array([400.0, 0.0, 65.0]), axis=1) - 65.0)
            residual = np.minimum(on_ball, np.abs(pts[:, 2]))
            assert np.mean(residual < 0.3) > 0.97 and (on_ball < 0.3).sum() > 50
        for fault in ("truncate", "corrupt_crc"):
            setattr(server.faults, fault, {1})
            with pytest.raises(DeviceError) as info:
                burst(4)
            assert "short" in str(info.value) and "3 of 4" in str(info.value)
            setattr(server.faults, fault, set())
        assert len(burst(3)) == 3                                    # recovered at the next burst
        server.faults.silent_after_frames = 2
        with pytest.raises(DeviceTimeout) as info:
            burst(5, timeout_s=10.0)
        assert "2 of 5" in str(info.value)
        with pytest.raises(DeviceTimeout) as info:
            scanner.start_burst(3)                                   # silent: no OK to the command
        assert "no reply" in str(info.value)
    finally:
        rig.close()
