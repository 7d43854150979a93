"""Driving a cell for calibration through the controller's own probe primitives.

:class:`CellDriver` wraps :class:`~elastoprobe.controller.probe.ProbeExecutor`: every
move is validated (IK along the straight path, tool shapes against the obstacle mesh,
keep-outs, workspace) before it is sent, every wait polls trips and status bits, and
F/T samples and poses are logged as the executor logs them. Failures surface as
``ProbeFault`` / ``MotionRefused`` from the controller.
"""
from __future__ import annotations

import numpy as np

from elastoprobe.controller.core.collision import SceneChecker, boxes_from_cell, shapes_from_cell
from elastoprobe.controller.core.devices import Cell, MotionState, Scan, WrenchBlock
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.kinematics import ur5e
from elastoprobe.controller.core.validation import PathValidator
from elastoprobe.controller.machine import SessionMachine
from elastoprobe.controller.probe import ProbeExecutor, ProbeFault, ProbeSettings


def build_validator(cell_spec, cell: Cell, obstacle_mesh_base=None,  # noqa: ANN001 — config.CellSpec, trimesh
                    contact_allowance_mm: float = 40.0) -> PathValidator:
    """A path validator for the cell with ``obstacle_mesh_base`` (base frame) as the object."""
    limits = None
    if cell_spec.robot.joint_limits_deg is not None:
        limits = np.radians(np.array(cell_spec.robot.joint_limits_deg, dtype=float))
    model = ur5e(cell_spec.tool.flange_to_tcp.pose(), limits)
    workspace, keep_out = boxes_from_cell(cell_spec.limits)
    checker = SceneChecker(shapes_from_cell(cell_spec.tool), obstacle_mesh_base, keep_out, workspace)
    return PathValidator(model, checker, cell.arm.status().joints_rad, contact_allowance_mm)


def probe_settings(cell_spec, speed_mm_s: float | None = None) -> ProbeSettings:  # noqa: ANN001
    lim = cell_spec.limits
    return ProbeSettings(scans_per_step=1, settle_s=0.0, standoff_mm=20.0, force_rate_n_s=10.0,
                         force_tolerance_n=0.5, contact_force_n=lim.contact_force_n,
                         contact_speed_mm_s=min(lim.contact_speed_mm_s, 2.0),
                         free_speed_mm_s=speed_mm_s or lim.free_speed_mm_s,
                         free_accel_mm_s2=lim.free_accel_mm_s2, search_distance_mm=lim.search_distance_mm,
                         tip_radius_mm=cell_spec.tool.tip_radius_mm)


class CellDriver:
    """Validated moves, still F/T averages, touch-offs and scan bursts on a cell."""

    def __init__(self, cell: Cell, validator: PathValidator, settings: ProbeSettings, travel_z_mm: float) -> None:
        self.cell = cell
        self.validator = validator
        self.settings = settings
        # The executor's travel height is object_top + clearance: pass it so that travel_to
        # lifts to ``travel_z_mm``.
        self.ex = ProbeExecutor(cell, SessionMachine(), settings, validator,
                                object_top_z_mm=travel_z_mm - settings.clearance_mm)
        self.step = 0
        self.seed = 0

    def begin_step(self) -> None:
        """A new step key for the simulator's noise streams (real cells ignore it)."""
        self.step += 1
        self.cell.begin_step((self.seed, self.step, 0))

    def pose(self) -> Pose:
        return self.cell.arm.status().tcp_pose

    def move_to(self, target: Pose, speed_mm_s: float | None = None) -> None:
        """A validated straight move (MotionRefused if the path is not clear)."""
        here = self.pose()
        d_mm, d_deg = here.distance_to(target)
        if d_mm < 0.01 and d_deg < 0.01:
            return
        self.validator.validate_path(here, target)
        self.ex._move(target, speed_mm_s or self.settings.free_speed_mm_s)

    def travel_to(self, target: Pose) -> None:
        """Up to travel height, across, down (each leg validated), as the controller travels."""
        self.ex._travel_to(target)

    def hold(self, duration_s: float) -> None:
        self.ex._hold(duration_s)

    def tare(self) -> None:
        self.ex._tare()

    def still_wrench(self, settle_s: float, average_s: float) -> tuple[np.ndarray, np.ndarray, int]:
        """Mean force (N) and torque (N m), sensor frame, over ``average_s`` after ``settle_s`` at rest."""
        self.hold(settle_s)
        self.ex._rec.clear()
        self.hold(average_s)
        block = WrenchBlock.concat(self.ex._rec.blocks)
        ok = block.status == 0
        if ok.sum() < 10:
            raise ProbeFault("device", f"only {int(ok.sum())} healthy F/T samples while averaging")
        return block.force_n[ok].mean(axis=0), block.torque_nm[ok].mean(axis=0), int(ok.sum())

    def touch(self, direction: np.ndarray, max_distance_mm: float) -> Pose | None:
        """Tare, then move along ``direction`` (base, unit) until contact; the TCP pose at rest
        after the stop, or None when nothing was touched. The path is validated with the tip
        allowed to touch."""
        s = self.settings
        e = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
        here = self.pose()
        self.validator.validate_path(here, Pose(here.position_mm + e * max_distance_mm, here.rotation),
                                     contact_allowed=True)
        self.tare()
        motion = self.cell.arm.seek_contact(e, s.contact_speed_mm_s, s.contact_force_n, max_distance_mm)
        state = self.ex._wait(motion, timeout_s=max_distance_mm / s.contact_speed_mm_s * 2.0 + 5.0)
        if state == MotionState.NO_CONTACT:
            return None
        self.ex._expect(state, MotionState.CONTACT, "seek_contact")
        self.hold(0.05)
        return self.pose()

    def back_off(self, direction: np.ndarray, distance_mm: float) -> None:
        """Slowly back out of a contact along ``-direction`` (contact allowed along the way)."""
        here = self.pose()
        e = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
        away = Pose(here.position_mm - e * distance_mm, here.rotation)
        self.validator.validate_path(here, away, contact_allowed=True)
        self.ex._move(away, self.settings.contact_speed_mm_s * 5.0)

    def scan_burst(self, count: int) -> tuple[list[Scan], np.ndarray]:
        """``count`` profiles at rest and the TCP pose (mm + rotation vector) of each."""
        return self.ex._scan_burst(count)


def try_reach(driver: CellDriver, target: Pose, via: Pose | None = None) -> bool:
    """Move to ``target`` directly, else via ``via``; False (nothing moved past a refusal) if refused."""
    try:
        driver.move_to(target)
        return True
    except MotionRefused:
        pass
    if via is None:
        return False
    try:
        driver.move_to(via)
        driver.move_to(target)
        return True
    except MotionRefused:
        return False
