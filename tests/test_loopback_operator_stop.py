"""The operator's authority over the arm, end to end: `elastoprobe run` of the loopback plan on
the loopback cell (the real drivers against the served world, each in its own process), and
mid-probe someone stops the robot's program from the dashboard.

The session pauses (exit 3) with the robot's reason, the link never uploads its script again
by itself, and the arm is not moved again until `elastoprobe resume`, which finishes the
session. The arm is watched the way any RTDE client watches a UR: its pose and force streamed
from port 30004. Real time (a few minutes), so slow; fixed ports, so loopback.
"""
from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.journal import Journal
from elastoprobe.sim.servers.ur_rtde_protocol import (CMD_DATA_PACKAGE, CMD_REQUEST_PROTOCOL_VERSION,
                                                      CMD_SETUP_OUTPUTS, CMD_START, HEADER, frame)
from test_loopback_rig import copy_loopback_configs, dashboard, read_exact

HOST = "127.0.0.197"
CLI = "import sys; from elastoprobe.controller.cli import main; sys.exit(main(sys.argv[1:]))"
_STREAM = struct.Struct(">Bd6d6dI")       # recipe id, timestamp, actual_TCP_pose, actual_TCP_force, robot_status_bits


class ArmWatch:
    """An RTDE output subscriber: (wall-clock time s, TCP position mm, |force| N, program running)."""

    def __init__(self, host: str) -> None:
        self.samples: list[tuple[float, np.ndarray, float, bool]] = []
        self.sock: socket.socket | None = None
        self._thread = threading.Thread(target=self._run, args=(host,), daemon=True)
        self._stop = threading.Event()
        self._thread.start()

    def _connect(self, host: str) -> socket.socket | None:
        while not self._stop.is_set():
            try:
                return socket.create_connection((host, 30004), timeout=1.0)
            except OSError:
                time.sleep(0.2)
        return None

    def _request(self, sock: socket.socket, command: int, payload: bytes) -> None:
        sock.sendall(frame(command, payload))
        while True:
            size, cmd = HEADER.unpack(read_exact(sock, HEADER.size))
            read_exact(sock, size - HEADER.size)
            if cmd == command:
                return

    def _run(self, host: str) -> None:
        sock = self._connect(host)
        if sock is None:
            return
        self.sock = sock
        try:
            self._request(sock, CMD_REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
            self._request(sock, CMD_SETUP_OUTPUTS, struct.pack(">d", 125.0)
                          + b"timestamp,actual_TCP_pose,actual_TCP_force,robot_status_bits")
            self._request(sock, CMD_START, b"")
            while not self._stop.is_set():
                size, cmd = HEADER.unpack(read_exact(sock, HEADER.size))
                body = read_exact(sock, size - HEADER.size)
                if cmd != CMD_DATA_PACKAGE or len(body) != _STREAM.size:
                    continue
                values = _STREAM.unpack(body)
                pose, force, bits = np.array(values[2:5]) * 1e3, np.array(values[8:11]), values[14]
                self.samples.append((time.time(), pose, float(np.linalg.norm(force)), bool(bits & 2)))
        except (OSError, ConnectionError):
            return                            # the served world ended with the session

    def close(self) -> None:
        self._stop.set()
        if self.sock is not None:
            self.sock.close()
        self._thread.join(3.0)


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(900)
def test_a_dashboard_stop_mid_probe_pauses_the_session_and_the_arm_waits_for_resume(tmp_path: Path) -> None:
    plan, cell = copy_loopback_configs(tmp_path, HOST)
    out = tmp_path / "session"
    run = subprocess.Popen([sys.executable, "-c", CLI, "run", str(plan), "--cell", str(cell), "--seed", "1",
                            "--out", str(out), "--quiet", "--allow-stale-calibration"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watch = ArmWatch(HOST)
    try:
        # Mid-probe: the probe presses the ball (the first contact comes after the sweep).
        deadline = time.monotonic() + 300.0
        while time.monotonic() < deadline and run.poll() is None:
            if watch.samples and watch.samples[-1][2] > 2.0:
                break
            time.sleep(0.01)
        assert run.poll() is None and watch.samples[-1][2] > 2.0, "the probe never pressed"
        assert dashboard(HOST, "stop") == ["Stopped"]
        t_stop = time.time()
        code = run.wait(240.0)
    finally:
        if run.poll() is None:
            run.kill()
        watch.close()
    assert code == 3, run.stderr.read()
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    paused_at = [datetime.fromisoformat(e["t_wall_utc"]).timestamp() for e in events if e["event"] == "session_paused"]
    assert paused_at, [e["event"] for e in events][-10:]
    # Stopped where it pressed: after the program's stop ramp (10 m/s^2) nothing moved the arm
    # until the session had paused (and closed its cell, taking the served world with it).
    after = [(t, p, running) for t, p, _, running in watch.samples if t >= t_stop + 0.2]
    assert after and after[-1][0] >= paused_at[-1], "the stream ended before the session paused"
    positions = np.array([p for _, p, _ in after])
    assert np.linalg.norm(positions - positions[0], axis=1).max() < 0.01
    assert not any(running for _, _, running in after)            # no program uploaded again
    with Journal.open_readonly(out) as j:
        session = j.session()
    assert session["status"] == "paused"
    assert "stopped by the operator" in session["status_reason"]
    assert "pendant or the dashboard" in session["status_reason"]
    assert "operator_stop" in [e["event"] for e in events]
    # A real cell resumes behind the same calibration guard it ran behind: refused, untouched.
    refused = subprocess.run([sys.executable, "-c", CLI, "resume", str(out), "--quiet"], capture_output=True,
                             text=True, timeout=120)
    assert refused.returncode == 2 and "calibration is not current" in refused.stderr, refused.stderr
    assert "Traceback" not in refused.stderr
    with Journal.open_readonly(out) as j:
        assert j.session()["status"] == "paused"
    # Resume: the session finishes (the arm's program is started by the new link, not before).
    resumed = subprocess.run([sys.executable, "-c", CLI, "resume", str(out), "--quiet", "--allow-stale-calibration"],
                             capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    with Journal.open_readonly(out) as j:
        assert j.session()["status"] == "done"
