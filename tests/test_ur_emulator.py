"""The UR emulator: kinematics of its stand-in arm, its RTDE wire protocol, and the REAL
ur_rtde 1.6.5 driving it on loopback.

ur_rtde's constructors hold the GIL while they wait on the network, so the real library
always runs in a subprocess here (an in-process emulator would starve).
"""
from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

from elastoprobe.controller.core import kinematics as kin
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.sim.servers.ur_backend import KinematicBackend, trapezoid_position
from elastoprobe.sim.servers.ur_emulator import Cmd, UREmulator
from elastoprobe.sim.servers.ur_rtde_protocol import HEADER, frame
from test_loopback_rig import dashboard, read_exact

START_POSE = [0.4, -0.1, 0.3, 0.0, np.pi, 0.0]


# ---------------------------------------------------------------- kinematic backend (no network)
def test_trapezoid_reaches_length_with_analytic_duration() -> None:
    length, v, a = 0.2, 0.25, 1.2
    s, s_dot, total = trapezoid_position(length, v, a, 10.0)
    assert s == pytest.approx(length)
    assert s_dot == pytest.approx(0.0)
    assert total == pytest.approx(length / v + v / a)      # cruise + one accel ramp
    s_half, s_dot_half, _ = trapezoid_position(length, v, a, total / 2)
    assert s_half == pytest.approx(length / 2)
    assert s_dot_half == pytest.approx(v)


def test_trapezoid_triangular_when_too_short_to_cruise() -> None:
    length, v, a = 0.01, 1.0, 1.0
    _, _, total = trapezoid_position(length, v, a, 0.0)
    assert total == pytest.approx(2 * np.sqrt(length / a))


def test_kinematic_backend_straight_line_and_stop() -> None:
    arm = KinematicBackend(START_POSE, t0_s=0.0)
    goal = np.array(START_POSE) + np.array([0.1, 0.05, 0.0, 0, 0, 0])
    arm.move_linear(goal, 0.25, 1.2)
    for k in range(1, 200):
        arm.advance(k * 0.002)
        p = arm.tcp_pose_ur()[:3]
        # Straight line: the offset from the start stays parallel to the goal offset.
        offset = p - np.array(START_POSE[:3])
        assert np.linalg.norm(np.cross(offset, goal[:3] - START_POSE[:3])) < 1e-12
    arm.stop(2.0)
    speed_at_stop = np.linalg.norm(arm.tcp_speed_ur()[:3])
    assert speed_at_stop > 0.1
    t = 0.4
    while arm.is_moving() and t < 2.0:
        t += 0.002
        arm.advance(t)
    assert not arm.is_moving()
    # Braking distance v^2 / (2 a) within a tick's worth.
    travelled = np.linalg.norm(arm.tcp_pose_ur()[:3] - START_POSE[:3])
    s_at_stop, _, _ = trapezoid_position(np.linalg.norm(goal[:3] - START_POSE[:3]), 0.25, 1.2, 0.398)
    assert travelled == pytest.approx(s_at_stop + speed_at_stop ** 2 / 4.0, abs=2e-3)
    assert travelled < np.linalg.norm(goal[:3] - START_POSE[:3])


def test_kinematic_backend_speedl_accelerates_then_cruises() -> None:
    arm = KinematicBackend(START_POSE, t0_s=0.0)
    arm.speed_linear(np.array([0.0, 0.0, -0.05, 0, 0, 0]), 0.5)
    arm.advance(0.05)
    assert np.linalg.norm(arm.tcp_speed_ur()[:3]) == pytest.approx(0.025)
    arm.advance(1.0)
    assert arm.tcp_speed_ur()[2] == pytest.approx(-0.05)
    assert arm.tcp_pose_ur()[2] < START_POSE[2]


