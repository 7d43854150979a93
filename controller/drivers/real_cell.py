"""A Cell on the real drivers: the hardware process (arm + F/T + safety path) and the scanner.

``build_real_cell`` is what the cell registry (``controller/cellfactory.py``) calls for cell
kinds ``ur`` and ``loopback``:

- ``ur``: connect to the robot at ``robot.host``, the Net F/T at ``ft.host`` and the
  scanner at ``scanner.url``.
- ``loopback``: the registry first starts the simulated servers for this cell
  (``sim/servers/loopback.py``) and passes their addresses, their ground truth and a handle
  that stops them; the same real drivers then connect to them.

The scanner driver runs in the controller's process: it is not on the safety path.
"""
from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from ..core.clock import RealClock
from ..core.devices import GroundTruth
from ..core.geometry import Pose
from .hardware import HardwareConfig, HardwareProcess
from .line_scanner import SerialLineScanner
from .ur_link import URLinkConfig


class Stoppable(Protocol):
    """What a loopback cell's served world offers its cell: stop it when the cell closes."""

    def stop(self) -> None: ...


class RealCell:
    """Implements ``Cell`` over :class:`HardwareProcess` and a :class:`SerialLineScanner`."""

    is_simulated = False

    def __init__(self, hardware: HardwareProcess, scanner: Any, tcp_to_scanner: Pose, tcp_to_sensor: Pose,
                 base_to_object: Pose, ground_truth: GroundTruth | None = None,
                 servers: Stoppable | None = None) -> None:
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


def build_real_cell(cell: Any, limits: Any, *, addresses: dict[str, Any] | None = None,
                    ground_truth: GroundTruth | None = None, servers: Any = None) -> RealCell:
    """A ``RealCell`` for a ``ur`` or ``loopback`` cell (see the module docstring).

    ``cell``: the validated ``CellSpec`` (as the controller believes it); ``limits``: the
    ``SafetyLimits`` the hardware process enforces (a session's are tightened by its plan,
    calibration runs within the cell's own); ``addresses``: a served world's ``robot_host``,
    ``ft_host``, ``rdt_port``, ``calinfo_port`` and ``scanner_url`` in place of the cell
    file's; ``servers``: what to ``stop()`` when the cell closes. On failure nothing started
    here is left running (the caller stops ``servers``)."""
    if cell.kind not in ("ur", "loopback"):
        raise ValueError(f"build_real_cell handles kinds 'ur' and 'loopback', not {cell.kind!r}")
    addresses = dict(addresses or {})
    scanner_url = addresses.pop("scanner_url", cell.scanner.url)
    hardware = None
    try:
        hardware = HardwareProcess(hardware_config(cell, limits, **addresses)).start()
        scanner = SerialLineScanner(scanner_url, RealClock(), timeout_s=2.0)
    except BaseException:
        if hardware is not None:
            hardware.close()
        raise
    return RealCell(hardware, scanner, cell.tool.tcp_to_scanner.pose(), cell.tool.tcp_to_sensor.pose(),
                    cell.object.base_to_object.pose(), ground_truth, servers)
