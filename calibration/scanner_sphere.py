"""Scanner extrinsics (tcp <- scanner) from profiles of a sphere of known radius.

Each laser profile lies in the scanner's x-z plane (y = 0). Where the plane cuts a
sphere of radius R the profile is a circle arc: its centre (x_c, z_c) and radius r
give the sphere centre in the scanner frame, p = (x_c, +-sqrt(R^2 - r^2), z_c); the
sign (which side of the laser plane the centre lies) comes from the current estimate
of the mount, so poses are planned with the plane clearly off the centre.

With the TCP pose (R_i, t_i) of each profile, every centre satisfies
c = R_i (R_s p_i + t_s) + t_i, linear in (R_s as a free 3x3, t_s, c): solved by least
squares, R_s projected on SO(3), (t_s, c) re-solved, then everything refined on the
point-to-sphere distances of all profile points (robust loss). Pure translations
cannot separate t_s from c, and a single rotation axis leaves the mount's turn about
it free: the rotation spread and the Jacobian's conditioning are checked.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from elastoprobe.controller.core.errors import CalibrationError
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix

from .common import (FitReport, data_sha256, residual_stats, rotation_spread_deg,
                     scaled_condition_number)

MIN_PROFILES = 8
MIN_ARC_POINTS = 12


@dataclass(frozen=True)
class CircleFit:
    centre_xz_mm: np.ndarray
    radius_mm: float
    rms_mm: float
    inliers: np.ndarray          # boolean mask over the points given


def fit_circle(xz_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit refined geometrically: (centre (2,), radius) of points (N,2)."""
    p = np.asarray(xz_mm, dtype=float)
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = np.einsum("ij,ij->i", p, p)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:2]
    radius = float(np.sqrt(max(sol[2] + centre @ centre, 1e-12)))

    def res(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p - x[:2], axis=1) - x[2]

    out = least_squares(res, np.array([*centre, radius]), method="lm")
    return out.x[:2], float(out.x[2])


def table_line_mask(xz_mm: np.ndarray, inlier_mm: float = 0.3, min_points: int = 15, min_extent_mm: float = 15.0,
                    trials: int = 200, seed: int = 0) -> np.ndarray:
    """Points (N,2, finite) on the profile's dominant straight line, if it is long: the table.

    Removed before the circle search because a short straight run lies within a thin band
    of a large circle and would outvote a small arc of the sphere.
    """
    p = np.asarray(xz_mm, dtype=float)
    best = np.zeros(len(p), dtype=bool)
    if len(p) < min_points:
        return best
    rng = np.random.default_rng(seed)
    for _ in range(trials):
        a, b = p[rng.choice(len(p), 2, replace=False)]
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 1e-6:
            continue
        normal = np.array([-d[1], d[0]]) / length
        inl = np.abs((p - a) @ normal) < inlier_mm
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < min_points:
        return np.zeros(len(p), dtype=bool)
    direction = p[best] - p[best].mean(axis=0)
    _, _, vt = np.linalg.svd(direction, full_matrices=False)
    extent = float(np.ptp(direction @ vt[0]))
    return best if extent >= min_extent_mm else np.zeros(len(p), dtype=bool)