# ---------------------------------------------------------------- loopback helpers
def _start_emulator(first_octet: int, **kwargs: object) -> UREmulator:
    """An emulator on the first free 127.0.0.x from ``first_octet`` (fixed UR ports)."""
    last: OSError | None = None
    for octet in range(first_octet, first_octet + 8):
        emu = UREmulator(f"127.0.0.{octet}", KinematicBackend(START_POSE, t0_s=time.monotonic()), **kwargs)
        try:
            return emu.start()
        except OSError as exc:
            last = exc
    raise RuntimeError(f"no free loopback address from 127.0.0.{first_octet}: {last}")


@pytest.fixture
def emulator_at():
    """Factory: an emulator on 127.0.0.n (or the next free one); all stopped at teardown."""
    started: list[UREmulator] = []

    def make(octet: int, **kwargs: object) -> UREmulator:
        emu = _start_emulator(octet, **kwargs)
        started.append(emu)
        return emu

    yield make
    for emu in started:
        emu.stop()
        assert emu.alive_threads == 0


def _rtde_request(sock: socket.socket, command: int, payload: bytes = b"") -> tuple[int, bytes]:
    sock.sendall(frame(command, payload))
    while True:
        size, cmd = HEADER.unpack(read_exact(sock, 3))
        body = read_exact(sock, size - 3)
        if cmd == command:
            return cmd, body


def _run_client(code: str, host: str, *args: str, timeout_s: float = 40.0) -> dict:
    """Run real ur_rtde code in a subprocess (argv: host, then ``args``); it prints one JSON line."""
    done = subprocess.run([sys.executable, "-c", code, host, *args], capture_output=True, text=True,
                          timeout=timeout_s)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert done.returncode == 0 and lines, f"client failed:\n{done.stdout}\n{done.stderr}"
    return json.loads(lines[-1])


# ---------------------------------------------------------------- raw RTDE protocol
@pytest.mark.loopback
@pytest.mark.timeout(30)
def test_rtde_negotiation_recipes_and_input_ownership(emulator_at) -> None:
    emulator = emulator_at(21)
    a = socket.create_connection((emulator.host, 30004), timeout=2.0)
    b = socket.create_connection((emulator.host, 30004), timeout=2.0)
    try:
        _, body = _rtde_request(a, ord("V"), struct.pack(">H", 2))
        assert body == b"\x01"
        _, body = _rtde_request(a, ord("v"))
        assert struct.unpack(">IIII", body)[:2] == (5, 11)
        _, body = _rtde_request(a, ord("O"), struct.pack(">d", 125.0) + b"actual_TCP_pose,no_such_thing")
        assert body[1:].decode() == "VECTOR6D,NOT_FOUND"
        _, body = _rtde_request(a, ord("O"), struct.pack(">d", 125.0) + b"actual_TCP_pose,robot_status_bits")
        assert body[0] == 1 and body[1:].decode() == "VECTOR6D,UINT32"
        _, body = _rtde_request(a, ord("I"), b"input_int_register_5,input_double_register_5")
        assert body[0] == 1 and body[1:].decode() == "INT32,DOUBLE"
        _rtde_request(b, ord("V"), struct.pack(">H", 2))
        _, body = _rtde_request(b, ord("I"), b"input_int_register_5")
        assert body[1:].decode() == "IN_USE"          # another client owns it
        _, body = _rtde_request(a, ord("S"))
        assert body == b"\x01"
        size, cmd = HEADER.unpack(read_exact(a, 3))
        data = read_exact(a, size - 3)
        assert cmd == ord("U") and data[0] == 1
        values = struct.unpack(">6dI", data[1:])
        assert values[:6] == pytest.approx(START_POSE)
        assert values[6] & 1                             # powered on
        a.sendall(frame(ord("U"), bytes([1]) + struct.pack(">id", 7, 1.5)))
        deadline = time.monotonic() + 2.0
        while emulator._inputs.get("input_int_register_5") != 7 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert emulator._inputs["input_int_register_5"] == 7
        assert emulator._inputs["input_double_register_5"] == 1.5
    finally:
        a.close()
        b.close()


