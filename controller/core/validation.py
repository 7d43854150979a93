"""Motion validation before anything is sent (docs/design.md §5).

A straight TCP path is accepted only if inverse kinematics exists along it within
the joint limits without a branch flip (what moveL can execute) and the tool's
collision shapes (probe, F/T sensor, scanner, flange) clear the object mesh, the
keep-out boxes and stay inside the workspace along the whole path, not only at
its end. During contact moves the last millimetres of the probe may touch.
"""
from __future__ import annotations

import numpy as np

from .collision import Box, SceneChecker, ToolShape
from .config import CellSpec, SessionInputs, effective_motion_limits
from .devices import Cell
from .errors import MotionRefused
from .geometry import Pose
from .kinematics import ArmModel, inverse, linear_path_joints, ur5e


def arm_model_for(cell: CellSpec) -> ArmModel:
    """The arm model of a cell: UR5e kinematics, its TCP, and the cell's joint limits."""
    return ur5e(cell.tool.flange_to_tcp.pose(), cell.robot.joint_limits_rad())


class PathValidator:
    """Checks straight TCP paths for reachability and collisions; raises MotionRefused."""

    def __init__(self, model: ArmModel, checker: object | None, seed_joints: np.ndarray,
                 contact_allowance_mm: float) -> None:
        self.model = model
        self.checker = checker
        self.seed_joints = np.asarray(seed_joints, dtype=float)
        self.contact_allowance_mm = contact_allowance_mm

    def validate_path(self, start: Pose, end: Pose, contact_allowed: bool = False) -> None:
        self._check_workspace(start, end)
        joints = linear_path_joints(self.model, start, end, self.seed_joints)
        if joints is None:
            raise MotionRefused(f"no joint path for the straight move to {np.round(end.position_mm, 1).tolist()} mm "
                                f"(unreachable, outside the joint limits, or through a singularity)")
        collision = self.collision(start, end, contact_allowed, leaving=True)
        if collision is not None:
            raise MotionRefused(f"collision: {collision}")
        self.seed_joints = np.asarray(joints[-1], dtype=float)

    def _check_workspace(self, start: Pose, end: Pose) -> None:
        """The TCP's ends inside the workspace box (so the whole straight path is: a box is
        convex), checked first: it costs nothing, and the rest of the work grows with the path."""
        workspace = getattr(self.checker, "workspace", None)
        if workspace is None:
            return
        for what, pose in (("start", start), ("end", end)):
            outside = float(workspace.signed_distance(pose.position_mm[None])[0])
            if outside > 0:
                raise MotionRefused(f"the move's {what} {np.round(pose.position_mm, 1).tolist()} mm is "
                                    f"{outside:.0f} mm outside the workspace")

    def collision(self, start: Pose, end: Pose, contact_allowed: bool = False, leaving: bool = False) -> str | None:
        """The first collision along the straight TCP path (a message), None when clear.
        Geometry only: no inverse kinematics, and the validator's state is unchanged, so
        planning can ask about moves long before they are made. ``leaving``: a move about to
        be made from where the arm is or will be (validate_path), which may leave a
        keep-out's clearance it starts in (core/collision.py)."""
        if self.checker is None:
            return None
        allowance = self.contact_allowance_mm if contact_allowed else 0.0
        hits = self.checker.check_path(start, end, ignore_tip_mm=allowance,   # type: ignore[attr-defined]
                                       leaving=leaving)
        return hits[0].message if hits else None

    def reachable_at_all_angles(self, poses: list[Pose]) -> bool:
        """IK exists within the joint limits for every pose (e.g. every angle of a target)."""
        return all(inverse(self.model, p, self.seed_joints) is not None for p in poses)


def build_validator(inputs: SessionInputs, cell: Cell, object_mesh: object) -> PathValidator:
    """A validator for a cell: its kinematics, tool shapes, object mesh in the base frame, boxes."""

    spec = inputs.cell
    shapes = [ToolShape(name=s.name, kind=s.kind, pose_in_tcp=s.pose.pose(), radius_mm=s.radius_mm,
                        length_mm=s.length_mm, size_mm=s.size_mm) for s in spec.tool.shapes]
    mesh_base = None
    if object_mesh is not None:
        mesh_base = object_mesh.copy()            # type: ignore[attr-defined]
        mesh_base.apply_transform(cell.base_to_object.matrix())
    lim = spec.limits
    keep_out = [Box(b.name, np.array(b.min_mm), np.array(b.max_mm)) for b in lim.keep_out]
    workspace = Box("workspace", np.array(lim.workspace.min_mm), np.array(lim.workspace.max_mm))
    checker = SceneChecker(shapes, mesh_base, keep_out, workspace)
    pr = inputs.plan.probing
    # The probe may touch along the contact search: as far as the plan's (tightened) search goes.
    allowance = pr.standoff_mm + effective_motion_limits(inputs)["search_distance_mm"] + spec.tool.tip_radius_mm
    return PathValidator(arm_model_for(inputs.cell), checker, cell.arm.status().joints_rad, allowance)
