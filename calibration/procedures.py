"""Calibration procedures: plan reachable poses, drive the cell, collect the data each solver needs.

Each ``collect_*`` works on any :class:`~elastoprobe.controller.core.devices.Cell` through a
:class:`~.driver.Rig` (validated moves, the controller's polling loop). Poses
the validator refuses (reach, joint limits, collisions, workspace) are skipped and
listed; the solver then judges whether what remains is enough and well spread.

Set-ups (docs/calibration.md):
- ft: the tool in free air, turned through tilts up to ~75 deg at several headings
  and rolls about one point; the F/T stream is tared once at the start, never between poses.
- tcp and scanner: a rigid reference sphere (radius known from its certificate) on
  the table, its centre roughly known (the cell's object placement, +-10 mm).
  tcp: touch-offs whose approach leans up to ~45 deg from the probe axis, from all
  sides; scanner: profiles with the laser plane 8..16 mm off the sphere's centre,
  the tool tilted up to ~30 deg at headings all round.
- object: raster sweeps of the scanner over the object along both base axes, mapped
  with the calibrated scanner mount, then mesh-to-cloud registration.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose, rotvec_to_matrix, scan_points_base
from elastoprobe.controller.toolhead import ProbeFault

from .driver import Rig, back_off, touch, try_reach
from .scanner_sphere import SphereProfile

DOWN = np.diag([1.0, -1.0, -1.0])      # tool z pointing down, tool x along base +x


def tool_rotation(tilt_deg: float, tilt_azimuth_deg: float, heading_deg: float) -> np.ndarray:
    """A tool turned ``heading_deg`` about its own axis from straight down, then tilted by
    ``tilt_deg`` about the horizontal axis perpendicular to azimuth ``tilt_azimuth_deg``."""
    az = np.radians(tilt_azimuth_deg)
    axis = np.array([-np.sin(az), np.cos(az), 0.0])
    return (rotvec_to_matrix(axis * np.radians(tilt_deg)) @ rotvec_to_matrix(np.array([0.0, 0.0, np.radians(heading_deg)]))
            @ DOWN)


@dataclass
class Collected:
    """What a procedure gathered, and what it had to skip (with the reasons)."""

    skipped: list[str] = field(default_factory=list)
    robot_time_s: float = 0.0


# ----------------------------------------------------------------------------------- F/T
FT_ORIENTATIONS = [(0, 0, 0), (0, 0, 90), (0, 0, 180), (40, 0, 0), (40, 90, 45), (40, 180, 90), (40, 270, 135),
                   (75, 0, 90), (75, 90, 0), (75, 180, 180), (75, 270, 270), (60, 45, 300), (60, 225, 30),
                   (20, 135, 200)]


@dataclass
class FTData(Collected):
    r_base_tcp: list[np.ndarray] = field(default_factory=list)
    force_n: list[np.ndarray] = field(default_factory=list)
    torque_nm: list[np.ndarray] = field(default_factory=list)


def collect_ft(rig: Rig, centre_mm: np.ndarray, settle_s: float = 0.5, average_s: float = 1.0) -> FTData:
    """Static F/T readings at spread orientations about ``centre_mm`` (TCP position, base frame)."""
    out = FTData()
    t0 = rig.cell.clock.now_s()
    neutral = Pose(np.asarray(centre_mm, float), DOWN)
    rig.head.travel_to(neutral)
    rig.head.tare()
    for tilt, az, heading in FT_ORIENTATIONS:
        target = Pose(np.asarray(centre_mm, float), tool_rotation(tilt, az, heading))
        if not try_reach(rig.head, target, via=neutral):
            out.skipped.append(f"ft pose tilt {tilt} az {az} heading {heading}: refused")
            continue
        rig.begin_step()
        f, t, _ = rig.head.still_wrench(settle_s, average_s)
        out.r_base_tcp.append(rig.head.pose().rotation)
        out.force_n.append(f)
        out.torque_nm.append(t)
    try_reach(rig.head, neutral)
    out.robot_time_s = rig.cell.clock.now_s() - t0
    return out


# ----------------------------------------------------------------------------------- tip
@dataclass
class TouchData(Collected):
    rotations: list[np.ndarray] = field(default_factory=list)
    positions_mm: list[np.ndarray] = field(default_factory=list)
    approach_dirs: list[np.ndarray] = field(default_factory=list)


def touch_plan(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(approach direction e, tool rotation) pairs: e from above at elevations 35..90 deg all
    round; the probe axis leaned 0..45 deg from e, always still pushing down-ish."""
    rng = np.random.default_rng(seed)
    plan = []
    for k in range(n * 4):
        if len(plan) >= n:
            break
        elev = np.radians(rng.uniform(35.0, 85.0))
        az = 2 * np.pi * (k + rng.uniform(0, 0.5)) / max(n, 1) * 1.618
        e = -np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        lean = np.radians([0.0, 25.0, 45.0][k % 3])
        perp = np.cross(e, rng.normal(size=3))
        perp /= np.linalg.norm(perp)
        d = rotvec_to_matrix(perp * lean) @ e
        if d[2] > -0.3:
            continue
        x = np.cross([0.0, 0.0, 1.0], d) if abs(d[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        x = np.cross(rotvec_to_matrix(d * rng.uniform(-np.pi, np.pi)) @ x, d)
        x /= np.linalg.norm(x)
        rot = np.column_stack([x, np.cross(d, x), d])
        plan.append((e, rot))
    return plan


def collect_touches(rig: Rig, centre_mm: np.ndarray, rho_mm: float, n: int = 18, seed: int = 0,
                    standoff_mm: float = 8.0) -> TouchData:
    """Touch-offs on the reference sphere (centre roughly ``centre_mm``; ``rho_mm`` = sphere + tip radius)."""
    out = TouchData()
    t0 = rig.cell.clock.now_s()
    c = np.asarray(centre_mm, dtype=float)
    for e, rot in touch_plan(n, seed):
        start = Pose(c - e * (rho_mm + standoff_mm), rot)
        try:
            rig.head.travel_to(start)
        except (MotionRefused, ProbeFault) as exc:
            out.skipped.append(f"touch from {np.round(e, 2).tolist()}: {exc}")
            continue
        rig.begin_step()
        try:
            hit = touch(rig.head, e, standoff_mm + 8.0, expected_mm=standoff_mm)
        except MotionRefused as exc:      # the touching path itself is not clear: next touch
            out.skipped.append(f"touch from {np.round(e, 2).tolist()}: {exc}")
            continue
        if hit is None:
            out.skipped.append(f"touch from {np.round(e, 2).tolist()}: no contact")
            back_off(rig.head, e, 1.0)
            continue
        out.rotations.append(hit.rotation)
        out.positions_mm.append(hit.position_mm)
        out.approach_dirs.append(e)
        back_off(rig.head, e, standoff_mm)
    out.robot_time_s = rig.cell.clock.now_s() - t0
    return out


# ----------------------------------------------------------------------------------- scanner
@dataclass
class SphereScans(Collected):
    profiles: list[SphereProfile] = field(default_factory=list)


def scan_plan(n: int, seed: int, sphere_radius_mm: float, tip_radius_mm: float,
              gap_mm: float = 15.0) -> list[tuple[Pose, np.ndarray]]:
    """(tool rotation as a Pose with zero position, sphere centre in the TCP frame) pairs."""
    rng = np.random.default_rng(seed)
    plan = []
    for k in range(n):
        tilt = [0.0, 15.0, 30.0][k % 3]
        rot = tool_rotation(tilt, rng.uniform(0, 360), 360.0 * k / n + rng.uniform(-10, 10))
        side = 1.0 if k % 2 == 0 else -1.0
        y_off = side * rng.uniform(8.0, 16.0)
        centre_tcp = np.array([rng.uniform(-12.0, 12.0), y_off,
                               sphere_radius_mm + tip_radius_mm + gap_mm + rng.uniform(0.0, 15.0)])
        plan.append((Pose(np.zeros(3), rot), centre_tcp))
    return plan


def collect_sphere_scans(rig: Rig, centre_mm: np.ndarray, sphere_radius_mm: float, tip_radius_mm: float,
                         n: int = 30, seed: int = 0, profiles_per_pose: int = 2) -> SphereScans:
    """Profiles of the reference sphere from ``n`` planned poses (refused ones skipped)."""
    out = SphereScans()
    t0 = rig.cell.clock.now_s()
    c = np.asarray(centre_mm, dtype=float)
    for rot_pose, centre_tcp in scan_plan(n, seed, sphere_radius_mm, tip_radius_mm):
        target = Pose(c - rot_pose.rotation @ centre_tcp, rot_pose.rotation)
        try:
            rig.head.travel_to(target)
        except (MotionRefused, ProbeFault) as exc:
            out.skipped.append(f"scan pose at {np.round(target.position_mm, 0).tolist()}: {exc}")
            continue
        rig.begin_step()
        rig.head.hold(0.05)
        scans, poses = rig.head.scan_burst(profiles_per_pose)
        for sc, p6 in zip(scans, poses):
            out.profiles.append(SphereProfile(Pose.from_list(p6), np.column_stack([sc.x_mm, sc.z_mm])))
    out.robot_time_s = rig.cell.clock.now_s() - t0
    return out


# ----------------------------------------------------------------------------------- object
def sweep_lines_both_axes(lo_mm: np.ndarray, hi_mm: np.ndarray, tcp_z_mm: float, strip_mm: float,
                          margin_mm: float = 40.0) -> list[tuple[Pose, Pose]]:
    """Raster lines over a base-frame box: along y (laser plane x-z) and along x (laser plane y-z),
    both headings each. One axis alone samples the walls facing along the travel only at the profile
    spacing: the walls parallel to the laser plane are never hit, so the object's position along
    the travel would be known only to about that spacing."""
    lo, hi = np.asarray(lo_mm, float), np.asarray(hi_mm, float)
    up = np.array([0.0, 0.0, 1.0])
    lines = []
    for along, across in ((1, 0), (0, 1)):
        for sign in (1.0, -1.0):
            t = np.zeros(3)
            t[across] = sign
            steps = np.arange(lo[across] - margin_mm, hi[across] + margin_mm + 1e-9, strip_mm)
            for i, s in enumerate(steps if sign > 0 else steps[::-1]):
                a, b = np.zeros(3), np.zeros(3)
                a[across] = b[across] = s
                a[along], b[along] = lo[along] - margin_mm, hi[along] + margin_mm
                if i % 2:
                    a, b = b, a
                a[2] = b[2] = tcp_z_mm
                lines.append((probe_tcp_pose(a, up, t, 90.0), probe_tcp_pose(b, up, t, 90.0)))
    return lines


@dataclass
class ObjectCloud(Collected):
    points_base_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def sweep_object(rig: Rig, lo_mm: np.ndarray, hi_mm: np.ndarray, tcp_to_scanner: Pose,
                 spacing_mm: float = 3.0, height_above_mm: float = 40.0, strip_mm: float = 120.0) -> ObjectCloud:
    """Scan the object's bounding box (base frame) in both raster directions; points mapped with
    ``tcp_to_scanner`` (in the frame of the TCP the arm reports). Refused lines are skipped."""
    out = ObjectCloud()
    t0 = rig.cell.clock.now_s()
    speed = spacing_mm * rig.cell.scanner.rate_hz
    pts = []
    for start, end in sweep_lines_both_axes(lo_mm, hi_mm, float(hi_mm[2]) + height_above_mm, strip_mm):
        try:
            scans, poses = rig.head.scan_while_moving(start, end, speed)
        except MotionRefused as exc:
            out.skipped.append(f"line {np.round(start.position_mm, 0).tolist()} -> "
                               f"{np.round(end.position_mm, 0).tolist()}: {exc}")
            continue
        if scans:
            xz = np.stack([np.stack([s.x_mm, s.z_mm], axis=1) for s in scans])
            pts.append(scan_points_base(xz, poses, tcp_to_scanner))
    out.points_base_mm = np.vstack(pts) if pts else np.zeros((0, 3))
    out.robot_time_s = rig.cell.clock.now_s() - t0
    return out