@pytest.mark.loopback
@pytest.mark.timeout(30)
def test_dashboard_refuses_unlock_for_the_delay_and_never_clears_an_estop(emulator_at) -> None:
    emu = emulator_at(23, unlock_delay_s=1.0)
    assert dashboard(emu.host, "PolyscopeVersion", "get serial number", "is in remote control") == [
        "URSoftware 5.11.1.108318 (Mar 22 2021)", "20235500042", "true"]
    emu.inject_protective_stop()
    assert dashboard(emu.host, "safetystatus") == ["Safetystatus: PROTECTIVE_STOP"]
    assert dashboard(emu.host, "unlock protective stop")[0].startswith("Cannot unlock protective stop")
    assert emu.protective_stopped
    time.sleep(1.1)
    assert dashboard(emu.host, "unlock protective stop", "close safety popup", "safetystatus") == [
        "Protective stop releasing", "closing safety popup", "Safetystatus: NORMAL"]
    emu.inject_emergency_stop()
    replies = dashboard(emu.host, "unlock protective stop", "close safety popup", "safetystatus")
    assert replies[0] != "Protective stop releasing"
    assert replies[2] == "Safetystatus: ROBOT_EMERGENCY_STOP"
    assert emu.emergency_stopped
    emu.release_emergency_stop()
    assert dashboard(emu.host, "safetystatus") == ["Safetystatus: NORMAL"]


# ---------------------------------------------------------------- the real ur_rtde against it
_MOVE_CLIENT = r"""
import json, sys, time
import rtde_control, rtde_receive
host = sys.argv[1]
r = rtde_receive.RTDEReceiveInterface(host, frequency=125.0)
c = rtde_control.RTDEControlInterface(host, frequency=125.0, flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
import rtde_io
io = rtde_io.RTDEIOInterface(host)       # a third, concurrent session
out = {"running": c.isProgramRunning(), "start": r.getActualTCPPose(), "io": io.setStandardDigitalOut(3, True)}
target = list(out["start"]); target[2] += 0.05
out["sync_ok"] = c.moveL(target, 0.25, 1.2)
time.sleep(0.05)   # the receive stream may lag the control stream by one period (8 ms at 125 Hz)
out["after_sync"] = r.getActualTCPPose()
far = list(target); far[0] += 0.3
out["async_ok"] = c.moveL(far, 0.25, 1.2, True)
progress = []
for _ in range(4):
    progress.append(c.getAsyncOperationProgress()); time.sleep(0.1)
c.stopL(2.0)
time.sleep(0.3)
out["progress_during"] = progress
out["progress_after"] = c.getAsyncOperationProgress()
out["after_stop"] = r.getActualTCPPose()
out["far"] = far
out["speed_after"] = r.getActualTCPSpeed()
out["status_bits"] = r.getRobotStatus()
out["safety_bits"] = r.getSafetyStatusBits()
c.stopScript()
out["running_after_stop_script"] = c.isProgramRunning()
c.disconnect(); r.disconnect(); io.disconnect()
print(json.dumps(out))
"""


@pytest.mark.loopback
@pytest.mark.timeout(60)
def test_real_ur_rtde_moves_the_emulated_arm(emulator_at) -> None:
    emulator = emulator_at(25)
    out = _run_client(_MOVE_CLIENT, emulator.host)
    assert out["running"] is True
    assert out["io"] is True
    assert emulator._inputs["standard_digital_output_mask"] == 1 << 3
    assert emulator._inputs["standard_digital_output"] == 1 << 3
    assert out["start"] == pytest.approx(START_POSE)
    assert out["sync_ok"] is True
    # moveL (synchronous) returned at the goal, read back through rtde_receive.
    assert out["after_sync"][:3] == pytest.approx([0.4, -0.1, 0.35], abs=1e-6)
    # Async moveL: the progress word says "running" (>= 0) until stopL, then "finished" (< 0).
    assert out["async_ok"] is True
    assert all(p >= 0 for p in out["progress_during"])
    assert out["progress_after"] < 0
    # stopL mid-move: the arm stopped short of the far goal, on the line towards it, at rest.
    x_after = out["after_stop"][0]
    assert 0.4 + 0.05 < x_after < out["far"][0] - 0.05
    assert out["after_stop"][1:3] == pytest.approx([-0.1, 0.35], abs=1e-6)
    assert np.linalg.norm(out["speed_after"][:3]) == pytest.approx(0.0, abs=1e-9)
    assert out["status_bits"] & 0b11 == 0b11     # powered on, program running
    assert out["safety_bits"] == 1               # normal mode
    assert out["running_after_stop_script"] is False
    # The emulator's ground truth agrees with what ur_rtde read.
    assert emulator.tcp_pose_ur()[:3] == pytest.approx(out["after_stop"][:3], abs=1e-6)
    # Command ids the real library sent: moveL x2, stopL, stop script.
    assert emulator.commands_seen == [Cmd.MOVEL, Cmd.MOVEL, Cmd.STOPL, Cmd.STOP_SCRIPT]
    # A non-.1 host makes ur_rtde ask the dashboard for more.
    assert {"PolyscopeVersion", "is in remote control"} <= set(emulator.dashboard_log)


