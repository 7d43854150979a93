"""How much of an object's top surface a point cloud has seen.

The top surface is what a probe can reach from above: at each point of a regular grid
over the object (seen from straight above), the highest face of the nominal mesh,
kept where that face tilts no more than the plan's limit from the vertical. A point of
it counts as seen when a cloud point lies within ``within_mm`` of it. The grid is fixed
by the object, not by the cloud, so two clouds of one object are scored on the same
points (e.g. before and after sweeping a band again).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

SEEN_WITHIN_MM = 2.0          # a surface point with a cloud point this close counts as seen
MAX_GRID_POINTS = 400_000     # a large object gets a coarser grid, not an unbounded one


@dataclass(frozen=True)
class TopSurface:
    """Grid points on the top surface (N, 3) mm, their outward normals (N, 3), the area of the
    surface each stands for (N,) mm^2 (the grid cell's area over the face's cos(tilt)), and
    their cells (N, 2) on the grid of ``spacing_mm``."""

    points_mm: np.ndarray
    normals: np.ndarray
    area_mm2: np.ndarray
    cells: np.ndarray
    spacing_mm: float

    @property
    def total_mm2(self) -> float:
        return float(self.area_mm2.sum())


def grid_spacing_mm(mesh: trimesh.Trimesh, spacing_mm: float) -> float:
    """``spacing_mm``, widened so the grid over the mesh's footprint stays within MAX_GRID_POINTS."""
    extent = np.ptp(np.asarray(mesh.vertices)[:, :2], axis=0)
    cells = float(np.prod(extent / spacing_mm + 1.0))
    return float(spacing_mm * max(1.0, np.sqrt(cells / MAX_GRID_POINTS)))


def top_surface(mesh: trimesh.Trimesh, spacing_mm: float = 1.0, max_tilt_deg: float = 90.0) -> TopSurface:
    """The mesh's surface seen from straight above on a ``spacing_mm`` grid (widened for large
    meshes, see :func:`grid_spacing_mm`), where it tilts at most ``max_tilt_deg``.

    Each upward face is rasterised onto the grid cells whose centres it covers (seen from
    above) and the highest face wins per cell: a face hidden under another (the part of a
    pillow's top under a box standing on it) is not top surface.
    """
    s = grid_spacing_mm(mesh, spacing_mm)
    tris = np.asarray(mesh.triangles, dtype=float)
    normals = np.asarray(mesh.face_normals, dtype=float)
    up = np.flatnonzero(normals[:, 2] > 1e-9)
    tris, normals = tris[up], normals[up]
    lo = np.asarray(mesh.vertices, dtype=float)[:, :2].min(axis=0)
    # Cells whose centres lie inside each face's bounding box: (face, i, j) pairs.
    tmin, tmax = tris[:, :, :2].min(axis=1), tris[:, :, :2].max(axis=1)
    first = np.ceil((tmin - lo) / s - 0.5).astype(np.int64)
    last = np.floor((tmax - lo) / s - 0.5).astype(np.int64)
    span = np.maximum(last - first + 1, 0)
    count = span[:, 0] * span[:, 1]
    face = np.repeat(np.arange(len(tris)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    i = first[face, 0] + k // np.maximum(span[face, 1], 1)
    j = first[face, 1] + k % np.maximum(span[face, 1], 1)
    x = lo[0] + (i + 0.5) * s
    y = lo[1] + (j + 0.5) * s
    # Barycentric coordinates of the cell centres in each face's projection.
    a, b, c = tris[face, 0], tris[face, 1], tris[face, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-12
    det = np.where(ok, det, 1.0)
    wb = ((x - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (y - a[:, 1])) / det
    wc = ((b[:, 0] - a[:, 0]) * (y - a[:, 1]) - (x - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    wa = 1.0 - wb - wc
    eps = 1e-9
    inside = ok & (wa >= -eps) & (wb >= -eps) & (wc >= -eps)
    face, i, j, x, y = face[inside], i[inside], j[inside], x[inside], y[inside]
    z = wa[inside] * a[inside, 2] + wb[inside] * b[inside, 2] + wc[inside] * c[inside, 2]
    # The highest face per cell.
    cell = i * (int(j.max(initial=0)) + 1) + j
    order = np.lexsort((z, cell))
    last_of_cell = order[np.r_[cell[order][1:] != cell[order][:-1], True]]
    face, i, j = face[last_of_cell], i[last_of_cell], j[last_of_cell]
    x, y, z = x[last_of_cell], y[last_of_cell], z[last_of_cell]
    n = normals[face]
    keep = n[:, 2] >= np.cos(np.radians(max_tilt_deg)) - 1e-12
    return TopSurface(np.column_stack([x, y, z])[keep], n[keep], s * s / n[keep, 2],
                      np.column_stack([i, j])[keep], s)


def seen_mask(surface_mm: np.ndarray, cloud_mm: np.ndarray, within_mm: float = SEEN_WITHIN_MM) -> np.ndarray:
    """Which surface points (N, 3) have a cloud point (M, 3), same frame, within ``within_mm``."""
    cloud = np.asarray(cloud_mm, dtype=float).reshape(-1, 3)
    surface = np.asarray(surface_mm, dtype=float).reshape(-1, 3)
    if len(cloud) == 0 or len(surface) == 0:
        return np.zeros(len(surface), dtype=bool)
    dist, _ = cKDTree(cloud).query(surface, distance_upper_bound=within_mm)
    return np.isfinite(dist)


def unseen_patches(top: TopSurface, seen: np.ndarray, min_area_mm2: float = 0.0) -> list[np.ndarray]:
    """The unseen top surface as connected patches (cells touching at an edge or a corner):
    indices into ``top`` per patch of at least ``min_area_mm2``, the largest first."""
    idx = np.flatnonzero(~np.asarray(seen, dtype=bool))
    if idx.size == 0:
        return []
    ij = top.cells[idx]
    ij = ij - ij.min(axis=0)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
    of_point = labels[ij[:, 0], ij[:, 1]] - 1
    order = np.argsort(of_point, kind="stable")
    patches = np.split(idx[order], np.flatnonzero(np.diff(of_point[order])) + 1)
    patches = [p for p in patches if float(top.area_mm2[p].sum()) >= min_area_mm2]
    return sorted(patches, key=lambda p: -float(top.area_mm2[p].sum()))


def cloud_summary(cloud_outputs: dict) -> dict:
    """What ``status`` and the report say of a committed cloud (the journal's cloud phase
    outputs): points, and for a swept cloud the share of the top surface seen, the area
    left unseen (mm^2) and how many sweep lines were planned again or refused."""
    out = {"points": cloud_outputs.get("n_points")}
    sweep = cloud_outputs.get("sweep")
    if isinstance(sweep, dict):
        out.update(coverage=sweep.get("coverage"), unseen_mm2=sweep.get("unseen_mm2"),
                   top_surface_mm2=sweep.get("top_surface_mm2"), lines=sweep.get("lines"),
                   lines_replanned=len(sweep.get("lines_replanned", [])),
                   lines_refused=len(sweep.get("lines_refused", [])))
    return out


def describe_cloud(summary: dict) -> str:
    """One line of text for :func:`cloud_summary`."""
    text = f"{summary.get('points')} points"
    if summary.get("coverage") is not None:
        text += (f", {100.0 * summary['coverage']:.1f} % of the top surface seen ({summary['unseen_mm2']:.0f} mm^2 "
                 f"of {summary['top_surface_mm2']:.0f} unseen); {summary['lines']} sweep lines, "
                 f"{summary['lines_replanned']} planned again, {summary['lines_refused']} refused")
    return text