def robust_circle(xz_mm: np.ndarray, max_radius_mm: float, inlier_mm: float = 0.3, trials: int = 200,
                  seed: int = 0) -> CircleFit | None:
    """RANSAC circle on a profile (N,2) with radius <= ``max_radius_mm``: the sphere's arc among table
    points (the dominant long straight run, removed first) and stray samples. ``inliers`` indexes the
    finite points. None when no arc of at least MIN_ARC_POINTS points spanning 30 deg is found."""
    p_all = np.asarray(xz_mm, dtype=float)
    p_all = p_all[np.all(np.isfinite(p_all), axis=1)]
    if len(p_all) < MIN_ARC_POINTS:
        return None
    candidate = ~table_line_mask(p_all, inlier_mm, seed=seed)
    p = p_all[candidate]
    if len(p) < MIN_ARC_POINTS:
        return None
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    for _ in range(trials):
        i = rng.choice(len(p), 3, replace=False)
        try:
            c, r = _circle_through(p[i])
        except ValueError:
            continue
        if r > max_radius_mm * 1.02:
            continue
        inl = np.abs(np.linalg.norm(p - c, axis=1) - r) < inlier_mm
        if best is None or inl.sum() > best.sum():
            best = inl
    if best is None or best.sum() < MIN_ARC_POINTS:
        return None
    centre, radius = fit_circle(p[best])
    inl = np.abs(np.linalg.norm(p - centre, axis=1) - radius) < inlier_mm
    if inl.sum() < MIN_ARC_POINTS:
        return None
    centre, radius = fit_circle(p[inl])
    if radius > max_radius_mm * 1.02:
        return None
    ang = np.arctan2(p[inl, 1] - centre[1], p[inl, 0] - centre[0])
    span = np.ptp(np.unwrap(np.sort(ang)))
    if span < np.radians(30.0):
        return None          # too short an arc to pin its centre down
    rms = float(np.sqrt(np.mean((np.linalg.norm(p[inl] - centre, axis=1) - radius) ** 2)))
    mask = np.zeros(len(p_all), dtype=bool)
    mask[np.flatnonzero(candidate)[inl]] = True
    return CircleFit(centre, radius, rms, mask)


def _circle_through(p3: np.ndarray) -> tuple[np.ndarray, float]:
    (x1, y1), (x2, y2), (x3, y3) = p3
    d = 2.0 * (x1 * (y2 - y3) + x2 * (y3 - y1) + x3 * (y1 - y2))
    if abs(d) < 1e-9:
        raise ValueError("collinear")
    s1, s2, s3 = x1 * x1 + y1 * y1, x2 * x2 + y2 * y2, x3 * x3 + y3 * y3
    ux = (s1 * (y2 - y3) + s2 * (y3 - y1) + s3 * (y1 - y2)) / d
    uy = (s1 * (x3 - x2) + s2 * (x1 - x3) + s3 * (x2 - x1)) / d
    c = np.array([ux, uy])
    return c, float(np.linalg.norm(p3[0] - c))


@dataclass(frozen=True)
class ScannerFit:
    """Solved mount ``tcp <- scanner`` (in the frame of the poses given), sphere centre (base, mm)."""

    tcp_to_scanner: Pose
    sphere_centre_base_mm: np.ndarray
    report: FitReport
    data_sha256: str


@dataclass(frozen=True)
class SphereProfile:
    """One profile of the sphere: TCP pose at exposure and the sphere's points (scanner x, z in mm)."""

    tcp_pose: Pose
    xz_mm: np.ndarray


def _centre_in_scanner(circle: CircleFit, radius_mm: float, sign: float) -> np.ndarray:
    h = np.sqrt(max(radius_mm**2 - circle.radius_mm**2, 0.0))
    return np.array([circle.centre_xz_mm[0], sign * h, circle.centre_xz_mm[1]])


def _linear_mount(rot: np.ndarray, trans: np.ndarray, centres_s: np.ndarray) -> tuple[Pose, np.ndarray, float]:
    """Linear least squares of c = R_i (R_s p_i + t_s) + t_i with R_s free, then projected on SO(3)."""
    n = rot.shape[0]
    a = np.zeros((3 * n, 15))
    for i in range(n):
        a[3 * i:3 * i + 3, :9] = np.kron(rot[i], centres_s[i][None, :])
        a[3 * i:3 * i + 3, 9:12] = rot[i]
        a[3 * i:3 * i + 3, 12:] = -np.eye(3)
    cond = scaled_condition_number(a)
    x, *_ = np.linalg.lstsq(a, -trans.ravel(), rcond=None)
    u, _, vt = np.linalg.svd(x[:9].reshape(3, 3))
    r_s = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    # Re-solve translation and centre with the rotation fixed.
    b = np.zeros((3 * n, 6))
    rhs = np.zeros(3 * n)
    for i in range(n):
        b[3 * i:3 * i + 3, :3] = rot[i]
        b[3 * i:3 * i + 3, 3:] = -np.eye(3)
        rhs[3 * i:3 * i + 3] = -trans[i] - rot[i] @ r_s @ centres_s[i]
    y, *_ = np.linalg.lstsq(b, rhs, rcond=None)
    return Pose(y[:3], r_s), y[3:], cond


