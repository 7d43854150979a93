"""Cloud acquisition: raster sweeps of the eye-in-hand scanner over the object.

The scanner looks obliquely at the tip, so one heading leaves shadows behind tall
parts (the box on the pillow); the sweep runs every line in both headings. Lines lie
one strip apart, a strip being the part of the laser line the scanner sees on a level
surface at the sweep's height (:func:`line_footprint_mm`) less an overlap, so that
neighbouring lines leave no band between them.

A line refused by motion validation (a keep-out box, the object, joint limits) is
planned again before it is given up: reversed, shifted sideways, with the tool turned
about its axis, or in pieces around what blocks it; every candidate is validated with
the route to its start before the arm moves. Then the top surface the cloud has not
seen (:mod:`elastoprobe.controller.coverage`) gets lines of its own, once; what is
still unseen is reported with its area.

Points are mapped through the TCP pose at each profile's exposure into the base
frame, then into the object frame with the nominal placement.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import numpy as np
import trimesh

from .core.collision import ToolShape
from .core.errors import MotionRefused
from .core.geometry import Pose, probe_tcp_pose, rotvec_to_matrix, scan_points_base
from .coverage import SEEN_WITHIN_MM, TopSurface, seen_mask, top_surface, unseen_patches
from .probe import ProbeExecutor

UP = np.array([0.0, 0.0, 1.0])
TOP_GRID_MM = 1.0              # grid of the top surface the coverage is measured on


def line_footprint_mm(tcp_to_scanner: Pose, field_of_view_deg: float, max_range_mm: float, depth_mm: float,
                      tool_shapes: list[ToolShape], tip_radius_mm: float, samples: int = 256) -> tuple[float, float]:
    """Where the laser line falls on a level surface ``depth_mm`` below the tip, the tool
    pointing straight down: (lowest, highest) tool-x offset from the tip (mm) of the rays
    that reach it within range without passing through the tool itself.

    The scanner looks past the probe at the tip, so beyond the tip the probe and its tip
    sphere hide the line; the fan's edge and the range bound the other side. Of several
    unhidden runs of rays, the widest counts. Raises MotionRefused when no ray reaches the
    surface (the cell's scanner cannot sweep at this height).
    """
    half = np.radians(field_of_view_deg) / 2.0
    angles = np.linspace(-half, half, samples)
    o = tcp_to_scanner.position_mm
    dirs = np.column_stack([np.sin(angles), np.zeros(samples), np.cos(angles)]) @ tcp_to_scanner.rotation.T
    with np.errstate(divide="ignore", invalid="ignore"):
        rng = (depth_mm - o[2]) / dirs[:, 2]
    reach = (dirs[:, 2] > 1e-9) & (rng > 0.0) & (rng <= max_range_mm)
    # Points along each ray up to 0.5 mm short of the surface, 0.5 mm apart.
    steps = np.linspace(0.0, 1.0, int(np.ceil(np.nanmax(np.where(reach, rng, 0.0)) / 0.5)) + 2)
    along = np.where(reach, rng - 0.5, 0.0)[:, None] * steps[None, :]
    pts = o + along[:, :, None] * dirs[:, None, :]
    flat = pts.reshape(-1, 3)
    blocked = np.linalg.norm(flat, axis=1) < tip_radius_mm
    for shape in tool_shapes:
        to_local = shape.pose_in_tcp.inverse()
        if shape.signed_distance_local(to_local.apply(o[None, :]))[0] <= 0.0:
            continue            # the scanner's own housing: the rays start inside it
        blocked |= shape.signed_distance_local(to_local.apply(flat)) < 0.0
    clear = reach & ~blocked.reshape(samples, -1).any(axis=1)
    if not clear.any():
        raise MotionRefused(f"the scanner's line does not reach a surface {depth_mm:.0f} mm below the tip "
                            f"(field of view, range or the tool's own shadow)")
    # The widest run of consecutive clear rays.
    edges = np.diff(np.r_[0, clear.astype(int), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(stops - starts))
    x = (o + rng[:, None] * dirs)[starts[k]:stops[k], 0]
    return float(x.min()), float(x.max())


@dataclass(frozen=True)
class SweepSettings:
    """How to sweep (mm, degrees)."""

    spacing_mm: float                   # between profiles along a line (speed = spacing x scanner rate)
    height_above_mm: float              # the tip this far above the object's highest point
    footprint_mm: tuple[float, float]   # line_footprint_mm at height_above_mm: tool-x offsets seen
    max_tilt_deg: float = 90.0          # the top surface to cover: faces tilted at most this
    max_points: int = 200_000
    seed: int = 0
    margin_mm: float = 40.0             # lines run this far past the object; the outer ones lie this far outside
    # Of the footprint, the share next lines also see: the footprint is that of a level
    # surface at the top, and the line tilts off it on sloped faces.
    overlap: float = 0.1

    @property
    def strip_mm(self) -> float:
        lo, hi = self.footprint_mm
        return max((hi - lo) * (1.0 - self.overlap), self.spacing_mm)

    @property
    def seen_within_mm(self) -> float:
        """A surface point is seen when a cloud point lies this close: SEEN_WITHIN_MM, or, for
        profiles further apart than twice that, half their spacing (a point midway between two
        profiles is that far from both) and the 0.5 mm between samples along a profile."""
        return max(SEEN_WITHIN_MM, 0.5 * self.spacing_mm + 0.5)


@dataclass(frozen=True)
class SweepLine:
    """One straight scan at height ``z_mm`` along base ``axis`` (0: x, 1: y) from ``from_mm`` to
    ``to_mm``, at ``across_mm`` on the other horizontal axis. The tool points down with its x
    (the scanner's side) along ``heading`` (+1 or -1) times that other axis, so the laser line
    lies across the motion; ``turn_deg`` turns the tool about its own axis from there."""

    across_mm: float
    from_mm: float
    to_mm: float
    z_mm: float
    heading: int
    axis: int = 1
    turn_deg: float = 0.0

    def poses(self) -> tuple[Pose, Pose]:
        across = 1 - self.axis
        t = np.zeros(3)
        t[across] = float(self.heading)
        turn = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(self.turn_deg)]))
        out = []
        for along_mm in (self.from_mm, self.to_mm):
            p = np.array([0.0, 0.0, self.z_mm])
            p[self.axis], p[across] = along_mm, self.across_mm
            pose = probe_tcp_pose(p, UP, t, 90.0)
            out.append(Pose(pose.position_mm, pose.rotation @ turn))
        return out[0], out[1]

    @property
    def length_mm(self) -> float:
        return abs(self.to_mm - self.from_mm)

    def reversed(self) -> "SweepLine":
        return replace(self, from_mm=self.to_mm, to_mm=self.from_mm)

    def part(self, from_mm: float, to_mm: float) -> "SweepLine":
        return replace(self, from_mm=from_mm, to_mm=to_mm)

    def describe(self) -> str:
        return f"line at {'yx'[self.axis]}={self.across_mm:.0f} mm heading {self.heading:+d}"


def sweep_lines(bbox_min_mm: np.ndarray, bbox_max_mm: np.ndarray, tcp_height_mm: float,
                strip_mm: float, margin_mm: float = 40.0) -> list[SweepLine]:
    """Raster lines along base y over a base-frame bounding box, both headings.

    The outer lines lie ``margin_mm`` outside the box in x, the others evenly between, at
    most ``strip_mm`` apart; every line runs ``margin_mm`` past the box in y.
    """
    lo, hi = np.asarray(bbox_min_mm, float), np.asarray(bbox_max_mm, float)
    span = hi[0] - lo[0] + 2.0 * margin_mm
    xs = np.linspace(lo[0] - margin_mm, hi[0] + margin_mm, int(np.ceil(span / strip_mm - 1e-9)) + 1)
    lines = []
    for heading in (-1, 1):
        # Scanner toward the robot first, near to far; then the wrist turns over the
        # far side and the other heading comes back, ending with the scanner on the
        # side away from the robot's column.
        for i, x in enumerate(xs if heading < 0 else xs[::-1]):
            y0, y1 = lo[1] - margin_mm, hi[1] + margin_mm
            if i % 2:
                y0, y1 = y1, y0
            lines.append(SweepLine(float(x), float(y0), float(y1), float(tcp_height_mm), heading))
    return lines


def alternatives(line: SweepLine, strip_mm: float) -> Iterator[tuple[str, SweepLine]]:
    """Other ways to scan a refused line's strip, those that cover most of it first: (how, line).

    Reversed (another approach and joint path); shifted sideways by a quarter or half a
    strip; the tool turned about its axis by 30 or 60 deg (the scanner swings away from
    what it met, and the line crosses the strip at that angle, covering cos(turn) of its
    width); both together. Each also reversed. Splitting around an obstacle needs the
    validator: :func:`clear_pieces`.
    """
    yield "reversed", line.reversed()
    variants = []
    for shift in (0.0, -0.25, 0.25, -0.5, 0.5):
        for turn_deg in (0.0, 30.0, -30.0, 60.0, -60.0):
            if shift == 0.0 and turn_deg == 0.0:
                continue
            # The part of the strip (width 1) the moved line's laser still spans.
            half = 0.5 * np.cos(np.radians(turn_deg))
            covered = max(0.0, min(0.5, shift + half) - max(-0.5, shift - half))
            how = " and ".join(([f"shifted {shift * strip_mm:+.0f} mm"] if shift else [])
                               + ([f"turned {turn_deg:+.0f} deg"] if turn_deg else []))
            variants.append((-covered, abs(turn_deg), how,
                             replace(line, across_mm=line.across_mm + shift * strip_mm, turn_deg=turn_deg)))
    for _, _, how, moved in sorted(variants, key=lambda v: (v[0], v[1])):
        yield how, moved
        yield how + ", reversed", moved.reversed()


def clear_pieces(line: SweepLine, collision: Callable[[Pose, Pose], str | None], step_mm: float,
                 over_mm: tuple[float, float]) -> list[SweepLine]:
    """The parts of ``line`` (in its direction) whose path meets nothing, checked ``step_mm``
    at a time, that run at least a step within ``over_mm`` (the object's extent along the
    line). Empty when the whole line is clear (nothing to split around) or none of it is."""
    n = max(1, int(np.ceil(line.length_mm / step_mm)))
    ts = np.linspace(line.from_mm, line.to_mm, n + 1)
    clear = np.array([collision(*line.part(float(a), float(b)).poses()) is None for a, b in zip(ts[:-1], ts[1:])])
    if clear.all():
        return []
    edges = np.diff(np.r_[0, clear.astype(int), 0])
    pieces = [line.part(float(ts[a]), float(ts[b]))
              for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]
    lo, hi = over_mm
    return [p for p in pieces if min(hi, max(p.from_mm, p.to_mm)) - max(lo, min(p.from_mm, p.to_mm)) >= step_mm]


@dataclass
class SweepResult:
    """What a sweep gathered and what it could not."""

    points_mm: np.ndarray                   # object frame (N, 3)
    robot_s: float
    refused: list[str] = field(default_factory=list)      # lines given up, and why
    replanned: list[str] = field(default_factory=list)    # lines refused as planned, scanned another way
    lines: int = 0                                         # lines planned (raster and fill)
    fill_lines: int = 0                                    # of which planned for unseen surface
    top_mm2: float = 0.0                                   # the top surface to cover (area)
    unseen_mm2: float = 0.0                                # of it, no point within seen_within_mm
    seen_within_mm: float = 0.0
    unseen_where: list[dict] = field(default_factory=list)   # describe_unseen
    top: TopSurface | None = None                          # the surface scored (not journaled)

    @property
    def coverage(self) -> float:
        return 1.0 - self.unseen_mm2 / self.top_mm2 if self.top_mm2 > 0 else 1.0

    def outputs(self) -> dict:
        """JSON-able figures for the journal's cloud phase."""
        return {"lines": self.lines, "fill_lines": self.fill_lines, "lines_replanned": list(self.replanned),
                "lines_refused": list(self.refused), "top_surface_mm2": round(self.top_mm2, 1),
                "unseen_mm2": round(self.unseen_mm2, 1), "seen_within_mm": round(self.seen_within_mm, 3),
                "coverage": round(self.coverage, 5),
                "unseen_patches": self.unseen_where}


class _Sweeper:
    """Scans lines, planning refused ones again; collects the points in the object frame."""

    def __init__(self, executor: ProbeExecutor, settings: SweepSettings, bbox_mm: tuple[np.ndarray, np.ndarray]) -> None:
        self.ex = executor
        self.s = settings
        self.bbox_mm = bbox_mm          # the object's base-frame bounding box (min, max)
        self.speed_mm_s = settings.spacing_mm * executor.cell.scanner.rate_hz
        self.points: list[np.ndarray] = []
        self.refused: list[str] = []
        self.replanned: list[str] = []

    def collision(self, start: Pose, end: Pose) -> str | None:
        """What the straight path meets (geometry only; no joint path is planned), None if nothing."""
        check = getattr(self.ex.validator, "collision", None)
        return None if check is None else check(start, end)

    def _scan(self, line: SweepLine) -> np.ndarray:
        """Scan one line -> its object-frame points; MotionRefused (the arm not moved for it)
        if the line or the route to it is refused."""
        start, end = line.poses()
        hit = self.collision(start, end)
        if hit is not None:
            raise MotionRefused(f"collision: {hit}")
        scans, poses = self.ex.scan_while_moving(start, end, self.speed_mm_s)
        xz = np.stack([np.stack([s.x_mm, s.z_mm], axis=1) for s in scans]) if scans else np.zeros((0, 0, 2))
        cell = self.ex.cell
        pts = cell.base_to_object.inverse().apply(scan_points_base(xz, poses, cell.tcp_to_scanner))
        self.points.append(pts)
        return pts

    def scan(self, line: SweepLine) -> np.ndarray:
        """Scan ``line``, or the first of its alternatives that validates, or its clear pieces;
        returns the object-frame points gathered (none when all were refused)."""
        try:
            return self._scan(line)
        except MotionRefused as exc:
            why = str(exc)
        for how, other in alternatives(line, self.s.strip_mm):
            try:
                pts = self._scan(other)
            except MotionRefused:
                continue
            self.replanned.append(f"{line.describe()}: {why}; scanned {how}")
            return pts
        step_mm = max(10.0, 2.0 * self.s.spacing_mm)
        done, got = [], []
        extent = (float(self.bbox_mm[0][line.axis]), float(self.bbox_mm[1][line.axis]))
        for piece in clear_pieces(line, self.collision, step_mm, extent):
            for candidate in (piece, piece.reversed()):
                try:
                    got.append(self._scan(candidate))
                except MotionRefused:
                    continue
                done.append(f"{'xy'[line.axis]} {piece.from_mm:.0f}..{piece.to_mm:.0f} mm")
                break
        if done:
            self.replanned.append(f"{line.describe()}: {why}; scanned in {len(done)} piece(s) around "
                                  f"what blocks it ({', '.join(done)})")
            return np.vstack(got)
        self.refused.append(f"{line.describe()}: {why}")
        return np.zeros((0, 3))

    def object_points(self) -> np.ndarray:
        return np.vstack(self.points) if self.points else np.zeros((0, 3))


def acquire_cloud(executor: ProbeExecutor, object_mesh: trimesh.Trimesh, settings: SweepSettings) -> SweepResult:
    """Sweep the scanner over the object (``object_mesh``: the nominal surface, object frame,
    placed by ``executor.cell.base_to_object``) and report what it saw.

    Raises MotionRefused when no line at all could be scanned.
    """
    cell = executor.cell
    t0 = cell.clock.now_s()
    b2o = cell.base_to_object
    verts = b2o.apply(np.asarray(object_mesh.vertices, dtype=float))
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    tcp_z = float(hi[2]) + settings.height_above_mm
    sweeper = _Sweeper(executor, settings, (lo, hi))
    lines = sweep_lines(lo, hi, tcp_z, settings.strip_mm, settings.margin_mm)
    for line in lines:
        sweeper.scan(line)
    top = top_surface(object_mesh, TOP_GRID_MM, settings.max_tilt_deg)
    within = settings.seen_within_mm
    seen = seen_mask(top.points_mm, sweeper.object_points(), within)
    fill = fill_unseen(sweeper, top, seen, tcp_z, max_lines=len(lines) // 2)
    obj_pts = sweeper.object_points()
    if len(obj_pts) == 0:
        raise MotionRefused("no sweep line could be scanned: " + "; ".join(sweeper.refused))
    # What the sweep saw, before the plan's max_points thins the cloud it keeps.
    result = SweepResult(obj_pts, cell.clock.now_s() - t0, sweeper.refused, sweeper.replanned,
                         lines=len(lines) + fill, fill_lines=fill, top_mm2=top.total_mm2,
                         unseen_mm2=float(top.area_mm2[~seen].sum()), seen_within_mm=within,
                         unseen_where=describe_unseen(top, seen, within), top=top)
    if len(obj_pts) > settings.max_points:
        rng = np.random.default_rng(settings.seed)
        result.points_mm = obj_pts[np.sort(rng.choice(len(obj_pts), settings.max_points, replace=False))]
    return result


def min_patch_mm2(seen_within_mm: float) -> float:
    """An unseen patch smaller than the neighbourhood one cloud point vouches for (a square
    of twice ``seen_within_mm``) is a hole between points (dropouts), not a band a line missed."""
    return (2.0 * seen_within_mm) ** 2


def describe_unseen(top: TopSurface, seen: np.ndarray, seen_within_mm: float, max_patches: int = 10) -> list[dict]:
    """The largest unseen patches of the top surface: object-frame x and y ranges (mm) and
    area (mm^2); smaller holes between points summed in one last entry."""
    patches = unseen_patches(top, seen, min_patch_mm2(seen_within_mm))
    out = []
    for p in patches[:max_patches]:
        xy = top.points_mm[p, :2]
        out.append({"x_mm": [round(float(xy[:, 0].min()), 1), round(float(xy[:, 0].max()), 1)],
                    "y_mm": [round(float(xy[:, 1].min()), 1), round(float(xy[:, 1].max()), 1)],
                    "area_mm2": round(float(top.area_mm2[p].sum()), 1)})
    listed = sum(b["area_mm2"] for b in out)
    rest = float(top.area_mm2[~seen].sum()) - listed
    if rest > 0.05:
        out.append({"holes_and_smaller_patches_mm2": round(rest, 1)})
    return out


def unseen_of_cloud(top: TopSurface, points_mm: np.ndarray, seen_within_mm: float) -> dict:
    """The part of ``top`` (the sweep's top surface, :attr:`SweepResult.top`) a cloud (object
    frame, mm) has not seen, as the sweep reports it: ``unseen_mm2``, ``top_surface_mm2``,
    ``coverage`` and ``unseen_patches`` (:func:`describe_unseen`). The cloud phase scores the
    cloud it keeps with it: the sweep's own figures count what it saw, the table included,
    and a band the table removal drops would go unreported."""
    seen = seen_mask(top.points_mm, points_mm, seen_within_mm)
    unseen = float(top.area_mm2[~seen].sum())
    return {"top_surface_mm2": round(top.total_mm2, 1), "unseen_mm2": round(unseen, 1),
            "coverage": round(1.0 - unseen / top.total_mm2 if top.total_mm2 > 0 else 1.0, 5),
            "unseen_patches": describe_unseen(top, seen, seen_within_mm)}


def fill_unseen(sweeper: _Sweeper, top: TopSurface, seen: np.ndarray, tcp_z_mm: float, max_lines: int) -> int:
    """Scan lines over the patches of top surface the sweep has not seen, the largest patch
    first; returns how many lines were planned (at most ``max_lines``).

    The raster's laser lines lie across base x, so they meet slopes facing +-y at a grazing
    incidence that dark materials do not return; a patch of those (unseen surface whose
    normals lean more toward y than x) gets lines along x, whose laser lines lie across y,
    any other patch lines along y. Per patch: lines at most a strip apart across it,
    centred on it, as long as it plus the margin; the scanner first on the side the patch
    faces (away from the robot for a level patch), then, for what that left unseen (a
    wall between scanner and patch), on the other. ``seen`` is updated in place.
    """
    b2o = sweeper.ex.cell.base_to_object
    s = sweeper.s
    strip = s.strip_mm
    centre = 0.5 * (s.footprint_mm[0] + s.footprint_mm[1])     # of the footprint, in tool x
    normals = b2o.apply_vector(top.normals)
    faces_y = (np.abs(normals[:, 1]) > np.abs(normals[:, 0])) & (np.abs(normals[:, 1]) > np.sin(np.radians(15.0)))
    patches = [(p, axis) for axis, group in ((0, faces_y), (1, ~faces_y))
               for p in unseen_patches(top, seen | ~group, min_patch_mm2(s.seen_within_mm))]
    patches.sort(key=lambda item: -float(top.area_mm2[item[0]].sum()))
    planned = 0
    for patch, axis in patches:
        across = 1 - axis
        p = b2o.apply(top.points_mm[patch])
        a0, a1 = float(p[:, across].min()), float(p[:, across].max())
        n = int(np.ceil((a1 - a0) / strip - 1e-9))
        positions = [0.5 * (a0 + a1)] if n <= 1 else list(np.linspace(a0 + 0.5 * strip, a1 - 0.5 * strip, n))
        facing = float(np.sum(normals[patch, across] * top.area_mm2[patch]))
        headings = (1, -1) if facing >= 0.0 else (-1, 1)
        for at in positions:
            near = np.abs(p[:, across] - at) <= 0.5 * strip
            mine = patch[near]
            t0, t1 = float(p[near, axis].min()) - s.margin_mm, float(p[near, axis].max()) + s.margin_mm
            for heading in headings:
                if seen[mine].all() or planned >= max_lines:
                    break
                planned += 1
                got = sweeper.scan(SweepLine(at - heading * centre, t0, t1, tcp_z_mm, heading, axis))
                seen[mine] |= seen_mask(top.points_mm[mine], got, s.seen_within_mm)
    return planned