_WATCHDOG_CLIENT = r"""
import json, sys, time
import rtde_control, rtde_receive
host = sys.argv[1]
r = rtde_receive.RTDEReceiveInterface(host, frequency=125.0)
c = rtde_control.RTDEControlInterface(host, frequency=125.0, flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
out = {"set": c.setWatchdog(10.0)}
start = r.getActualTCPPose(); far = list(start); far[0] += 0.5
kicks = 0
for _ in range(25):                       # 0.5 s of kicks at 50 Hz keep it alive
    kicks += c.kickWatchdog(); time.sleep(0.02)
out["running_while_kicked"] = c.isProgramRunning()
c.moveL(far, 0.25, 1.2, True)
time.sleep(0.6)                           # no kicks: the watchdog (0.1 s) must stop the program
out["running_after"] = c.isProgramRunning()
out["pose_after"] = r.getActualTCPPose()
out["speed_after"] = r.getActualTCPSpeed()
out["far"] = far
out["kicks"] = kicks
print(json.dumps(out))
"""


@pytest.mark.loopback
@pytest.mark.timeout(60)
def test_watchdog_stops_program_and_arm_without_kicks(emulator_at) -> None:
    emulator = emulator_at(27)
    out = _run_client(_WATCHDOG_CLIENT, emulator.host)
    assert out["set"] is True and out["kicks"] == 25
    assert out["running_while_kicked"] is True
    assert out["running_after"] is False
    expired = emulator.events_of("watchdog_expired")
    assert len(expired) == 1
    stopped = [e for e in emulator.events_of("program_stopped") if e.detail == "watchdog"]
    assert len(stopped) == 1
    # The arm stopped well short of the goal, and is at rest.
    assert out["pose_after"][0] < out["far"][0] - 0.2
    assert np.linalg.norm(out["speed_after"][:3]) == pytest.approx(0.0, abs=1e-9)
    assert not emulator.is_moving()


_TCP_CLIENT = r"""
import json, sys, time
import rtde_control, rtde_receive
host = sys.argv[1]
r = rtde_receive.RTDEReceiveInterface(host, frequency=125.0)
c = rtde_control.RTDEControlInterface(host, frequency=125.0, flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
out = {"offset_at_start": c.getTCPOffset(), "pose_flange": r.getActualTCPPose()}
out["set"] = c.setTcp([0.01, 0.0, 0.16, 0.0, 0.0, 0.0])
out["offset"] = c.getTCPOffset()
time.sleep(0.05)
out["pose_tcp"] = r.getActualTCPPose()
target = [0.45, -0.05, 0.12, 0.0, 3.141592653589793, 0.0]
out["moved"] = c.moveL(target, 0.25, 1.2)
time.sleep(0.05)
out["pose_after_move"] = r.getActualTCPPose()
out["target"] = target
c.stopScript()                           # as after a protective stop: the program has ended
time.sleep(0.1)
c.reuploadScript()
time.sleep(0.3)
out["offset_after_reupload"] = c.getTCPOffset()
out["pose_after_reupload"] = r.getActualTCPPose()
c.stopScript(); c.disconnect(); r.disconnect()
print(json.dumps(out))
"""


