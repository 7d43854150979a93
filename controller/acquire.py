"""Cloud acquisition: raster sweeps of the eye-in-hand scanner over the object (DESIGN §2).

The scanner looks obliquely at the tip, so one heading leaves shadows behind tall
parts (the box on the pillow); the sweep runs every line in both headings.
Points are mapped through the TCP pose at each profile's exposure into the base
frame, then into the object frame with the nominal placement.
"""
from __future__ import annotations

import numpy as np

from .geometry import Pose, probe_tcp_pose
from .probe import ProbeExecutor


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


def sweep_lines(bbox_min_mm: np.ndarray, bbox_max_mm: np.ndarray, tcp_height_mm: float,
                strip_mm: float, margin_mm: float = 40.0) -> list[tuple[Pose, Pose]]:
    """Raster lines (start, end) along base y over a base-frame bounding box, both headings.

    The tool points straight down; heading 0 has tool +x (the scanner side) along +x,
    heading 180 along -x. Lines are spaced by ``strip_mm`` along x.
    """
    lo, hi = np.asarray(bbox_min_mm, float), np.asarray(bbox_max_mm, float)
    xs = np.arange(lo[0] - margin_mm, hi[0] + margin_mm + 1e-9, strip_mm)
    lines = []
    for heading_t in (np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        # Scanner toward the robot first, near to far; then the wrist turns over the
        # far side and the other heading comes back, ending with the scanner on the
        # side away from the robot's column.
        for i, x in enumerate(xs if heading_t[0] < 0 else xs[::-1]):
            y0, y1 = lo[1] - margin_mm, hi[1] + margin_mm
            if i % 2:
                y0, y1 = y1, y0
            a = probe_tcp_pose(np.array([x, y0, tcp_height_mm]), np.array([0.0, 0.0, 1.0]), heading_t, 90.0)
            b = probe_tcp_pose(np.array([x, y1, tcp_height_mm]), np.array([0.0, 0.0, 1.0]), heading_t, 90.0)
            lines.append((a, b))
    return lines


def acquire_cloud(executor: ProbeExecutor, bbox_min_mm: np.ndarray, bbox_max_mm: np.ndarray,
                  spacing_mm: float, height_above_mm: float, strip_mm: float = 120.0,
                  max_points: int = 200_000, seed: int = 0) -> tuple[np.ndarray, float, list[str]]:
    """Sweep the scanner over the box and return (object-frame points (N,3) mm, robot seconds,
    the lines refused by motion validation and why).

    ``spacing_mm`` is the distance between profiles along a line (speed = spacing x rate).
    A line whose path or approach would collide (e.g. the scanner near the robot's
    column) is skipped: the other heading covers that strip.
    """
    from .errors import MotionRefused

    cell = executor.cell
    t0 = cell.clock.now_s()
    tcp_z = float(bbox_max_mm[2]) + height_above_mm
    speed = spacing_mm * cell.scanner.rate_hz
    pts = []
    skipped: list[str] = []
    for start, end in sweep_lines(bbox_min_mm, bbox_max_mm, tcp_z, strip_mm):
        try:
            scans, poses = executor.scan_while_moving(start, end, speed)
        except MotionRefused as exc:
            skipped.append(f"line at x={start.position_mm[0]:.0f} mm heading {start.rotation[0, 0]:+.0f}: {exc}")
            continue
        xz = np.stack([np.stack([s.x_mm, s.z_mm], axis=1) for s in scans]) if scans else np.zeros((0, 0, 2))
        pts.append(scan_points_base(xz, poses, cell.tcp_to_scanner))
    base_pts = np.vstack(pts) if pts else np.zeros((0, 3))
    obj_pts = cell.base_to_object.inverse().apply(base_pts)
    if len(obj_pts) > max_points:
        rng = np.random.default_rng(seed)
        obj_pts = obj_pts[np.sort(rng.choice(len(obj_pts), max_points, replace=False))]
    if len(obj_pts) == 0:
        raise MotionRefused("no sweep line could be scanned: " + "; ".join(skipped))
    return obj_pts, cell.clock.now_s() - t0, skipped
