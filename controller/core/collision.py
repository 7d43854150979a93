"""Motion validation against the cell: the tool's shapes (probe, F/T sensor, scanner,
flange) against the object mesh, the keep-out boxes and the workspace, along a whole
straight-line move and not only at its end (docs/design.md §5).

Frames and units: mm; ``base`` is the robot base, poses are ``base <- tcp``; tool
shapes are given in the TCP frame (+z from the flange toward the tip, the TCP at the
tip centre).

How it is exact enough and fast:
- Tool shapes are analytic (cylinder, box): their signed distance at any point is exact.
- The object mesh is sampled once, deterministically, into surface points (a barycentric
  grid, spacing ``mesh_spacing_mm``) held in a cKDTree with their face normals. Any
  surface point lies within ``r = spacing / sqrt(3)`` of a sample, so a shape's true
  distance to the mesh lies in [sampled - r, sampled]; a collision is reported when
  ``sampled - r < clearance`` (conservative: it never misses, it may flag up to r early).
- Each shape is covered by a few spheres; only spheres with a surface sample within
  reach are expanded to their nearby samples (ball queries), and only poses whose shape
  bounding box meets the mesh's are looked at.
- A shape wholly inside the object (no surface near it) is caught by the side of the
  nearest surface sample its centre lies on (the sample's outward face normal).
- Along a path, poses are sampled so that no point of any shape moves more than
  ``step_mm`` between samples; with ``step_mm <= 2 * clearance_mm`` a real intrusion
  between two samples is still within the clearance at one of them.
- A move from where the arm is that starts inside a keep-out box's clearance may leave
  it: it is refused only where it comes closer to that box than it started. The
  clearance is a margin, and an arm already in it (a force loop that pushed the tool
  sideways, a fault's unvalidated retract) must be able to move away; refusing every
  path from there left generated composite 1211's arm where it was for the rest of the
  night (1530 steps skipped).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .geometry import Pose, matrix_to_rotvec

# How much closer than its start a path leaving a keep-out's clearance may come (mm):
# rounding, not an allowance (a straight move along a box's face keeps its gap exactly).
LEAVING_TOLERANCE_MM = 1e-6


# ---------------------------------------------------------------------------------------
# Shapes


@dataclass(frozen=True)
class ToolShape:
    """Collision geometry carried by the arm, in the TCP frame (from the cell file).

    ``kind`` "cylinder": axis along the local z, centred at ``pose_in_tcp``'s origin,
    ``radius_mm`` and ``length_mm``. ``kind`` "box": centred, edges ``size_mm`` along the
    local x, y, z.
    """

    name: str
    kind: str
    pose_in_tcp: Pose
    radius_mm: float = 0.0
    length_mm: float = 0.0
    size_mm: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.kind == "cylinder":
            if self.radius_mm <= 0 or self.length_mm <= 0:
                raise ValueError(f"shape {self.name!r}: a cylinder needs radius_mm > 0 and length_mm > 0")
        elif self.kind == "box":
            if self.size_mm is None or min(self.size_mm) <= 0:
                raise ValueError(f"shape {self.name!r}: a box needs three positive size_mm")
        else:
            raise ValueError(f"shape {self.name!r}: kind must be 'cylinder' or 'box', not {self.kind!r}")

    def half_extents_mm(self) -> np.ndarray:
        """Half sizes of the shape's own bounding box along its local x, y, z (mm)."""
        if self.kind == "cylinder":
            return np.array([self.radius_mm, self.radius_mm, self.length_mm / 2.0])
        return np.asarray(self.size_mm, dtype=float) / 2.0

    def signed_distance_local(self, points_mm: np.ndarray) -> np.ndarray:
        """Exact signed distance (mm, negative inside) of points (N, 3) in the shape frame."""
        p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        if self.kind == "cylinder":
            q = np.stack([np.hypot(p[:, 0], p[:, 1]) - self.radius_mm,
                          np.abs(p[:, 2]) - self.length_mm / 2.0], axis=1)
        else:
            q = np.abs(p) - self.half_extents_mm()
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(np.max(q, axis=1), 0.0)
        return outside + inside

    def cover_spheres_local(self, max_cell_mm: float = 30.0) -> tuple[np.ndarray, float]:
        """Centres (K, 3) in the shape frame and one radius (mm) of spheres covering the shape.

        The shape's bounding box is cut into near-cubic cells of side about its smallest
        dimension (at most ``max_cell_mm``); cells that miss the shape are dropped.
        """
        half = self.half_extents_mm()
        side = float(np.clip(2.0 * half.min(), 1.0, max_cell_mm))
        counts = np.maximum(1, np.ceil(2.0 * half / side - 1e-9)).astype(int)
        cell = 2.0 * half / counts
        axes = [(-half[i] + cell[i] * (np.arange(counts[i]) + 0.5)) for i in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        radius = float(np.linalg.norm(cell) / 2.0)
        keep = self.signed_distance_local(centres) <= radius
        return centres[keep], radius

    def surface_points_local(self, spacing_mm: float = 2.0) -> tuple[np.ndarray, float]:
        """Points (M, 3) on the shape's surface at most ``spacing_mm`` apart, and the
        covering radius (mm): every surface point lies within it of a sample."""
        if self.kind == "cylinder":
            r, half_len = self.radius_mm, self.length_mm / 2.0
            n_around = max(8, math.ceil(2.0 * math.pi * r / spacing_mm))
            n_along = max(1, math.ceil(2.0 * half_len / spacing_mm))
            ang = np.linspace(0.0, 2.0 * math.pi, n_around, endpoint=False)
            zs = np.linspace(-half_len, half_len, n_along + 1)
            side = np.stack([np.repeat(r * np.cos(ang)[None], zs.size, 0),
                             np.repeat(r * np.sin(ang)[None], zs.size, 0),
                             np.repeat(zs[:, None], ang.size, 1)], axis=-1).reshape(-1, 3)
            rings = []
            for rr in np.arange(spacing_mm, r, spacing_mm):
                n = max(6, math.ceil(2.0 * math.pi * rr / spacing_mm))
                a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
                rings.append(np.stack([rr * np.cos(a), rr * np.sin(a)], axis=1))
            disc = np.vstack([np.zeros((1, 2)), *rings]) if rings else np.zeros((1, 2))
            caps = np.vstack([np.column_stack([disc, np.full(len(disc), z)]) for z in (-half_len, half_len)])
            chord = max(2.0 * math.pi * r / n_around, 2.0 * half_len / n_along)
            return np.vstack([side, caps]), max(chord, spacing_mm)
        half = self.half_extents_mm()
        pts = []
        for axis in range(3):
            others = [i for i in range(3) if i != axis]
            grids = [np.linspace(-half[i], half[i], max(1, math.ceil(2 * half[i] / spacing_mm)) + 1)
                     for i in others]
            g = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 2)
            for sign in (-1.0, 1.0):
                face = np.empty((len(g), 3))
                face[:, others[0]], face[:, others[1]], face[:, axis] = g[:, 0], g[:, 1], sign * half[axis]
                pts.append(face)
        return np.vstack(pts), spacing_mm


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in the base frame (mm): a keep-out volume or the workspace."""

    name: str
    min_mm: np.ndarray
    max_mm: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "min_mm", np.asarray(self.min_mm, dtype=float).reshape(3))
        object.__setattr__(self, "max_mm", np.asarray(self.max_mm, dtype=float).reshape(3))
        if np.any(self.min_mm >= self.max_mm):
            raise ValueError(f"box {self.name!r}: min_mm must be below max_mm on every axis")

    def signed_distance(self, points_mm: np.ndarray) -> np.ndarray:
        """Exact signed distance (mm, negative inside) of base-frame points (N, 3)."""
        p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        centre, half = (self.min_mm + self.max_mm) / 2.0, (self.max_mm - self.min_mm) / 2.0
        q = np.abs(p - centre) - half
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(np.max(q, axis=1), 0.0)


@dataclass(frozen=True)
class Collision:
    """One problem found on a move: ``shape`` (a tool shape or "tcp") meets ``obstacle``
    ("object", a keep-out box's name, or "workspace") first at ``at_fraction`` of the
    path (0 for a single pose). ``distance_mm``: the smallest distance found there
    (negative = penetration / outside the workspace by that much)."""

    shape: str
    obstacle: str
    at_fraction: float
    distance_mm: float
    message: str


# ---------------------------------------------------------------------------------------
# Mesh sampling


def _divisions(mesh: trimesh.Trimesh, spacing_mm: float) -> np.ndarray:
    tris = np.asarray(mesh.triangles, dtype=float)
    edges = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2).max(axis=1)
    return np.maximum(1, np.ceil(edges / spacing_mm - 1e-9)).astype(np.int64)


def mesh_spacing_for(mesh: trimesh.Trimesh, spacing_mm: float, max_samples: int) -> float:
    """The smallest spacing >= ``spacing_mm`` whose sample count stays under ``max_samples``
    (a large object is sampled more coarsely, and its checks are more conservative)."""
    spacing = float(spacing_mm)
    for _ in range(60):
        n = _divisions(mesh, spacing)
        count = int(np.sum(np.where(n == 1, 0, (n + 1) * (n + 2) // 2))) + len(mesh.vertices)
        if count <= max_samples:
            return spacing
        spacing *= 1.15
    return spacing


def sample_mesh_surface(mesh: trimesh.Trimesh, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic surface samples (N, 3) and outward normals (N, 3).

    Each triangle gets a barycentric grid with ``ceil(longest edge / spacing)``
    divisions per edge, so every point of the surface lies within spacing / sqrt(3) of
    a sample. Triangles already smaller than the spacing contribute their vertices once
    (with the vertex normal); larger ones their grid (points on shared edges repeat,
    which costs a little memory and nothing else).
    """
    tris = np.asarray(mesh.triangles, dtype=float)
    normals = np.asarray(mesh.face_normals, dtype=float)
    divisions = _divisions(mesh, spacing_mm)
    small = np.nonzero(divisions == 1)[0]
    vertex_ids = np.unique(np.asarray(mesh.faces)[small].ravel())
    points = [np.asarray(mesh.vertices, dtype=float)[vertex_ids]]
    point_normals = [np.asarray(mesh.vertex_normals, dtype=float)[vertex_ids]]
    for n in np.unique(divisions[divisions > 1]):
        idx = np.nonzero(divisions == n)[0]
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j) <= n
        w = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], axis=1) / n      # (G, 3)
        points.append(np.einsum("gk,tkc->tgc", w, tris[idx]).reshape(-1, 3))
        point_normals.append(np.repeat(normals[idx], w.shape[0], axis=0))
    return np.vstack(points), np.vstack(point_normals)