@pytest.mark.loopback
@pytest.mark.timeout(60)
def test_poses_are_the_active_tcp_s_and_a_new_script_starts_with_the_installation_tcp(emulator_at) -> None:
    """As on a real UR: actual_TCP_pose = flange pose ∘ TCP offset, a moveL target is where the
    TCP goes, and setTcp lasts until the program ends (a re-uploaded script starts with the
    installation's TCP, here the flange's)."""
    emulator = emulator_at(29)
    out = _run_client(_TCP_CLIENT, emulator.host)
    flange = Pose.from_ur(START_POSE)                      # the kinematic stand-in's poses are the flange's
    offset = Pose.from_ur([0.01, 0.0, 0.16, 0.0, 0.0, 0.0])
    assert out["offset_at_start"] == pytest.approx([0.0] * 6)
    assert out["pose_flange"] == pytest.approx(START_POSE)
    assert out["set"] is True and out["offset"] == pytest.approx([0.01, 0.0, 0.16, 0.0, 0.0, 0.0])
    # The flange points down (rotation pi about y): the TCP is 160 mm below it, 10 mm along -x.
    assert out["pose_tcp"][:3] == pytest.approx(flange.compose(offset).to_ur()[:3], abs=1e-9)
    assert out["pose_tcp"][:3] == pytest.approx([0.39, -0.1, 0.14], abs=1e-9)
    # moveL takes the TCP to the target; the flange (the arm itself) is one offset back.
    assert out["moved"] is True
    assert out["pose_after_move"][:3] == pytest.approx(out["target"][:3], abs=1e-6)
    flange_now = Pose.from_ur(emulator.backend.tcp_pose_ur())
    expected_flange = Pose.from_ur(out["target"]).compose(offset.inverse())
    assert flange_now.distance_to(expected_flange)[0] < 1e-3          # mm
    # A new program starts with the installation's TCP: the same arm reads as its flange again.
    assert out["offset_after_reupload"] == pytest.approx([0.0] * 6)
    assert out["pose_after_reupload"][:3] == pytest.approx(flange_now.to_ur()[:3], abs=1e-6)
    assert [e.kind for e in emulator.events_of("tcp_set")] == ["tcp_set"]


def test_kinematic_backend_joint_move_and_joints_follow_the_pose() -> None:
    model = kin.ur5e()
    arm = KinematicBackend(START_POSE, t0_s=0.0)
    q0 = arm.joints_rad().copy()
    assert Pose.from_ur(START_POSE).distance_to(kin.forward(model, q0))[0] < 1e-6
    q1 = q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.1, 0.0])
    arm.move_joint(q1, 1.0, 2.0)
    t = 0.0
    while arm.is_moving() and t < 5.0:
        t += 0.002
        arm.advance(t)
    assert arm.joints_rad() == pytest.approx(q1)
    assert Pose.from_ur(arm.tcp_pose_ur()).distance_to(kin.forward(model, q1))[0] < 1e-6


# ---------------------------------------------------------------- faithful to a real controller
_THREADS_CLIENT = r"""
import json, sys, time
import rtde_control, rtde_receive
host = sys.argv[1]
r = rtde_receive.RTDEReceiveInterface(host, frequency=125.0)
c = rtde_control.RTDEControlInterface(host, frequency=125.0, flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
start = r.getActualTCPPose(); up = list(start); up[2] += 0.02
out = {}
c.speedL([0.0, 0.0, -0.01, 0.0, 0.0, 0.0], 0.5, 0.0)
time.sleep(0.2)
out["speed_stop"] = c.speedStop(2.0)
out["after_speed_stop"] = c.moveL(up, 0.1, 0.5)
out["running_after_speed_stop"] = c.isProgramRunning()
c.speedL([0.0, 0.0, -0.01, 0.0, 0.0, 0.0], 0.5, 0.0)
time.sleep(0.2)
# No speedStop: the speed thread still runs.
if sys.argv[2] == "moveL":
    c.moveL(start, 0.1, 0.5, True)
elif sys.argv[2] == "stopL":
    c.stopL(2.0, True)
else:
    c.forceModeStop()
time.sleep(0.3)
out["running_after_move_over_speed"] = c.isProgramRunning()
print(json.dumps(out))
"""