def _sphere_centre(fits: list[tuple[SphereProfile, CircleFit]], mount: Pose, radius_mm: float) -> np.ndarray:
    """Centre (base, mm) of the sphere of known radius best fitting all arcs mapped through ``mount``."""
    pts = []
    for pr, c in fits:
        xz = pr.xz_mm[np.all(np.isfinite(pr.xz_mm), axis=1)][c.inliers]
        local = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
        pts.append(pr.tcp_pose.compose(mount).apply(local))
    p = np.vstack(pts)
    # Start below the cap's mean along the direction the scanner looked from (points face the scanner).
    viewpoints = np.stack([pr.tcp_pose.compose(mount).position_mm for pr, _ in fits])
    inward = p.mean(axis=0) - viewpoints.mean(axis=0)
    start = p.mean(axis=0) + radius_mm * inward / max(np.linalg.norm(inward), 1e-9)
    sol = least_squares(lambda c: np.linalg.norm(p - c, axis=1) - radius_mm, start, loss="soft_l1", f_scale=1.0)
    return sol.x


def _points_scanner(profiles: list[SphereProfile], masks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    pts, idx = [], []
    for i, (pr, m) in enumerate(zip(profiles, masks)):
        xz = pr.xz_mm[m]
        pts.append(np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]]))
        idx.append(np.full(len(xz), i))
    return np.vstack(pts), np.concatenate(idx)