# ---------------------------------------------------------------------------------------
# The checker


@dataclass
class _PreparedShape:
    shape: ToolShape
    rot_local: np.ndarray          # tcp <- shape rotation
    centre_local: np.ndarray       # shape centre in the tcp frame (mm)
    half: np.ndarray               # half extents in the shape frame
    spheres_local: np.ndarray      # (K, 3) cover-sphere centres in the shape frame
    sphere_radius_mm: float
    surface_local: np.ndarray      # (M, 3) surface samples in the shape frame
    surface_cover_mm: float
    reach_mm: float = field(default=0.0)   # farthest shape point from the TCP (mm)


class SceneChecker:
    """Validates TCP poses and straight moves against the object, keep-outs and workspace.

    ``object_mesh_base``: the object's mesh in the base frame (None: no object check).
    ``clearance_mm``: the smallest allowed gap to the object and keep-outs. The workspace
    is a hard boundary: the TCP and every shape must lie inside it (no clearance).
    ``mesh_spacing_mm``: surface sampling of the mesh (see the module doc), coarsened
    if the mesh would need more than ``max_mesh_samples`` samples.
    ``tip_zone_radius_mm``: lateral radius around the tool axis of the zone near the tip
    that ``ignore_tip_mm`` exempts.
    """

    def __init__(self, tool_shapes: list[ToolShape], object_mesh_base: trimesh.Trimesh | None,
                 keep_out: list[Box], workspace: Box, clearance_mm: float = 2.0,
                 mesh_spacing_mm: float = 1.5, tip_zone_radius_mm: float = 20.0,
                 max_mesh_samples: int = 600_000) -> None:
        if clearance_mm < 0:
            raise ValueError("clearance_mm must be >= 0")
        self.clearance_mm = float(clearance_mm)
        self.keep_out = list(keep_out)
        self.workspace = workspace
        self.tip_zone_radius_mm = float(tip_zone_radius_mm)
        self._shapes = [self._prepare(s) for s in tool_shapes]
        self._reach_mm = max([s.reach_mm for s in self._shapes], default=0.0)
        self._tree: cKDTree | None = None
        if object_mesh_base is not None and len(object_mesh_base.faces):
            mesh_spacing_mm = mesh_spacing_for(object_mesh_base, mesh_spacing_mm, max_mesh_samples)
            pts, nrm = sample_mesh_surface(object_mesh_base, mesh_spacing_mm)
            self._mesh_points, self._mesh_normals = pts, nrm
            self._tree = cKDTree(pts)
            self._mesh_spacing_mm = float(mesh_spacing_mm)
            self._mesh_cover_mm = mesh_spacing_mm / math.sqrt(3.0)
            self._mesh_min, self._mesh_max = pts.min(axis=0), pts.max(axis=0)

    @staticmethod
    def _prepare(shape: ToolShape) -> _PreparedShape:
        spheres, radius = shape.cover_spheres_local()
        surface, cover = shape.surface_points_local()
        local_pts = shape.pose_in_tcp.apply(surface)
        return _PreparedShape(shape=shape, rot_local=shape.pose_in_tcp.rotation,
                              centre_local=shape.pose_in_tcp.position_mm, half=shape.half_extents_mm(),
                              spheres_local=spheres, sphere_radius_mm=radius, surface_local=surface,
                              surface_cover_mm=cover,
                              reach_mm=float(np.linalg.norm(local_pts, axis=1).max()))

    @property
    def mesh_sample_count(self) -> int:
        return 0 if self._tree is None else int(self._tree.n)

    @property
    def mesh_spacing_mm(self) -> float | None:
        """The mesh sampling in use (None without an object); checks err by up to spacing / sqrt(3)."""
        return None if self._tree is None else self._mesh_spacing_mm

    # -- public ---------------------------------------------------------------------------
    def check_pose(self, tcp_pose: Pose, ignore_tip_mm: float = 0.0) -> list[Collision]:
        """Everything the tool at ``tcp_pose`` (base <- tcp) would hit; [] when clear."""
        return self._check(tcp_pose.position_mm[None], tcp_pose.rotation[None], np.zeros(1), ignore_tip_mm)

    def check_path(self, start: Pose, end: Pose, step_mm: float = 2.0, ignore_tip_mm: float = 0.0,
                   leaving: bool = False) -> list[Collision]:
        """Everything the tool hits along the straight move start -> end (positions
        linear, rotation geodesic, as :func:`geometry.interpolate_pose`), the first
        occurrence per (shape, obstacle), ordered along the path; [] when clear.
        Poses are sampled so no point of the tool moves more than ``step_mm`` between them.
        ``leaving``: ``start`` is where the arm is, and a start inside a keep-out's clearance
        may be left (see the module docstring); planning from poses the arm is not at
        leaves it False, so no plan starts inside a margin it could not get into."""
        if step_mm <= 0:
            raise ValueError("step_mm must be positive")
        rel = matrix_to_rotvec(start.rotation.T @ end.rotation)
        angle = float(np.linalg.norm(rel))
        dist = float(np.linalg.norm(end.position_mm - start.position_mm))
        n = max(1, math.ceil(max(dist, angle * self._reach_mm) / step_mm - 1e-9))
        fractions = np.linspace(0.0, 1.0, n + 1)
        positions = start.position_mm + fractions[:, None] * (end.position_mm - start.position_mm)
        rotations = start.rotation @ _axis_angle_matrices(rel, fractions)
        return self._check(positions, rotations, fractions, ignore_tip_mm, leaving)

    # -- internals ------------------------------------------------------------------------
    def _check(self, positions: np.ndarray, rotations: np.ndarray, fractions: np.ndarray,
               ignore_tip_mm: float, leaving: bool = False) -> list[Collision]:
        found: dict[tuple[str, str], Collision] = {}

        def report(shape: str, obstacle: str, k: int, distance_mm: float, message: str) -> None:
            key = (shape, obstacle)
            if key not in found or fractions[k] < found[key].at_fraction:
                found[key] = Collision(shape, obstacle, float(fractions[k]), float(distance_mm), message)

        self._check_tcp(positions, rotations, ignore_tip_mm, report, leaving)
        for prep in self._shapes:
            rot = rotations @ prep.rot_local                                 # (P, 3, 3) base <- shape
            centre = positions + rotations @ prep.centre_local              # (P, 3)
            half_ext = self._aabb_half_extents(prep, rot)                   # (P, 3)
            lo, hi = centre - half_ext, centre + half_ext
            self._check_workspace(prep, lo, hi, report)
            for box in self.keep_out:
                self._check_keep_out(prep, box, rot, centre, lo, hi, report, leaving)
            if self._tree is not None:
                self._check_object(prep, rot, centre, lo, hi, positions, rotations, ignore_tip_mm, report)
        return sorted(found.values(), key=lambda c: (c.at_fraction, c.shape, c.obstacle))

    @staticmethod
    def _aabb_half_extents(prep: _PreparedShape, rot: np.ndarray) -> np.ndarray:
        """Exact half extents (P, 3) of the shape's axis-aligned bounding box in the base frame."""
        if prep.shape.kind == "cylinder":
            axis = rot[:, :, 2]
            return (np.abs(axis) * prep.half[2]
                    + prep.shape.radius_mm * np.sqrt(np.clip(1.0 - axis * axis, 0.0, None)))
        return np.abs(rot) @ prep.half

    def _nearest_side(self, points: np.ndarray, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the sampled surface and which side of it each point is on.

        Near an edge the nearest samples belong to both faces and a single sample's
        normal can say "inside" for a point above the other face by a hair; among the
        samples as near as the nearest (within one spacing), the face the point is most
        clearly off decides.
        """
        assert self._tree is not None
        dist, idx = self._tree.query(points, k=k)
        diff = points[:, None, :] - self._mesh_points[idx]
        side = np.einsum("pkc,pkc->pk", diff, self._mesh_normals[idx])
        candidate = dist <= dist[:, :1] + self._mesh_spacing_mm
        score = np.where(candidate, np.abs(side), -1.0)
        pick = np.argmax(score, axis=1)
        rows = np.arange(len(points))
        return dist[:, 0], side[rows, pick]

    def _keep_out_limit_mm(self, start_gap_mm: float, leaving: bool) -> float:
        """The smallest gap (mm) to a keep-out box a path may come to: the clearance; for a
        path (``leaving``) that starts inside the clearance, the gap it starts with (it may
        move away or along, never closer). The gap may be below zero: a shape's sampled
        distance is conservative by its surface cover, and wherever the arm is, it got there,
        so moving away from it is the one safe direction."""
        if leaving and start_gap_mm < self.clearance_mm:
            return start_gap_mm - LEAVING_TOLERANCE_MM
        return self.clearance_mm

    def _check_tcp(self, positions, rotations, ignore_tip_mm, report, leaving: bool = False) -> None:
        ws = self.workspace.signed_distance(positions)
        out = np.nonzero(ws > 0)[0]
        if out.size:
            k = int(out[0])
            report("tcp", "workspace", k, -ws[k],
                   f"TCP {np.round(positions[k], 1).tolist()} mm is {ws[k]:.1f} mm outside the workspace")
        for box in self.keep_out:
            d = box.signed_distance(positions)
            bad = np.nonzero(d < self._keep_out_limit_mm(float(d[0]), leaving))[0]
            if bad.size:
                k = int(bad[0])
                report("tcp", box.name, k, d[k], f"TCP is {d[k]:.1f} mm from keep-out box {box.name!r} "
                       f"(clearance {self.clearance_mm} mm)")
        if self._tree is not None and ignore_tip_mm <= 0.0:
            dist, side = self._nearest_side(positions)
            signed = np.where(side < 0, -dist, dist - self._mesh_cover_mm)
            bad = np.nonzero(signed < self.clearance_mm)[0]
            if bad.size:
                k = int(bad[0])
                report("tcp", "object", k, signed[k],
                       f"TCP is {signed[k]:.1f} mm from the object (clearance {self.clearance_mm} mm, "
                       f"no tip allowance)")

    def _check_workspace(self, prep, lo, hi, report) -> None:
        ws = self.workspace
        excess = np.maximum(np.max(ws.min_mm - lo, axis=1), np.max(hi - ws.max_mm, axis=1))
        out = np.nonzero(excess > 1e-9)[0]
        if out.size:
            k = int(out[0])
            report(prep.shape.name, "workspace", k, -excess[k],
                   f"{prep.shape.name} sticks {excess[k]:.1f} mm out of the workspace")

    def _check_keep_out(self, prep, box: Box, rot, centre, lo, hi, report, leaving: bool = False) -> None:
        c = self.clearance_mm
        near = np.nonzero(np.all(lo <= box.max_mm + c, axis=1) & np.all(hi >= box.min_mm - c, axis=1))[0]

        def gap(k: int) -> tuple[float, float, bool]:
            pts = prep.surface_local @ rot[k].T + centre[k]
            d_min = float(box.signed_distance(pts).min())
            # A box smaller than the shape can sit wholly inside it: test its centre too.
            box_centre_local = rot[k].T @ ((box.min_mm + box.max_mm) / 2.0 - centre[k])
            inside = prep.shape.signed_distance_local(box_centre_local[None])[0] <= 0
            return d_min, d_min - prep.surface_cover_mm, bool(inside)

        limit = c
        for k in near:
            d_min, gap_k, inside = gap(int(k))
            if k == 0 and not inside:           # the start: a path may leave the clearance it is in
                limit = self._keep_out_limit_mm(gap_k, leaving)
            if gap_k < limit or inside:
                report(prep.shape.name, box.name, int(k), min(d_min, 0.0) if inside else d_min,
                       f"{prep.shape.name} comes {d_min:.1f} mm from keep-out box {box.name!r} "
                       f"(clearance {c} mm)")
                return

    def _in_tip_zone(self, points_base: np.ndarray, position: np.ndarray, rotation: np.ndarray,
                     ignore_tip_mm: float) -> np.ndarray:
        """Mask of base-frame points in the exempt zone: within ``ignore_tip_mm`` behind
        the tip along the tool axis (tcp z > -ignore) and near the axis."""
        local = (points_base - position) @ rotation
        return (local[:, 2] > -ignore_tip_mm) & (np.hypot(local[:, 0], local[:, 1]) < self.tip_zone_radius_mm)

    def _check_object(self, prep, rot, centre, lo, hi, positions, rotations, ignore_tip_mm, report) -> None:
        c, r_mesh = self.clearance_mm, self._mesh_cover_mm
        reach = prep.sphere_radius_mm + c + r_mesh
        margin = c + r_mesh
        near = np.nonzero(np.all(lo <= self._mesh_max + margin, axis=1)
                          & np.all(hi >= self._mesh_min - margin, axis=1))[0]
        if near.size == 0:
            return
        # Cover spheres of the candidate poses, in the base frame: (len(near), K, 3).
        spheres = np.einsum("pij,kj->pki", rot[near], prep.spheres_local) + centre[near][:, None, :]
        dist, _ = self._tree.query(spheres.reshape(-1, 3), distance_upper_bound=reach)
        hit = np.isfinite(dist).reshape(len(near), -1)
        # The shape's centre, for the "wholly inside" case.
        c_dist, c_side = self._nearest_side(centre[near])
        for row, k in enumerate(near):
            k = int(k)
            use_tip = ignore_tip_mm > 0.0
            # Only trusted clearly below the surface: near an edge the nearest sample's
            # normal can belong to the other face, and there the surface test decides.
            if c_side[row] < 0 and c_dist[row] > self._mesh_spacing_mm and not (use_tip and self._in_tip_zone(centre[k][None], positions[k], rotations[k],
                                                                        ignore_tip_mm)[0]):
                report(prep.shape.name, "object", k, -float(c_dist[row]),
                       f"{prep.shape.name} is inside the object ({c_dist[row]:.1f} mm below its surface)")
                return
            if not hit[row].any():
                continue
            lists = self._tree.query_ball_point(spheres[row][hit[row]], reach, return_sorted=False)
            idx = np.unique(np.concatenate([np.asarray(l, dtype=np.int64) for l in lists]))
            pts = self._mesh_points[idx]
            if use_tip:
                pts = pts[~self._in_tip_zone(pts, positions[k], rotations[k], ignore_tip_mm)]
                if pts.shape[0] == 0:
                    continue
            local = (pts - centre[k]) @ rot[k]
            d_min = float(prep.shape.signed_distance_local(local).min())
            if d_min - r_mesh < c:
                what = "penetrates the object by" if d_min < 0 else "comes within"
                report(prep.shape.name, "object", k, d_min,
                       f"{prep.shape.name} {what} {abs(d_min):.1f} mm of the object surface "
                       f"(clearance {c} mm, sampling +-{r_mesh:.2f} mm)")
                return


def _axis_angle_matrices(rotvec_rad: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Rotation matrices (P, 3, 3) of ``fraction * rotvec`` (Rodrigues, vectorised)."""
    theta = float(np.linalg.norm(rotvec_rad))
    out = np.broadcast_to(np.eye(3), (fractions.size, 3, 3)).copy()
    if theta < 1e-12:
        return out
    k_axis = np.asarray(rotvec_rad, dtype=float) / theta
    k = np.array([[0.0, -k_axis[2], k_axis[1]], [k_axis[2], 0.0, -k_axis[0]], [-k_axis[1], k_axis[0], 0.0]])
    angles = fractions * theta
    return out + np.sin(angles)[:, None, None] * k + (1.0 - np.cos(angles))[:, None, None] * (k @ k)


def shapes_from_cell(tool_spec) -> list[ToolShape]:  # noqa: ANN001 — a config.ToolSpec
    """ToolShapes of a cell file's ``tool.shapes`` (config.ToolShapeSpec entries)."""
    return [ToolShape(name=s.name, kind=s.kind, pose_in_tcp=s.pose.pose(), radius_mm=s.radius_mm,
                      length_mm=s.length_mm, size_mm=None if s.size_mm is None else tuple(s.size_mm))
            for s in tool_spec.shapes]


def boxes_from_cell(limits_spec) -> tuple[Box, list[Box]]:  # noqa: ANN001 — a config.LimitsSpec
    """(workspace, keep-out boxes) of a cell file's ``limits``."""
    ws = limits_spec.workspace
    return (Box("workspace", np.array(ws.min_mm), np.array(ws.max_mm)),
            [Box(b.name, np.array(b.min_mm), np.array(b.max_mm)) for b in limits_spec.keep_out])
