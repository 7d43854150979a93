"""UR5e-like arm kinematics: forward, analytic inverse (8 branches), straight-line
(moveL) joint paths, trapezoidal timing and the Jacobian (docs/design.md §5, §8).

Frames and units:
- base: the robot base frame of the UR standard DH convention (what the UR
  controller reports poses in); positions in mm, rotations as matrices.
- flange: the tool flange (DH frame 6). tcp: the probe tip, ``flange <- tcp`` is
  ``ArmModel.flange_to_tcp`` (from the cell file).
- Joint angles in rad, joint speeds in rad/s; TCP speeds in mm/s.

DH convention (UR standard): ``T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
The analytic inverse follows the classic UR decomposition (shoulder from the wrist
centre, wrist 2 from the flange z, wrist 3 from the flange axes, then the planar
shoulder-elbow pair), re-derived here; every candidate is checked by forward
kinematics before it is offered.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import Pose, interpolate_pose, matrix_to_rotvec

TWO_PI = 2.0 * math.pi

# A solution must reproduce the target flange to this accuracy (mm; rotation matrix
# entries) to be offered; rounding is ~1e-12, poor branches at the edge of reach ~1e-3.
_IK_CHECK_POS_MM = 1e-6
_IK_CHECK_ROT = 1e-8
# Slack on acos/asin arguments from rounding at the edge of reach.
_ACOS_SLACK = 1e-9
# |sin(theta5)| below this is the wrist singularity: wrist 3 is then chosen freely.
_WRIST_SINGULAR_SIN = 1e-9


@dataclass(frozen=True)
class ArmModel:
    """Kinematic and motion limits of a 6-axis UR-type arm (standard DH, mm and rad)."""

    name: str
    dh_a_mm: np.ndarray
    dh_d_mm: np.ndarray
    dh_alpha_rad: np.ndarray
    joint_limits_rad: np.ndarray          # (6, 2): [min, max] per joint
    max_joint_speed_rad_s: np.ndarray     # (6,)
    max_joint_accel_rad_s2: np.ndarray    # (6,)
    max_tcp_speed_mm_s: float
    max_tcp_accel_mm_s2: float
    flange_to_tcp: Pose = field(default_factory=Pose.identity)   # flange <- tcp

    def __post_init__(self) -> None:
        for name, shape in (("dh_a_mm", (6,)), ("dh_d_mm", (6,)), ("dh_alpha_rad", (6,)),
                            ("joint_limits_rad", (6, 2)), ("max_joint_speed_rad_s", (6,)),
                            ("max_joint_accel_rad_s2", (6,))):
            value = np.array(getattr(self, name), dtype=float).reshape(shape)
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        if np.any(self.joint_limits_rad[:, 0] >= self.joint_limits_rad[:, 1]):
            raise ValueError("joint limits need min < max on every joint")

    @property
    def reach_mm(self) -> float:
        """An upper bound on the distance from the base origin to the TCP in any joint
        configuration: each DH link moves the frame by at most sqrt(a^2 + d^2) mm."""
        links = float(np.sum(np.hypot(self.dh_a_mm, self.dh_d_mm)))
        return links + float(np.linalg.norm(self.flange_to_tcp.position_mm))

    def with_tcp(self, flange_to_tcp: Pose) -> "ArmModel":
        """The same arm carrying a different tool."""
        return ArmModel(self.name, self.dh_a_mm, self.dh_d_mm, self.dh_alpha_rad, self.joint_limits_rad,
                        self.max_joint_speed_rad_s, self.max_joint_accel_rad_s2, self.max_tcp_speed_mm_s,
                        self.max_tcp_accel_mm_s2, flange_to_tcp)


def ur5e(flange_to_tcp: Pose = Pose.identity(), joint_limits_rad: np.ndarray | None = None) -> ArmModel:
    """A UR5e with its published DH parameters and limits.

    ``joint_limits_rad`` (6, 2) may tighten the default +-2 pi per joint (a cell file does).
    Speeds: 180 deg/s on every joint, TCP up to 1000 mm/s; accelerations are the
    teach pendant's ceilings (joint 800 deg/s^2, tool 5000 mm/s^2).
    """
    limits = np.tile([-TWO_PI, TWO_PI], (6, 1)) if joint_limits_rad is None else np.asarray(joint_limits_rad, float)
    return ArmModel(
        name="UR5e",
        dh_a_mm=np.array([0.0, -425.0, -392.2, 0.0, 0.0, 0.0]),
        dh_d_mm=np.array([162.5, 0.0, 0.0, 133.3, 99.7, 99.6]),
        dh_alpha_rad=np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]),
        joint_limits_rad=limits,
        max_joint_speed_rad_s=np.full(6, math.radians(180.0)),
        max_joint_accel_rad_s2=np.full(6, math.radians(800.0)),
        max_tcp_speed_mm_s=1000.0,
        max_tcp_accel_mm_s2=5000.0,
        flange_to_tcp=flange_to_tcp,
    )


# ---------------------------------------------------------------------------------------
# Forward kinematics


def _dh_matrix(a_mm: float, d_mm: float, alpha_rad: float, theta_rad: float) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` as a 4x4 matrix (mm)."""
    ct, st = math.cos(theta_rad), math.sin(theta_rad)
    ca, sa = math.cos(alpha_rad), math.sin(alpha_rad)
    return np.array([[ct, -st * ca, st * sa, a_mm * ct],
                     [st, ct * ca, -ct * sa, a_mm * st],
                     [0.0, sa, ca, d_mm],
                     [0.0, 0.0, 0.0, 1.0]])