def solve_scanner_sphere(profiles: list[SphereProfile], sphere_radius_mm: float, initial_tcp_to_scanner: Pose,
                         max_condition: float = 200.0, max_rms_mm: float = 0.2, min_spread_deg: float = 15.0,
                         inlier_mm: float = 0.3) -> ScannerFit:
    """The scanner mount from sphere profiles (see the module docstring).

    ``initial_tcp_to_scanner`` (the cell file's mount) decides which side of the laser
    plane each circle's sphere centre lies on, and is the second start of the refinement. Refuses fewer than
    8 usable profiles, a rotation spread under ``min_spread_deg``, a scaled
    condition number over ``max_condition`` or a point-to-sphere RMS over ``max_rms_mm``.
    """
    fits: list[tuple[SphereProfile, CircleFit]] = []
    for k, pr in enumerate(profiles):
        c = robust_circle(pr.xz_mm, sphere_radius_mm, inlier_mm, seed=k)
        if c is not None:
            fits.append((pr, c))
    if len(fits) < MIN_PROFILES:
        raise CalibrationError(f"scanner: {len(fits)} profiles show an arc of the sphere, at least {MIN_PROFILES} "
                               f"are needed")
    rot = np.stack([pr.tcp_pose.rotation for pr, _ in fits])
    trans = np.stack([pr.tcp_pose.position_mm for pr, _ in fits])
    spread = rotation_spread_deg(rot)
    if spread < min_spread_deg:
        raise CalibrationError(f"scanner: the poses' orientations span only {spread:.1f} deg (< {min_spread_deg:g}); "
                               f"pure translations cannot separate the mount from the sphere's position")
    mount = initial_tcp_to_scanner
    centre = None
    lin_cond = float("inf")
    for _ in range(3):
        # Side of the laser plane from the current estimate (the centre itself from the first pass's circles).
        if centre is None:
            centre = _sphere_centre(fits, mount, sphere_radius_mm)
        signs = []
        for pr, _ in fits:
            y = pr.tcp_pose.compose(mount).inverse().apply(centre)[1]
            signs.append(1.0 if y >= 0 else -1.0)
        centres_s = np.stack([_centre_in_scanner(c, sphere_radius_mm, s) for (_, c), s in zip(fits, signs)])
        mount, centre, lin_cond = _linear_mount(rot, trans, centres_s)
    used = [pr for pr, _ in fits]
    masks = [c.inliers for _, c in fits]
    clean = [pr.xz_mm[np.all(np.isfinite(pr.xz_mm), axis=1)] for pr in used]
    used = [SphereProfile(pr.tcp_pose, xz) for pr, xz in zip(used, clean)]
    pts_s, idx = _points_scanner(used, masks)
    pose_r = rot[idx]
    pose_t = trans[idx]

    def refine(start: Pose, centre0: np.ndarray):  # noqa: ANN202 — scipy OptimizeResult and the unpacker
        r0 = start.rotation

        def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return r0 @ rotvec_to_matrix(x[:3]), x[3:6], x[6:9]

        def residual(x: np.ndarray) -> np.ndarray:
            r_s, t_s, c = unpack(x)
            p_tcp = pts_s @ r_s.T + t_s
            p_base = np.einsum("nij,nj->ni", pose_r, p_tcp) + pose_t
            return np.linalg.norm(p_base - c, axis=1) - sphere_radius_mm

        x0 = np.concatenate([np.zeros(3), start.position_mm, centre0])
        sol = least_squares(residual, x0, loss="soft_l1", f_scale=inlier_mm,
                            x_scale=np.array([0.01] * 3 + [1.0] * 6), max_nfev=300)
        return sol, unpack, residual

    # Two starts: the linear solution and the given mount (the linear one can be thrown off
    # by a profile whose centre was put on the wrong side of the laser plane); the lower
    # robust cost wins.
    starts = [(mount, centre), (initial_tcp_to_scanner, _sphere_centre(fits, initial_tcp_to_scanner, sphere_radius_mm))]
    sol, unpack, residual = min((refine(m, c0) for m, c0 in starts), key=lambda t: t[0].cost)
    # Trim: points more than 1 mm off the sphere at the first solution (a stray arc) are dropped,
    # and the fit is repeated from it.
    r_s1, t_s1, c1 = unpack(sol.x)
    far = np.abs(residual(sol.x)) > max(1.0, 3.0 * inlier_mm)
    if far.any() and (~far).sum() > 50:
        pts_s, pose_r, pose_t = pts_s[~far], pose_r[~far], pose_t[~far]
        sol, unpack, residual = refine(Pose(t_s1, r_s1), c1)
    cond = scaled_condition_number(sol.jac)
    if not np.isfinite(cond) or cond > max_condition:
        raise CalibrationError(f"scanner: the mount is not observable from these poses (condition number "
                               f"{cond:.3g} > {max_condition:g}); turn the scanner about several axes")
    res = residual(sol.x)
    keep = np.abs(res) < 3.0 * inlier_mm
    rms, worst = residual_stats(res[keep])
    if rms > max_rms_mm or keep.mean() < 0.8:
        raise CalibrationError(f"scanner: point-to-sphere RMS {rms:.3f} mm (limit {max_rms_mm}), "
                               f"{100 * keep.mean():.0f}% of arc points within {3 * inlier_mm:.1f} mm")
    r_s, t_s, c = unpack(sol.x)
    return ScannerFit(Pose(t_s, r_s), c,
                      FitReport(len(used), rms, worst, "mm", cond,
                                {"points": int(keep.sum()), "linear_condition_number": lin_cond,
                                 "rotation_spread_deg": spread,
                                 "linear_start": Pose(mount.position_mm, mount.rotation).to_list()}),
                      data_sha256(rot, trans, pts_s))
