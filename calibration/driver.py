"""A cell's toolhead set up for calibration, and the few moves the routines compose from it.

The routines drive the arm through :class:`~elastoprobe.controller.toolhead.Toolhead`, the
public motion primitives the probe executor uses too: every move is validated (IK along
the straight path, tool shapes against the obstacle mesh, keep-outs, workspace) before it
is sent, every wait polls trips and status bits. Failures surface as ``ProbeFault`` /
``MotionRefused`` from the controller. :class:`Rig` adds the simulator's noise keys of
each measurement (real cells ignore them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastoprobe.controller.core.collision import SceneChecker, boxes_from_cell, shapes_from_cell
from elastoprobe.controller.core.devices import Cell
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.kinematics import ur5e
from elastoprobe.controller.core.validation import PathValidator
from elastoprobe.controller.toolhead import MotionSettings, Toolhead


# Touch-offs press a rigid sphere: under a 5 mm tip acetal (Hertz) goes from the 0.4 N contact
# threshold to the cell's 45 N limit in 0.027 mm of travel, so the stop must land within that
# travel's time. At 2 mm/s, on the real drivers (loopback, a loaded machine) a touch reached the
# cell's 1500 N/s force-rate limit; at 1 mm/s (27 ms to land the stop) a loaded 2-core CI
# machine still reached 46 N. So a touch crosses the free air at TOUCH_SPEED_MM_S and only the
# last TOUCH_SLOW_ZONE_MM before the expected surface, and anything beyond it, at
# SLOW_TOUCH_SPEED_MM_S: 91 ms to land the stop, with the force rate at the limit about half the
# cell's rate limit. The slow zone is the placement error the touch-offs are there to find
# (a few mm before calibration); a surface nearer than that is met at the free-air speed.
TOUCH_SPEED_MM_S = 1.0
SLOW_TOUCH_SPEED_MM_S = 0.3
TOUCH_SLOW_ZONE_MM = 3.0


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


def motion_settings(cell_spec, speed_mm_s: float | None = None) -> MotionSettings:  # noqa: ANN001
    """The cell's speeds, the contact search slowed to at most ``TOUCH_SPEED_MM_S`` (the
    slow leg of a touch goes slower still: :func:`touch`)."""
    lim = cell_spec.limits
    return MotionSettings(contact_force_n=lim.contact_force_n,
                          contact_speed_mm_s=min(lim.contact_speed_mm_s, TOUCH_SPEED_MM_S),
                          free_speed_mm_s=speed_mm_s or lim.free_speed_mm_s, free_accel_mm_s2=lim.free_accel_mm_s2)


@dataclass
class Rig:
    """A toolhead on the cell being calibrated, and the simulator's noise key of each measurement."""

    head: Toolhead
    seed: int = 0
    step: int = 0

    @property
    def cell(self) -> Cell:
        return self.head.cell

    def begin_step(self) -> None:
        """A new step key for the simulator's noise streams (real cells ignore it)."""
        self.step += 1
        self.head.cell.begin_step((self.seed, self.step, 0))


def make_rig(cell_spec, cell: Cell, mesh, seed: int) -> Rig:  # noqa: ANN001 — config.CellSpec, trimesh
    """A rig on ``cell`` with ``mesh`` (object frame) on its table, travelling 60 mm above it."""
    mesh_base = mesh.copy()
    mesh_base.apply_transform(cell.base_to_object.matrix())
    validator = build_validator(cell_spec, cell, mesh_base)
    head = Toolhead(cell, motion_settings(cell_spec), validator, travel_z_mm=float(mesh_base.bounds[1][2]) + 60.0)
    return Rig(head, seed)


def touch(head: Toolhead, direction: np.ndarray, max_distance_mm: float,
          expected_mm: float | None = None) -> Pose | None:
    """Tare, then move along ``direction`` (base) until contact: the TCP pose at rest after
    the stop, or None when nothing was touched within ``max_distance_mm``. ``expected_mm``:
    where the surface should be along the way (nominal geometry); the travel up to
    TOUCH_SLOW_ZONE_MM before it is crossed faster (None: the whole way slowly)."""
    e = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    head.tare()
    fast_mm = 0.0 if expected_mm is None else min(max(expected_mm - TOUCH_SLOW_ZONE_MM, 0.0), max_distance_mm)
    rest_mm = max_distance_mm - fast_mm
    touched = (fast_mm > 0.0 and head.seek_contact(e, fast_mm)) or \
        (rest_mm > 0.0 and head.seek_contact(e, rest_mm, SLOW_TOUCH_SPEED_MM_S))
    if not touched:
        return None
    head.hold(0.05)
    return head.pose()


def back_off(head: Toolhead, direction: np.ndarray, distance_mm: float) -> None:
    """Slowly back out of a contact along ``-direction`` (contact allowed along the way)."""
    e = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    head.retract(-e, distance_mm, head.s.contact_speed_mm_s * 5.0)


def try_reach(head: Toolhead, target: Pose, via: Pose | None = None) -> bool:
    """Move to ``target`` directly, else via ``via``; False (nothing moved past a refusal) if refused."""
    try:
        head.move(target)
        return True
    except MotionRefused:
        pass
    if via is None:
        return False
    try:
        head.move(via)
        head.move(target)
        return True
    except MotionRefused:
        return False
