"""A Cell on the real drivers: the hardware process (arm + F/T + safety path) and the scanner.

``build_real_cell(inputs, seed)`` is what ``controller.cellfactory.build_cell`` calls for
cell kinds ``ur`` and ``loopback``:

- ``ur``: connect to the robot at ``robot.host``, the Net F/T at ``ft.host`` and the
  scanner at ``scanner.url``.
- ``loopback``: first start ``sim serve`` for this cell in a child process (it dies with
  the controller), wait for its state file, then connect the same real drivers to it. The
  plan's ``simulated_object`` (or the cell's object) is the world served, and the cell
  can report its ground truth (the world is simulated even if the devices speak the
  real protocols).

The scanner driver runs in the controller's process: it is not on the safety path.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..clock import RealClock
from ..devices import GroundTruth
from ..errors import DeviceError
from ..geometry import Pose
from .hardware import HardwareConfig, HardwareProcess
from .ur_link import URLinkConfig


class RealCell:
    """Implements ``Cell`` over :class:`HardwareProcess` and a :class:`SerialLineScanner`."""

    is_simulated = False

    def __init__(self, hardware: HardwareProcess, scanner: Any, tcp_to_scanner: Pose, tcp_to_sensor: Pose,
                 base_to_object: Pose, ground_truth: GroundTruth | None = None,
                 servers: "LoopbackServers | None" = None) -> None:
        self.clock = RealClock()
        self.hardware = hardware
        self.arm = hardware.arm
        self.ft = hardware.ft
        self.scanner = scanner
        self.tcp_to_scanner = tcp_to_scanner
        self.tcp_to_sensor = tcp_to_sensor
        self.base_to_object = base_to_object
        self._ground_truth = ground_truth
        self.servers = servers

    def begin_step(self, step_key: tuple[int, int, int]) -> None:
        """Real devices have no noise keys."""

    def ground_truth(self) -> GroundTruth | None:
        return self._ground_truth

    def close(self) -> None:
        """Stop the arm and the hardware process, close the scanner, stop served worlds."""
        for closer in (self.hardware.close, self.scanner.close):
            try:
                closer()
            except Exception:  # noqa: BLE001 — close everything even if one part fails
                pass
        if self.servers is not None:
            self.servers.stop()


class LoopbackServers:
    """``sim serve`` in a spawned child process that dies with this one (PR_SET_PDEATHSIG)."""

    def __init__(self, cell_path: Path, object_path: Path | None, seed: int, lifetime_s: float = 4 * 3600.0) -> None:
        self.cell_path = Path(cell_path)
        self.object_path = object_path
        self.seed = int(seed)
        self.lifetime_s = lifetime_s
        self.run_dir = Path(tempfile.mkdtemp(prefix="elastoprobe-serve-"))
        self.proc: Any = None
        self.state: dict[str, Any] = {}

    def start(self, timeout_s: float = 60.0) -> "LoopbackServers":
        import multiprocessing as mp

        from elastoprobe.sim.servers.serve import read_state, serve_child_main

        ctx = mp.get_context("spawn")
        self.proc = ctx.Process(target=serve_child_main, name="elastoprobe-sim-serve", daemon=True,
                                args=(str(self.cell_path), None if self.object_path is None else str(self.object_path),
                                      self.seed, str(self.run_dir), self.lifetime_s, os.getpid()))
        self.proc.start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = read_state(self.run_dir)
            if state is not None:
                self.state = state
                return self
            if not self.proc.is_alive():
                break
            time.sleep(0.05)
        why = ""
        err = self.run_dir / "serve.error"
        if err.exists():
            why = ": " + err.read_text()
        self.stop()
        raise DeviceError(f"the loopback servers for {self.cell_path} did not start{why}")

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout_s)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(2.0)
        shutil.rmtree(self.run_dir, ignore_errors=True)


def hardware_config(cell: Any, limits: Any, *, robot_host: str | None = None, ft_host: str | None = None,
                    rdt_port: int | None = None, calinfo_port: int | None = None,
                    link: URLinkConfig | None = None) -> HardwareConfig:
    """The hardware process's configuration from a validated ``CellSpec`` (and the session's
    plan-tightened ``SafetyLimits``); addresses may be overridden (a served world's)."""
    tcp_to_sensor = cell.tool.tcp_to_sensor.pose()
    axis = tcp_to_sensor.rotation.T @ np.array([0.0, 0.0, 1.0])
    joint_limits = None if cell.robot.joint_limits_deg is None else np.radians(np.asarray(cell.robot.joint_limits_deg, float))
    if link is None:
        # On loopback the emulator streams RTDE in Python: 125 Hz spares the shared CPU, but
        # the control stream stays at 500 Hz: ur_rtde 1.6.5 sends a command (a stop) only
        # between two of its packages, so its period is in every stop's latency.
        link = URLinkConfig(frequency_hz=125.0, control_frequency_hz=500.0) if cell.kind == "loopback" \
            else URLinkConfig()
    return HardwareConfig(robot_host=robot_host or cell.robot.host, ft_host=ft_host or cell.ft.host, limits=limits,
                          rdt_port=rdt_port or cell.ft.rdt_port, calinfo_port=calinfo_port or cell.ft.calinfo_port,
                          ft_rate_hz=cell.ft.rate_hz, probe_axis_sensor=tuple(float(v) for v in axis),
                          tcp_to_sensor=tcp_to_sensor, flange_to_tcp=cell.tool.flange_to_tcp.pose(),
                          joint_limits_rad=joint_limits, link=link, force_loop=cell.force_loop.gains())


def _object_mesh(path: Path) -> Any:
    if path.suffix.lower() in (".yaml", ".yml"):
        from elastoprobe.sim.objects import load_object   # a described object: its mesh

        return load_object(path).mesh
    import trimesh

    return trimesh.load(str(path), force="mesh")


def build_real_cell(inputs: Any, seed: int) -> Any:
    """A ``BuiltCell`` for a ``ur`` or ``loopback`` cell (see the module docstring)."""
    from ..cellfactory import BuiltCell
    from .line_scanner import SerialLineScanner

    cell = inputs.cell
    obj_path = inputs.object_file()
    servers: LoopbackServers | None = None
    overrides: dict[str, Any] = {}
    scanner_url = cell.scanner.url
    ground_truth = None
    if cell.kind == "loopback":
        servers = LoopbackServers(inputs.cell_path, obj_path, seed).start()
        st = servers.state
        overrides = {"robot_host": st["robot_host"], "ft_host": st["ft_host"], "rdt_port": st["rdt_port"],
                     "calinfo_port": st["calinfo_port"]}
        scanner_url = st["scanner_url"]
        from elastoprobe.sim.cell import SimGroundTruth
        from elastoprobe.sim.objects import load_object

        ground_truth = SimGroundTruth(load_object(obj_path), cell.tool.tip_radius_mm)
    elif cell.kind != "ur":
        raise ValueError(f"build_real_cell handles kinds 'ur' and 'loopback', not {cell.kind!r}")
    hardware = None
    try:
        hardware = HardwareProcess(hardware_config(cell, inputs.limits, **overrides)).start()
        scanner = SerialLineScanner(scanner_url, RealClock(), timeout_s=2.0)
        mesh = _object_mesh(obj_path)
    except BaseException:
        if hardware is not None:
            hardware.close()
        if servers is not None:
            servers.stop()
        raise
    real = RealCell(hardware, scanner, cell.tool.tcp_to_scanner.pose(), cell.tool.tcp_to_sensor.pose(),
                    cell.object.base_to_object.pose(), ground_truth, servers)
    return BuiltCell(cell=real, object_mesh=mesh)
