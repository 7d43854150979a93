"""Rigid transforms, rotation vectors and the probe geometry (docs/frames.md).

Units: positions in mm, angles in degrees at the edges (YAML, CLI) and radians
inside; UR poses (ur_rtde) are ``[x, y, z, rx, ry, rz]`` in metres and a rotation
vector in radians. See docs/frames.md for the frames and sign conventions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NINE_ANGLES_DEG: tuple[float, ...] = (10.0, 25.0, 45.0, 75.0, 90.0, 105.0, 135.0, 155.0, 170.0)
# Approach angles (from the surface, 90 = along the normal) inside this range are the
# interior ones; outside it the approach grazes the surface, and on a surface wider than
# the tool the F/T sensor and flange meet it before the tip does.
INTERIOR_ANGLES_DEG: tuple[float, float] = (25.0, 155.0)


def rotvec_to_matrix(rotvec_rad: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (axis * angle, rad) -> 3x3 rotation matrix."""
    r = np.asarray(rotvec_rad, dtype=float)
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
        return np.eye(3) + k
    k_axis = r / theta
    k = np.array([[0.0, -k_axis[2], k_axis[1]], [k_axis[2], 0.0, -k_axis[0]], [-k_axis[1], k_axis[0], 0.0]])
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def matrix_to_rotvec(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> rotation vector (rad), angle in [0, pi], accurate at every angle.

    Through the unit quaternion (Shepperd's choice of the largest of its four components,
    so no step divides by a small number), then angle = 2 atan2(|v|, w). A matrix that is
    orthogonal only to ~1e-9 (built from a stored normal and scan direction rounded to 9
    digits) converts to within that error: the angle taken from the trace alone does not,
    within ~1e-4 rad of pi, where 1 + cos(angle) is smaller than the matrix's error; there
    the old axis-from-the-antisymmetric-part gave a rotation 0.85 rad off instead of pi, so
    a 90-degree probe on a flat top was recorded (and would be sent to the arm) tilted 54
    degrees, and its scans landed 30 mm off the object (a false ``object_moved``).
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(rotation, dtype=float).tolist()
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        s = 0.25 / w
        q = (w, (m21 - m12) * s, (m02 - m20) * s, (m10 - m01) * s)
    elif m00 >= max(m11, m22):
        x = 0.5 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        s = 0.25 / x
        q = ((m21 - m12) * s, x, (m01 + m10) * s, (m02 + m20) * s)
    elif m11 >= m22:
        y = 0.5 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        s = 0.25 / y
        q = ((m02 - m20) * s, (m01 + m10) * s, y, (m12 + m21) * s)
    else:
        z = 0.5 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        s = 0.25 / z
        q = ((m10 - m01) * s, (m02 + m20) * s, (m12 + m21) * s, z)
    w, x, y, z = q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])   # the same rotation, angle <= pi
    sin_half = math.sqrt(x * x + y * y + z * z)
    if sin_half < 1e-12:
        return np.array([2.0 * x, 2.0 * y, 2.0 * z]) / max(w, 1e-300)   # angle ~ 2|v|/w
    scale = 2.0 * math.atan2(sin_half, w) / sin_half      # |q| cancels: unnormalised is fine
    return np.array([x * scale, y * scale, z * scale])


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``parent <- child``: ``x_parent = rotation @ x_child + position_mm``."""

    position_mm: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_mm", np.asarray(self.position_mm, dtype=float).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=float).reshape(3, 3))

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.zeros(3), np.eye(3))

    @staticmethod
    def from_ur(pose_m_rotvec: "np.ndarray | list[float]") -> "Pose":
        """From a ur_rtde pose ``[x, y, z, rx, ry, rz]`` (m, rad)."""
        p = np.asarray(pose_m_rotvec, dtype=float)
        return Pose(p[:3] * 1000.0, rotvec_to_matrix(p[3:6]))

    def to_ur(self) -> list[float]:
        """To a ur_rtde pose ``[x, y, z, rx, ry, rz]`` (m, rad)."""
        return [*(self.position_mm / 1000.0).tolist(), *matrix_to_rotvec(self.rotation).tolist()]

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> "Pose":
        m = np.asarray(matrix, dtype=float)
        return Pose(m[:3, 3], m[:3, :3])

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.position_mm
        return m

    def compose(self, other: "Pose") -> "Pose":
        """``self * other``: apply ``other`` first, then ``self``."""
        return Pose(self.rotation @ other.position_mm + self.position_mm, self.rotation @ other.rotation)

    def inverse(self) -> "Pose":
        rt = self.rotation.T
        return Pose(-rt @ self.position_mm, rt)

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Map points (N,3) or (3,) from the child frame to the parent frame."""
        pts = np.asarray(points_mm, dtype=float)
        return pts @ self.rotation.T + self.position_mm

    def apply_vector(self, vectors: np.ndarray) -> np.ndarray:
        """Rotate directions (N,3) or (3,) from the child frame to the parent frame."""
        return np.asarray(vectors, dtype=float) @ self.rotation.T

    def distance_to(self, other: "Pose") -> tuple[float, float]:
        """(translation in mm, rotation angle in deg) between two poses."""
        d_mm = float(np.linalg.norm(self.position_mm - other.position_mm))
        r = self.rotation.T @ other.rotation
        angle_deg = float(np.degrees(np.linalg.norm(matrix_to_rotvec(r))))
        return d_mm, angle_deg

    def to_list(self) -> list[float]:
        """Compact storage form: 3 position (mm) + 3 rotation vector (rad)."""
        return [*self.position_mm.tolist(), *matrix_to_rotvec(self.rotation).tolist()]

    @staticmethod
    def from_list(values: "list[float] | np.ndarray") -> "Pose":
        v = np.asarray(values, dtype=float)
        return Pose(v[:3], rotvec_to_matrix(v[3:6]))