def joint_frames(model: ArmModel, joints_rad: np.ndarray) -> list[np.ndarray]:
    """``base <- frame_i`` (4x4, mm) for i = 0..6 (frame 0 is the base, 6 the flange)."""
    q = np.asarray(joints_rad, dtype=float).reshape(6)
    frames = [np.eye(4)]
    for i in range(6):
        frames.append(frames[-1] @ _dh_matrix(model.dh_a_mm[i], model.dh_d_mm[i], model.dh_alpha_rad[i], q[i]))
    return frames


def forward_flange_batch(model: ArmModel, joints_rad: np.ndarray) -> np.ndarray:
    """``base <- flange`` (N, 4, 4) in mm for joint rows (N, 6) in rad, vectorised."""
    q = np.asarray(joints_rad, dtype=float).reshape(-1, 6)
    out = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4)).copy()
    for i in range(6):
        ct, st = np.cos(q[:, i]), np.sin(q[:, i])
        ca, sa = math.cos(model.dh_alpha_rad[i]), math.sin(model.dh_alpha_rad[i])
        t = np.zeros((q.shape[0], 4, 4))
        t[:, 0, 0], t[:, 0, 1], t[:, 0, 2], t[:, 0, 3] = ct, -st * ca, st * sa, model.dh_a_mm[i] * ct
        t[:, 1, 0], t[:, 1, 1], t[:, 1, 2], t[:, 1, 3] = st, ct * ca, -ct * sa, model.dh_a_mm[i] * st
        t[:, 2, 1], t[:, 2, 2], t[:, 2, 3] = sa, ca, model.dh_d_mm[i]
        t[:, 3, 3] = 1.0
        out = out @ t
    return out


def forward_flange(model: ArmModel, joints_rad: np.ndarray) -> Pose:
    """``base <- flange`` at joint angles ``joints_rad`` (rad)."""
    return Pose.from_matrix(joint_frames(model, joints_rad)[-1])


def forward(model: ArmModel, joints_rad: np.ndarray) -> Pose:
    """``base <- tcp`` at joint angles ``joints_rad`` (rad)."""
    return forward_flange(model, joints_rad).compose(model.flange_to_tcp)