@pytest.mark.loopback
@pytest.mark.timeout(60)
@pytest.mark.parametrize("octet, second", [(31, "moveL"), (35, "stopL"), (37, "forceModeStop")])
def test_a_move_while_the_speed_thread_runs_halts_the_program(emulator_at, octet: int, second: str) -> None:
    """ur_rtde 1.6.5's moveL stops only the async move thread, and stopL and forceModeStop
    run stopl in the main thread: after speedL, any of them without speedStop makes two
    threads command the robot, and URScript halts the program."""
    emulator = emulator_at(octet)
    out = _run_client(_THREADS_CLIENT, emulator.host, second)
    assert out["speed_stop"] is True and out["after_speed_stop"] is True
    assert out["running_after_speed_stop"] is True
    assert out["running_after_move_over_speed"] is False
    errors = emulator.events_of("runtime_error")
    assert len(errors) == 1 and "Another thread is already controlling the robot" in errors[0].detail
    assert emulator.events_of("program_stopped")[-1].detail == "runtime_error"
    assert not emulator.is_moving()


_REUPLOAD_CLIENT = r"""
import json, sys, time
import dashboard_client, rtde_control, rtde_receive
host, clear = sys.argv[1], sys.argv[2] == "clear"
db = dashboard_client.DashboardClient(host); db.connect()
r = rtde_receive.RTDEReceiveInterface(host, frequency=125.0)
c = rtde_control.RTDEControlInterface(host, frequency=125.0, flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
c.speedL([0.0, 0.0, -0.02, 0.0, 0.0, 0.0], 0.5, 0.0)
print("speeding", flush=True)
sys.stdin.readline()                     # the test protective-stops the arm, waits out the unlock delay
db.unlockProtectiveStop()
db.closeSafetyPopup()
if clear:
    c.kickWatchdog()                     # NO_CMD into input_int_register_0, with no program running
c.reuploadScript()
deadline = time.monotonic() + 5.0
while not c.isProgramRunning() and time.monotonic() < deadline:
    time.sleep(0.01)
before = r.getActualTCPPose()
time.sleep(0.5)
after = r.getActualTCPPose()
print(json.dumps({"running": c.isProgramRunning(), "before": before, "after": after}), flush=True)
"""


@pytest.mark.loopback
@pytest.mark.timeout(60)
@pytest.mark.parametrize("clear", [False, True])
def test_input_registers_outlive_the_program(emulator_at, clear: bool) -> None:
    """A protective stop during speedL, then the script uploaded again: without clearing the
    command register first, the new program runs the last speedL again and the arm drives
    itself down; cleared, it stays still."""
    emulator = emulator_at(33, unlock_delay_s=0.3)
    proc = subprocess.Popen([sys.executable, "-c", _REUPLOAD_CLIENT, emulator.host, "clear" if clear else "keep"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "speeding"
        time.sleep(0.2)
        emulator.inject_protective_stop("test")
        time.sleep(0.4)
        assert emulator._inputs["input_int_register_0"] == Cmd.SPEEDL
        proc.stdin.write("go\n")
        proc.stdin.flush()
        line = proc.stdout.readline()
        assert line.startswith("{"), proc.stderr.read()
        out = json.loads(line)
    finally:
        proc.kill()
        proc.wait(5.0)
    assert out["running"] is True
    moved_mm = (out["before"][2] - out["after"][2]) * 1e3
    if clear:
        assert abs(moved_mm) < 0.01
    else:
        assert moved_mm > 5.0               # 0.5 s at the replayed 20 mm/s