def interpolate_pose(a: Pose, b: Pose, fraction: float) -> Pose:
    """Straight-line position and geodesic rotation between two poses."""
    f = float(np.clip(fraction, 0.0, 1.0))
    rel = matrix_to_rotvec(a.rotation.T @ b.rotation)
    return Pose(a.position_mm + f * (b.position_mm - a.position_mm), a.rotation @ rotvec_to_matrix(f * rel))


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise ValueError("zero-length vector has no direction")
    return v / n


def scan_direction(normal: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The scan direction t: ``reference`` projected on the tangent plane of ``normal``.

    One fixed rule (docs/frames.md), so that an angle means the same thing at every
    point of a region. Falls back to a stable perpendicular when ``reference`` is
    parallel to the normal.
    """
    n = unit(normal)
    r = np.asarray(reference, dtype=float)
    t = r - np.dot(r, n) * n
    if np.linalg.norm(t) < 1e-6:
        fallback = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t = fallback - np.dot(fallback, n) * n
    return unit(t)


def follows_scan_rule(normal: np.ndarray, t: np.ndarray, reference: np.ndarray) -> bool:
    """Whether ``t`` is the fixed rule's scan direction at ``normal`` (not a line turned at a
    border, docs/design.md §3): only such steps' angles mean what a region's model means."""
    return float(np.dot(np.asarray(t, dtype=float), scan_direction(normal, reference))) > 0.5


def push_direction(t: np.ndarray, n: np.ndarray, angle_deg: float) -> np.ndarray:
    """d = cos(a) t - sin(a) n: the direction the probe pushes (into the surface)."""
    a = np.radians(angle_deg)
    return np.cos(a) * np.asarray(t, dtype=float) - np.sin(a) * np.asarray(n, dtype=float)


def probe_axis(t: np.ndarray, n: np.ndarray, angle_deg: float) -> np.ndarray:
    """u = -cos(a) t + sin(a) n: from the contact point out along the probe body."""
    return -push_direction(t, n, angle_deg)


def probe_tcp_pose(point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, angle_deg: float,
                   offset_mm: float = 0.0) -> Pose:
    """TCP pose with the tip at ``point + offset * u`` for approach angle ``angle_deg``.

    Tool frame: +z is the push direction d (out of the flange, along the probe).
    +x lies in the (t, n) plane, perpendicular to the probe, on the side AWAY from
    the surface (x . n >= 0), so the eye-in-hand scanner mounted on the +x side
    looks down at the tip from above at every angle and its laser plane (the tool
    x-z plane) contains the probe axis and t. That side flips from +t to -t when
    the angle passes 90 degrees, so the wrist turns half a turn about the probe
    between 90 and 105 degrees; profiles do not care, being mapped through the pose.
    """
    n = unit(normal)
    t = unit(t)
    a = np.radians(angle_deg)
    z = unit(push_direction(t, n, angle_deg))
    side = 1.0 if angle_deg <= 90.0 else -1.0
    x = unit(side * (np.sin(a) * t + np.cos(a) * n))
    y = np.cross(z, x)
    rotation = np.column_stack([x, y, z])
    u = -z
    return Pose(np.asarray(point_mm, dtype=float) + offset_mm * u, rotation)


def scan_points_base(scans_xz_mm: np.ndarray, poses: np.ndarray, tcp_to_scanner: Pose) -> np.ndarray:
    """Scanner-frame profiles (S, L, 2) at TCP poses (S, 6) -> base-frame points (M, 3), NaN dropped."""
    out = []
    for xz, pose6 in zip(scans_xz_mm, poses):
        ok = np.isfinite(xz[:, 1]) & np.isfinite(xz[:, 0])
        if not ok.any():
            continue
        local = np.column_stack([xz[ok, 0], np.zeros(int(ok.sum())), xz[ok, 1]])
        base_scanner = Pose.from_list(pose6).compose(tcp_to_scanner)
        out.append(base_scanner.apply(local))
    return np.vstack(out) if out else np.zeros((0, 3))