def jacobian(model: ArmModel, joints_rad: np.ndarray) -> np.ndarray:
    """Geometric Jacobian of the TCP in the base frame, (6, 6).

    Rows 0-2: TCP linear velocity (mm/s per rad/s); rows 3-5: angular velocity
    (rad/s per rad/s). Column i is joint i.
    """
    frames = joint_frames(model, joints_rad)
    p_tcp = (frames[-1] @ model.flange_to_tcp.matrix())[:3, 3]
    jac = np.zeros((6, 6))
    for i in range(6):
        z = frames[i][:3, 2]
        jac[:3, i] = np.cross(z, p_tcp - frames[i][:3, 3])
        jac[3:, i] = z
    return jac


def manipulability(model: ArmModel, joints_rad: np.ndarray, length_scale_mm: float = 1000.0) -> float:
    """Yoshikawa's measure sqrt(det(J J^T)) with the linear rows in units of ``length_scale_mm``.

    Zero at a singularity (wrist, elbow stretched, wrist centre over the shoulder axis).
    """
    jac = jacobian(model, joints_rad)
    jac[:3] /= length_scale_mm
    return float(math.sqrt(max(np.linalg.det(jac @ jac.T), 0.0)))


# ---------------------------------------------------------------------------------------
# Inverse kinematics


