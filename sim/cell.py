"""The simulated probing cell (implements :class:`~elastoprobe.controller.devices.Cell`).

:class:`SimCellParams` carries what a cell file describes (tool geometry, scanner
mount, payload, limits, the simulation section: noise, miscalibration, faults) as
plain values; :func:`params_from_cell` maps a validated ``CellSpec`` onto it.
:class:`SimCell` builds the virtual clock, the world and its devices:

    cell = SimCell(params_from_cell(cell_spec, object_path, seed=7))
    cell.begin_step((7, step_id, attempt))
    motion = cell.arm.move_linear(pose, 100.0, 500.0)
    cell.clock.sleep_s(0.01)          # the world integrates up to the new time

The nominal ``tcp_to_scanner``/``tcp_to_sensor``/``base_to_object`` are what the
controller believes; the world uses the true ones (different only when the cell
enables miscalibration, or after an "object moved" fault).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from elastoprobe.controller.clock import VirtualClock
from elastoprobe.controller.geometry import Pose, rotvec_to_matrix
from elastoprobe.controller.kinematics import forward, ur5e
from elastoprobe.controller.safety import SafetyLimits

from .arm import ArmSettings, SimArm
from .faults import FaultInjector, FaultPlan
from .ft import FTSettings, SimForceTorque
from .scanner import ProbeGeometry, ScannerSettings, SimLineScanner
from .world import SimWorld


@dataclass(frozen=True)
class Miscalibration:
    """How far the true cell differs from its file (drawn from the seed when enabled).

    Each magnitude is exact, its direction random: the payload mass is off by
    +-``payload_mass_rel``, its centre of mass by ``payload_com_mm``, the tip by
    ``tip_mm``, the scanner mount by ``scanner_mm`` and ``scanner_deg``.
    """

    enabled: bool = False
    payload_mass_rel: float = 0.1
    payload_com_mm: float = 5.0
    tip_mm: float = 2.0
    scanner_deg: float = 2.0
    scanner_mm: float = 3.0


@dataclass
class SimCellParams:
    """Plain parameters of a simulated cell (mm, deg, N, kg, s)."""

    object: object                        # path of an object YAML, or a SimObject
    base_to_object: Pose
    tip_radius_mm: float
    flange_to_tcp: Pose
    tcp_to_scanner: Pose
    tcp_to_sensor: Pose
    payload_mass_kg: float
    payload_com_mm: np.ndarray            # centre of mass in the TCP frame
    limits: SafetyLimits
    seed: int = 0
    home_joints_deg: tuple[float, ...] = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)
    joint_limits_deg: list[tuple[float, float]] | None = None
    probe_radius_mm: float = 4.0          # the probe cylinder (its shadow), TCP frame z from a to b
    probe_z_range_mm: tuple[float, float] = (-148.0, -8.0)
    control_period_ms: float = 2.0
    ft: FTSettings = FTSettings()
    scanner: ScannerSettings = ScannerSettings()
    arm: ArmSettings = ArmSettings()
    miscalibration: Miscalibration = Miscalibration()
    faults: list[FaultPlan] = field(default_factory=list)
    start_time_s: float = 0.0


class SimGroundTruth:
    """Ground truth over the object, in the OBJECT frame (only evaluate uses it)."""

    def __init__(self, obj, tip_radius_mm: float) -> None:
        self._obj = obj
        self._tip_radius_mm = tip_radius_mm

    def region_of(self, points_mm: np.ndarray) -> np.ndarray:
        return self._obj.region_of(np.atleast_2d(points_mm))

    def true_profile_mm(self, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, force_n: float,
                        angle_deg: float, x_mm: np.ndarray) -> np.ndarray:
        return self._obj.true_profile_mm(point_mm, normal, t, force_n, angle_deg, x_mm, self._tip_radius_mm)

    def region_names(self) -> list[str]:
        return list(self._obj.region_names)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


class SimCell:
    """The in-process simulated cell: clock, world, arm, F/T, scanner, faults."""

    is_simulated = True

    def __init__(self, params: SimCellParams, clock: VirtualClock | None = None) -> None:
        from .objects import load_object

        self.params = params
        obj = load_object(params.object) if isinstance(params.object, (str, Path)) else params.object
        self.clock = clock if clock is not None else VirtualClock(params.start_time_s)
        self.tcp_to_scanner = params.tcp_to_scanner
        self.tcp_to_sensor = params.tcp_to_sensor
        self.base_to_object = params.base_to_object
        true = self._true_geometry(params)
        probe_axis_sensor = params.tcp_to_sensor.rotation.T @ np.array([0.0, 0.0, 1.0])
        period_us = int(round(params.control_period_ms * 1000.0))
        self.world = SimWorld(self.clock, obj, params.base_to_object, params.tip_radius_mm, params.seed,
                              params.limits, probe_axis_sensor, control_period_us=period_us,
                              tip_offset_tcp_mm=true["tip_offset"])
        limits_rad = None if params.joint_limits_deg is None else np.radians(np.asarray(params.joint_limits_deg, float))
        self._model = ur5e(params.flange_to_tcp, limits_rad)
        self.arm = SimArm(self.world, self._model, np.radians(params.home_joints_deg), params.arm)
        self.ft = SimForceTorque(self.world, params.tcp_to_sensor, true["mass"], true["com"], params.ft)
        z0, z1 = params.probe_z_range_mm
        probe = ProbeGeometry(np.array([0.0, 0.0, z0]), np.array([0.0, 0.0, z1]), params.probe_radius_mm,
                              true["tip_offset"], params.tip_radius_mm)
        self.scanner = SimLineScanner(self.world, true["tcp_to_scanner"], probe, params.scanner)
        self.faults = FaultInjector(self.world, params.faults)
        self.world.attach(self.arm, self.ft, self.scanner, self.faults)

    def _true_geometry(self, p: SimCellParams) -> dict:
        m = p.miscalibration
        true = {"mass": p.payload_mass_kg, "com": np.asarray(p.payload_com_mm, float), "tip_offset": np.zeros(3),
                "tcp_to_scanner": p.tcp_to_scanner}
        if not m.enabled:
            return true
        # Drawn from the seed alone (not from steps): the cell is what it is for a whole session.
        from .world import PRE_STEP, Stream, keyed_rng
        rng = keyed_rng(p.seed, PRE_STEP, 1, int(Stream.CONSTANTS))
        true["mass"] = p.payload_mass_kg * (1.0 + m.payload_mass_rel * rng.choice([-1.0, 1.0]))
        true["com"] = true["com"] + m.payload_com_mm * _random_unit(rng)
        true["tip_offset"] = m.tip_mm * _random_unit(rng)
        turn = Pose(m.scanner_mm * _random_unit(rng), rotvec_to_matrix(np.radians(m.scanner_deg) * _random_unit(rng)))
        true["tcp_to_scanner"] = p.tcp_to_scanner.compose(turn)
        return true

    # ------------------------------------------------------------------ Cell protocol
    def begin_step(self, step_key: tuple[int, int, int]) -> None:
        self.world.begin_step(step_key)

    def ground_truth(self) -> SimGroundTruth:
        return SimGroundTruth(self.world.obj, self.params.tip_radius_mm)

    def close(self) -> None:
        """Nothing to release (no threads, no sockets)."""

    # ------------------------------------------------------------------ simulator extras
    def home_pose(self) -> Pose:
        """The TCP pose at the home joints (base frame)."""
        return forward(self._model, np.radians(self.params.home_joints_deg))

    def restore_history(self, presses: list[tuple[np.ndarray, np.ndarray, float]]) -> None:
        """Rebuild permanent dents on resume: (point in the object frame, normal, max force N)."""
        self.world.restore_history(presses)

    def press_history(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """What :meth:`restore_history` needs to rebuild the object's state."""
        return [(p.point_obj.copy(), p.normal_obj.copy(), p.max_force_n) for p in self.world.presses]

    def operator_clear_estop(self) -> None:
        """An operator releases the emergency stop (the controller never does this)."""
        self.faults.operator_clear_estop()

    def validity_report(self, max_force_n: float) -> list[str]:
        return self.world.obj.validity_report(max_force_n, self.params.tip_radius_mm)


