"""Shared rig of the loopback tests (no tests here): the served world + the hardware process.

``make_rig(octet)`` serves config/cells/loopback.yaml's simulated world on a free 127.0.0.x
(from ``octet`` on; ephemeral F/T and scanner ports) inside the test process, and starts
the real drivers' hardware process against it. ``Rig.close()`` stops everything.
"""
from __future__ import annotations

import socket
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from elastoprobe.controller.core.config import CellSpec, load_cell
from elastoprobe.controller.core.devices import Motion, MotionState
from elastoprobe.controller.core.errors import DeviceError
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.drivers.hardware import HardwareConfig, HardwareProcess
from elastoprobe.controller.drivers.real_cell import hardware_config
from elastoprobe.controller.drivers.ur_link import URLinkConfig
from elastoprobe.sim.servers.serve import ServedCell, start_servers

ROOT = Path(__file__).resolve().parent.parent
CELL = ROOT / "config" / "cells" / "loopback.yaml"
ABOVE_BALL_MM = np.array([400.0, 0.0, 150.0])     # the ball's top is at z = 130 mm


def wait_for(predicate: Callable[[], bool], timeout_s: float, period_s: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return bool(predicate())


def wait_motion(motion: Motion, timeout_s: float) -> MotionState:
    wait_for(lambda: motion.state() != MotionState.RUNNING, timeout_s)
    return motion.state()


def dashboard(host: str, *lines: str) -> list[str]:
    """Send text commands to the UR dashboard (port 29999) at ``host``; their replies."""
    with socket.create_connection((host, 29999), timeout=2.0) as s:
        f = s.makefile("rwb")
        assert f.readline().startswith(b"Connected: Universal Robots Dashboard Server")
        out = []
        for line in lines:
            f.write(line.encode() + b"\n")
            f.flush()
            out.append(f.readline().decode().strip())
        return out


def read_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``sock`` (ConnectionError if it closes first)."""
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed")
        buf += chunk
    return buf


def copy_loopback_configs(tmp_path: Path, host: str) -> tuple[Path, Path]:
    """The shipped loopback plan and cell in ``tmp_path``, the cell served on ``host`` and
    object paths absolute."""
    objects = ROOT / "config" / "objects"
    cell = (ROOT / "config" / "cells" / "loopback.yaml").read_text()
    cell = cell.replace("127.0.0.2", host).replace("file: ../objects/", f"file: {objects}/")
    plan = (ROOT / "config" / "plans" / "loopback.yaml").read_text()
    plan = plan.replace("simulated_object: ../objects/", f"simulated_object: {objects}/")
    (tmp_path / "cell.yaml").write_text(cell)
    (tmp_path / "plan.yaml").write_text(plan)
    return tmp_path / "plan.yaml", tmp_path / "cell.yaml"


def cell_on(host: str) -> CellSpec:
    spec, _ = load_cell(CELL)
    return spec.model_copy(update={
        "robot": spec.robot.model_copy(update={"host": host}),
        "ft": spec.ft.model_copy(update={"host": host, "rdt_port": 0, "calinfo_port": 0}),
        "scanner": spec.scanner.model_copy(update={"url": f"socket://{host}:0"})})


@dataclass
class Rig:
    spec: CellSpec
    served: ServedCell
    cfg: HardwareConfig
    hw: HardwareProcess | None = None
    extra: list[Any] = field(default_factory=list)

    @property
    def emulator(self) -> Any:
        return self.served.emulator

    @property
    def backend(self) -> Any:
        return self.served.backend

    def start_hardware(self) -> HardwareProcess:
        self.hw = HardwareProcess(self.cfg).start()
        return self.hw

    def go_above_ball(self, z_mm: float = 150.0) -> Pose:
        arm = self.hw.arm
        rot = arm.status().tcp_pose.rotation
        target = Pose(np.array([400.0, 0.0, z_mm]), rot)
        move = arm.move_linear(target, 150.0, 600.0)
        assert wait_motion(move, 15.0) == MotionState.DONE, (move.note, arm.trip())
        return target

    def close(self) -> None:
        for thing in self.extra:
            try:
                thing.close()
            except Exception:  # noqa: BLE001 — teardown is best effort
                pass
        if self.hw is not None:
            self.hw.close()
        self.served.stop()


def make_rig(octet: int, *, unlock_delay_s: float = 5.0, link: URLinkConfig | None = None,
             start_hardware: bool = True, spec_update: Callable[[CellSpec], CellSpec] | None = None,
             **cfg_overrides: Any) -> Rig:
    """Serve the world on the first free 127.0.0.x from ``octet`` and start the hardware process.

    ``spec_update`` changes the cell served (and driven), e.g. its simulated miscalibration."""
    last: Exception | None = None
    for o in range(octet, octet + 8):
        spec = cell_on(f"127.0.0.{o}")
        if spec_update is not None:
            spec = spec_update(spec)
        try:
            served = start_servers(spec, CELL, seed=3, lifetime_s=600.0, unlock_delay_s=unlock_delay_s)
            break
        except OSError as exc:
            last = exc
    else:
        raise RuntimeError(f"no free loopback address from 127.0.0.{octet}: {last}")
    cfg = hardware_config(spec, spec.limits.safety(), rdt_port=served.state["rdt_port"],
                          calinfo_port=served.state["calinfo_port"],
                          link=link or URLinkConfig(frequency_hz=125.0, call_timeout_s=3.0, start_timeout_s=30.0))
    cfg = replace(cfg, call_timeout_s=20.0, **cfg_overrides)
    rig = Rig(spec, served, cfg)
    if start_hardware:
        try:
            rig.start_hardware()
        except BaseException:
            rig.close()
            raise
    return rig


def served_stream_starved(rig: Rig) -> float | None:
    """How late (ms) the served Net F/T sent a record behind its sampling instant at worst, if
    that reaches the cell's stale limit (the server's thread starved of CPU on a busy host),
    else None. A stale trip is then the drivers' right answer, not a fault of theirs."""
    late_ms = rig.served.netft.log.longest_late_s * 1e3
    return late_ms if late_ms >= 0.9 * rig.spec.limits.ft_stale_ms else None


def run_on_a_live_stream(make: Callable[[], Rig], scenario: Callable[[Rig], None]) -> None:
    """``scenario(rig)`` on a fresh rig from ``make()``; closes it. When the scenario fails
    while the served F/T stream itself stalled past the stale limit (the served world's
    precondition, a live sensor, did not hold), it runs once more on a fresh rig, with a
    warning; a failure without such a stall, or a second failure, is the test's failure."""
    for attempt in (1, 2):
        rig = make()
        try:
            scenario(rig)
            return
        except (AssertionError, DeviceError) as exc:
            late_ms = served_stream_starved(rig)
            if attempt == 2 or late_ms is None:
                raise
            warnings.warn(f"the served F/T stream fell {late_ms:.0f} ms behind (stale limit "
                          f"{rig.spec.limits.ft_stale_ms:.0f} ms); running again on a fresh rig after: {exc}")
        finally:
            rig.close()