def _dh_batch(a_mm: float, d_mm: float, alpha_rad: float, theta_rad: np.ndarray) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` for an array of angles: (..., 4, 4)."""
    ct, st = np.cos(theta_rad), np.sin(theta_rad)
    ca, sa = math.cos(alpha_rad), math.sin(alpha_rad)
    out = np.zeros(np.shape(theta_rad) + (4, 4))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2], out[..., 0, 3] = ct, -st * ca, st * sa, a_mm * ct
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2], out[..., 1, 3] = st, ct * ca, -ct * sa, a_mm * st
    out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa, ca, d_mm
    out[..., 3, 3] = 1.0
    return out


def _rigid_inverse_batch(m: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    out = np.zeros_like(m)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, m[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _inverse_flange_batch(model: ArmModel, flange: np.ndarray, theta6_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8 analytic branches for each ``base <- flange`` (P, 4, 4) in mm, vectorised.

    Returns (q (P, 8, 6) in (-pi, pi], exists (P, 8)). Branch index = 4 * shoulder +
    2 * wrist + elbow (0 = +, 1 = -). At the wrist singularity (sin theta5 = 0) joints 4
    and 6 are coupled; theta6 is then ``theta6_hint`` (P,) and theta4 absorbs the rest.
    """
    a, d, alpha = model.dh_a_mm, model.dh_d_mm, model.dh_alpha_rad
    n_pose = flange.shape[0]
    rot, p06 = flange[:, :3, :3], flange[:, :3, 3]
    # Wrist centre (frame 5 origin): back along the flange z by d6.
    p05 = p06 - d[5] * rot[:, :, 2]
    r_xy = np.hypot(p05[:, 0], p05[:, 1])
    # Inside the shoulder's cylinder (r < d4) nothing reaches the wrist centre.
    exists_pose = r_xy >= abs(d[3]) - _ACOS_SLACK
    phi = np.arccos(np.clip(abs(d[3]) / np.maximum(r_xy, 1e-12), -1.0, 1.0))
    psi = np.arctan2(p05[:, 1], p05[:, 0])
    signs = np.array([1.0, -1.0])
    th1 = psi[:, None] + signs[None, :] * phi[:, None] + math.pi / 2                 # (P, 2)
    s1, c1 = np.sin(th1), np.cos(th1)
    cos5 = (p06[:, 0, None] * s1 - p06[:, 1, None] * c1 - d[3]) / d[5]
    exists_5 = np.abs(cos5) <= 1.0 + 1e-7
    th5 = signs[None, None, :] * np.arccos(np.clip(cos5, -1.0, 1.0))[:, :, None]      # (P, 2, 2)
    s5 = np.sin(th5)
    # theta6 from the rows of the flange rotation (the columns of its inverse).
    num_s = (-rot[:, 0, 1, None] * s1 + rot[:, 1, 1, None] * c1)[:, :, None]
    num_c = (rot[:, 0, 0, None] * s1 - rot[:, 1, 0, None] * c1)[:, :, None]
    singular = np.abs(s5) < _WRIST_SINGULAR_SIN
    safe_s5 = np.where(singular, 1.0, s5)
    th6 = np.where(singular, theta6_hint[:, None, None], np.arctan2(num_s / safe_s5, num_c / safe_s5))
    th1_b = np.broadcast_to(th1[:, :, None], th5.shape)
    t01 = _dh_batch(a[0], d[0], alpha[0], th1_b)
    t46 = _dh_batch(a[4], d[4], alpha[4], th5) @ _dh_batch(a[5], d[5], alpha[5], th6)
    t14 = _rigid_inverse_batch(t01) @ flange[:, None, None] @ _rigid_inverse_batch(t46)   # (P, 2, 2, 4, 4)
    # Frame 4's origin in frame 1: the planar shoulder-elbow pair works in the x1-y1
    # plane (p14 = a2 [c2, s2] + a3 [c23, s23], with d4 along z1).
    px, py = t14[..., 0, 3], t14[..., 1, 3]
    cos3 = (px * px + py * py - a[1] ** 2 - a[2] ** 2) / (2.0 * a[1] * a[2])
    exists_3 = np.abs(cos3) <= 1.0 + 1e-7
    th3 = signs * np.arccos(np.clip(cos3, -1.0, 1.0))[..., None]                     # (P, 2, 2, 2)
    th2 = np.arctan2(py, px)[..., None] - np.arctan2(a[2] * np.sin(th3), a[1] + a[2] * np.cos(th3))
    # Joints 2-4 are parallel (alpha = 0): their angles add up to frame 4's rotation about z1.
    th4 = np.arctan2(t14[..., 1, 0], t14[..., 0, 0])[..., None] - th2 - th3
    shape = th3.shape
    q = np.stack([np.broadcast_to(th1[:, :, None, None], shape), th2, th3, th4,
                  np.broadcast_to(th5[..., None], shape), np.broadcast_to(th6[..., None], shape)], axis=-1)
    q = np.arctan2(np.sin(q), np.cos(q)).reshape(n_pose, 8, 6)
    exists = (exists_pose[:, None, None, None] & exists_5[:, :, None, None] & exists_3[..., None])
    exists = np.broadcast_to(exists, shape).reshape(n_pose, 8)
    return q, exists


def _wrap_into_limits(q_rad: np.ndarray, limits_rad: np.ndarray, seed_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For solutions (N, 6): per joint, the 2 pi-equivalent inside the limits closest to
    the seed. Returns (wrapped (N, 6), ok (N,)); ok is False where some joint cannot fit."""
    lo, hi = limits_rad[:, 0], limits_rad[:, 1]
    k_min = math.floor((float(lo.min()) - math.pi) / TWO_PI)
    k_max = math.ceil((float(hi.max()) + math.pi) / TWO_PI)
    cand = q_rad[:, :, None] + TWO_PI * np.arange(k_min, k_max + 1)[None, None, :]     # (N, 6, K)
    slack = 1e-12
    inside = (cand >= lo[None, :, None] - slack) & (cand <= hi[None, :, None] + slack)
    cost = np.where(inside, np.abs(cand - seed_rad[None, :, None]), np.inf)
    best = np.argmin(cost, axis=2)
    wrapped = np.take_along_axis(cand, best[:, :, None], axis=2)[:, :, 0]
    ok = np.all(np.isfinite(np.take_along_axis(cost, best[:, :, None], axis=2)[:, :, 0]), axis=1)
    # The slack may leave a value a hair outside: put it exactly on the limit.
    return np.clip(wrapped, lo, hi), ok


def _tcp_to_flange(model: ArmModel, tcp_matrices: np.ndarray) -> np.ndarray:
    return tcp_matrices @ _rigid_inverse_batch(model.flange_to_tcp.matrix())


def _valid_branches(model: ArmModel, flange: np.ndarray, theta6_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(q (P, 8, 6), valid (P, 8)): branches that exist and reproduce the flange when
    checked by forward kinematics (numerically poor ones at the edge of reach are not
    offered). Joint limits are not applied yet."""
    q, exists = _inverse_flange_batch(model, flange, theta6_hint)
    got = forward_flange_batch(model, q.reshape(-1, 6)).reshape(q.shape[0], 8, 4, 4)
    pos_err = np.linalg.norm(got[..., :3, 3] - flange[:, None, :3, 3], axis=-1)
    rot_err = np.max(np.abs(got[..., :3, :3] - flange[:, None, :3, :3]), axis=(-1, -2))
    return q, exists & (pos_err <= _IK_CHECK_POS_MM) & (rot_err <= _IK_CHECK_ROT)


def _select(model: ArmModel, q: np.ndarray, valid: np.ndarray, seed: np.ndarray) -> list[np.ndarray]:
    """Valid branches (8, 6) wrapped into the limits near ``seed``, nearest first."""
    wrapped, ok = _wrap_into_limits(q, model.joint_limits_rad, seed)
    keep = wrapped[valid & ok]
    order = np.argsort(np.sum(np.abs(keep - seed), axis=1), kind="stable")
    return [keep[i] for i in order]


def inverse_all(model: ArmModel, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> list[np.ndarray]:
    """Every IK solution within the joint limits (one per branch, each joint wrapped by
    +-2 pi to the value closest to the seed), sorted by distance to the seed (rad)."""
    seed = np.zeros(6) if seed_joints_rad is None else np.asarray(seed_joints_rad, dtype=float).reshape(6)
    flange = _tcp_to_flange(model, tcp_pose.matrix()[None])
    q, valid = _valid_branches(model, flange, seed[5:6])
    return _select(model, q[0], valid[0], seed)


def inverse(model: ArmModel, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
    """Joint angles (rad) putting the TCP at ``tcp_pose`` (base <- tcp), within the joint
    limits, closest to ``seed_joints_rad`` (sum of |differences|; default: all zero);
    None if the pose is out of reach or needs a joint outside its limits."""
    found = inverse_all(model, tcp_pose, seed_joints_rad)
    return found[0] if found else None


# ---------------------------------------------------------------------------------------
# Straight-line paths


def path_samples(start: Pose, end: Pose, step_mm: float, step_deg: float) -> np.ndarray:
    """Fractions in [0, 1] so that consecutive poses differ by <= step_mm and <= step_deg."""
    dist_mm, angle_deg = start.distance_to(end)
    n = max(1, math.ceil(dist_mm / step_mm - 1e-9), math.ceil(angle_deg / step_deg - 1e-9))
    return np.linspace(0.0, 1.0, n + 1)


def singularity_margins_batch(model: ArmModel, joints_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`singularity_margins` for joint rows (N, 6): three arrays (N,)."""
    q = np.asarray(joints_rad, dtype=float).reshape(-1, 6)
    wrist_deg = np.degrees(np.arcsin(np.minimum(1.0, np.abs(np.sin(q[:, 4])))))
    elbow_deg = np.degrees(np.arcsin(np.minimum(1.0, np.abs(np.sin(q[:, 2])))))
    flange = forward_flange_batch(model, q)
    p05 = flange[:, :3, 3] - model.dh_d_mm[5] * flange[:, :3, 2]
    r2 = p05[:, 0] ** 2 + p05[:, 1] ** 2
    shoulder_mm = np.sqrt(np.maximum(r2 - model.dh_d_mm[3] ** 2, 0.0))
    return wrist_deg, elbow_deg, shoulder_mm


def singularity_margins(model: ArmModel, joints_rad: np.ndarray) -> tuple[float, float, float]:
    """How far a configuration is from the UR's three singularities:
    (wrist: |theta5| folded into [0, 90] deg, elbow: |theta3| folded likewise (deg),
    shoulder: horizontal distance (mm) of the wrist centre from the plane through the
    base axis parallel to the shoulder axis, sqrt(r^2 - d4^2))."""
    w, e, s = singularity_margins_batch(model, joints_rad)
    return float(w[0]), float(e[0]), float(s[0])


def linear_path_joints(model: ArmModel, start: Pose, end: Pose, seed_joints_rad: np.ndarray | None,
                       step_mm: float = 5.0, step_deg: float = 5.0,
                       max_joint_step_rad: float = math.radians(30.0), min_wrist_deg: float = 2.0,
                       min_elbow_deg: float = 2.0, min_shoulder_mm: float = 20.0) -> np.ndarray | None:
    """Joint angles (N, 6) along the straight TCP path start -> end (positions linear,
    rotation geodesic), each waypoint seeded by the previous one (the first by the seed).

    None when moveL cannot do that path:
    - a waypoint is out of reach or needs a joint outside its limits;
    - the joints jump between waypoints by more than ``max_joint_step_rad``: a branch
      flip, or the joint-rate blow-up beside a singularity. Waypoints are at most
      ``step_mm`` and ``step_deg`` apart; a regular configuration moves each joint by
      about 1 deg per 5 mm and the wrist about 1:1 with the tool's rotation, so the
      default bound (30 deg per waypoint) leaves a wide margin;
    - a waypoint lies within the given margins of a singularity (see
      :func:`singularity_margins`): passing exactly through one can be smooth in joint
      space, but the real controller stops a moveL there.

    Bounded work: an end beyond the arm's reach is refused before any waypoint is
    sampled, so a path has at most about 2 * reach / step_mm waypoints.
    """
    reach = model.reach_mm
    if max(float(np.linalg.norm(start.position_mm)), float(np.linalg.norm(end.position_mm))) > reach:
        return None
    fractions = path_samples(start, end, step_mm, step_deg)
    seed = np.zeros(6) if seed_joints_rad is None else np.asarray(seed_joints_rad, dtype=float).reshape(6)
    tcp = np.stack([interpolate_pose(start, end, float(f)).matrix() for f in fractions])
    flange = _tcp_to_flange(model, tcp)
    # All branches of all waypoints at once; at an exact wrist singularity theta6 keeps the seed's.
    q_all, valid_all = _valid_branches(model, flange, np.full(fractions.size, seed[5]))
    out = np.empty((fractions.size, 6))
    for k in range(fractions.size):
        found = _select(model, q_all[k], valid_all[k], seed)
        if not found:
            return None
        q = found[0]
        if k > 0 and float(np.max(np.abs(q - out[k - 1]))) > max_joint_step_rad:
            return None
        out[k] = q
        seed = q
    wrist_deg, elbow_deg, shoulder_mm = singularity_margins_batch(model, out)
    if (np.min(wrist_deg) < min_wrist_deg or np.min(elbow_deg) < min_elbow_deg
            or np.min(shoulder_mm) < min_shoulder_mm):
        return None
    return out


# ---------------------------------------------------------------------------------------
# Timing


def trapezoid_duration_s(distance: float, speed: float, accel: float) -> float:
    """Duration (s) of a rest-to-rest move over ``distance`` with cruise ``speed`` and
    ``accel`` (any consistent units: mm, mm/s, mm/s^2 or rad, rad/s, rad/s^2).
    Triangular when the distance is too short to reach the speed."""
    d = abs(float(distance))
    if d == 0.0:
        return 0.0
    if speed <= 0.0 or accel <= 0.0:
        raise ValueError("speed and accel must be positive")
    if d <= speed * speed / accel:          # the two ramps alone would cover more than d
        return 2.0 * math.sqrt(d / accel)
    return d / speed + speed / accel


def trapezoid_state(distance: float, speed: float, accel: float, t_s: float) -> tuple[float, float]:
    """(position, velocity) at time ``t_s`` along the rest-to-rest profile of
    :func:`trapezoid_duration_s`; signed like ``distance``; clamped to the ends."""
    sign = -1.0 if distance < 0 else 1.0
    d = abs(float(distance))
    total = trapezoid_duration_s(d, speed, accel)
    if d == 0.0 or t_s <= 0.0:
        return 0.0, 0.0
    if t_s >= total:
        return sign * d, 0.0
    if d <= speed * speed / accel:          # triangle: accelerate to the middle, then brake
        t_ramp, v_peak = total / 2.0, accel * total / 2.0
    else:
        t_ramp, v_peak = speed / accel, speed
    d_ramp = 0.5 * accel * t_ramp * t_ramp
    if t_s < t_ramp:
        return sign * 0.5 * accel * t_s * t_s, sign * accel * t_s
    if t_s <= total - t_ramp:
        return sign * (d_ramp + v_peak * (t_s - t_ramp)), sign * v_peak
    t_left = total - t_s
    return sign * (d - 0.5 * accel * t_left * t_left), sign * accel * t_left


def move_duration_s(model: ArmModel, start: Pose, end: Pose, speed_mm_s: float, accel_mm_s2: float,
                    angular_speed_deg_s: float | None = None, angular_accel_deg_s2: float | None = None,
                    seed_joints_rad: np.ndarray | None = None, rotation_equiv_mm_per_rad: float = 100.0,
                    check_joints: bool = True) -> float:
    """Robot time (s) of a rest-to-rest moveL from ``start`` to ``end`` (base <- tcp).

    One trapezoidal profile in the path parameter s in [0, 1]; its peak rate and
    acceleration are the smallest allowed by: the TCP speed/accel (clamped to the arm's
    limits) over the distance, the angular speed/accel over the rotation angle (default:
    the linear ones at ``rotation_equiv_mm_per_rad``, the simulated arm's rule, so a pure
    rotation takes a sensible time), and, with ``check_joints``, every joint's speed and
    acceleration limit over its largest rate dq/ds along the path (the arm slows down near
    singularities). Raises ValueError if the path is not feasible for moveL.
    """
    dist_mm, angle_deg = start.distance_to(end)
    angle_rad = math.radians(angle_deg)
    v = min(float(speed_mm_s), model.max_tcp_speed_mm_s)
    a = min(float(accel_mm_s2), model.max_tcp_accel_mm_s2)
    w = math.radians(angular_speed_deg_s) if angular_speed_deg_s is not None else v / rotation_equiv_mm_per_rad
    alpha = (math.radians(angular_accel_deg_s2) if angular_accel_deg_s2 is not None
             else a / rotation_equiv_mm_per_rad)
    if dist_mm < 1e-9 and angle_rad < 1e-12:
        return 0.0
    rates: list[float] = []      # peak ds/dt allowed by each limit (1/s)
    accels: list[float] = []     # peak d2s/dt2 (1/s^2)
    if dist_mm > 0.0:
        rates.append(v / dist_mm)
        accels.append(a / dist_mm)
    if angle_rad > 0.0:
        rates.append(w / angle_rad)
        accels.append(alpha / angle_rad)
    if check_joints:
        path = linear_path_joints(model, start, end, seed_joints_rad)
        if path is None:
            raise ValueError("moveL path is not feasible (out of reach, limits or a singularity)")
        if path.shape[0] > 1:
            dq_ds = np.max(np.abs(np.diff(path, axis=0)), axis=0) * (path.shape[0] - 1)   # rad per unit s
            moving = dq_ds > 1e-12
            if np.any(moving):
                rates.append(float(np.min(model.max_joint_speed_rad_s[moving] / dq_ds[moving])))
                accels.append(float(np.min(model.max_joint_accel_rad_s2[moving] / dq_ds[moving])))
    return trapezoid_duration_s(1.0, min(rates), min(accels))


def pose_error(a: Pose, b: Pose) -> tuple[float, float]:
    """(position error mm, rotation error rad) between two poses."""
    return (float(np.linalg.norm(a.position_mm - b.position_mm)),
            float(np.linalg.norm(matrix_to_rotvec(a.rotation.T @ b.rotation))))