def params_from_cell(cell, object_path: str | Path | None = None, seed: int = 0) -> SimCellParams:
    """Map a validated ``controller.config.CellSpec`` onto :class:`SimCellParams`.

    ``object_path`` defaults to the cell's object file (relative paths are the caller's
    to resolve). The probe cylinder is the tool shape named "probe" if there is one.
    """
    tool = cell.tool
    sim = cell.simulation
    probe_radius, probe_range = 4.0, (-148.0, -8.0)
    for shape in tool.shapes:
        if shape.name == "probe" and shape.kind == "cylinder":
            centre = shape.pose.pose()
            axis = centre.rotation[:, 2]
            if abs(abs(axis[2]) - 1.0) < 1e-6 and np.allclose(centre.position_mm[:2], 0.0):
                z = centre.position_mm[2]
                probe_radius = shape.radius_mm
                probe_range = (z - shape.length_mm / 2.0, z + shape.length_mm / 2.0)
    mis = sim.miscalibration
    faults = [FaultPlan(kind=f.kind, step=f.step, rate_per_100_steps=f.rate_per_100_steps,
                        clear_after_s=f.clear_after_s) for f in sim.faults]
    return SimCellParams(
        object=object_path if object_path is not None else cell.object.file,
        base_to_object=cell.object.base_to_object.pose(),
        tip_radius_mm=tool.tip_radius_mm,
        flange_to_tcp=tool.flange_to_tcp.pose(),
        tcp_to_scanner=tool.tcp_to_scanner.pose(),
        tcp_to_sensor=tool.tcp_to_sensor.pose(),
        payload_mass_kg=tool.payload_mass_kg,
        payload_com_mm=np.asarray(tool.payload_com_mm, float),
        limits=cell.limits.safety(),
        seed=seed,
        home_joints_deg=tuple(cell.robot.home_joints_deg),
        joint_limits_deg=cell.robot.joint_limits_deg,
        probe_radius_mm=probe_radius,
        probe_z_range_mm=probe_range,
        control_period_ms=sim.control_period_ms,
        ft=FTSettings(noise_n=sim.ft_noise_n, noise_nm=sim.ft_noise_nm, drift_n_per_h=sim.ft_drift_n_per_h,
                      range_n=cell.ft.range_n, range_nm=cell.ft.range_nm, rate_hz=cell.ft.rate_hz),
        scanner=ScannerSettings(samples=cell.scanner.samples_per_profile, rate_hz=cell.scanner.rate_hz,
                                field_of_view_deg=cell.scanner.field_of_view_deg,
                                max_range_mm=cell.scanner.max_range_mm, noise_scale=sim.scanner_noise_scale),
        miscalibration=Miscalibration(enabled=mis.enabled, payload_mass_rel=mis.payload_mass_rel,
                                      payload_com_mm=mis.payload_com_mm, tip_mm=mis.tip_mm,
                                      scanner_deg=mis.scanner_deg, scanner_mm=mis.scanner_mm),
        faults=faults,
    )
