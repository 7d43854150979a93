"""The object's true top surface, sampled at a fixed density: the reference maps are scored on.

A map is scored on what the object IS, not on the points a cell happened to scan: the
surface seen from above (the first hit of a vertical ray coming down), where its normal is
within the plan's tilt limit of +z (what the probe can press). Sampling:

- a square grid of vertical rays at the centres of ``spacing_mm`` cells, anchored to whole
  millimetres (x = floor(x_min) + (i + 1/2) spacing), over the mesh's bounding box: the
  same points for every session, whatever its cloud;
- per ray the highest face it crosses (exact for the triangle mesh: each grid column
  is cut once with the plane x = const, :class:`~elastoprobe.sim.raycast.PlaneSlicer`);
  kept when that face's normal is within ``max_tilt_deg`` of +z;
- each point stands for ``spacing^2 / n_z`` mm^2 of surface (its cell's projected area over
  the cosine of the tilt, taken as at least cos 85 deg), so area-weighted statistics are
  area-uniform on the surface (the grid is uniform per projected area; the weights undo
  the slope).

With the default 1 mm spacing a point stands for 1 to 1/cos(tilt) mm^2: one point per
projected square millimetre. Labels are the painted faces' (exact, no nearest-point
search); normals the object's own (analytic where it has them, e.g. the ball).

Frames and units: the object frame, mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .raycast import PlaneSlicer

DEFAULT_SPACING_MM = 1.0
MIN_COS_TILT = math.cos(math.radians(85.0))


@dataclass(frozen=True)
class TopSurface:
    """Samples of the true top: ``points_mm`` (P,3), outward ``normals`` (P,3), true region
    ``labels`` (P,), ``area_mm2`` (P,) the surface each stands for; the grid ``spacing_mm``
    and the tilt limit they were taken with."""

    points_mm: np.ndarray
    normals: np.ndarray
    labels: np.ndarray
    area_mm2: np.ndarray
    spacing_mm: float
    max_tilt_deg: float

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])

    @property
    def total_area_mm2(self) -> float:
        return float(self.area_mm2.sum())

    def subset(self, keep: np.ndarray) -> "TopSurface":
        """The samples where ``keep`` (P,) holds."""
        k = np.asarray(keep, dtype=bool)
        return TopSurface(self.points_mm[k], self.normals[k], self.labels[k], self.area_mm2[k], self.spacing_mm,
                          self.max_tilt_deg)


def highest_hits(slicer: PlaneSlicer, x_mm: float, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertical rays coming down at (x, y_j): the height z (J,) of the highest crossing and its
    face (J,) (-1 and NaN where a ray misses)."""
    z_out = np.full(y_mm.shape[0], np.nan)
    face_out = np.full(y_mm.shape[0], -1, dtype=np.int64)
    cut = slicer.cut(np.array([x_mm, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    if cut.p1.shape[0] == 0 or y_mm.size == 0:
        return z_out, face_out
    y1, y2, z1, z2 = cut.p1[:, 1], cut.p2[:, 1], cut.p1[:, 2], cut.p2[:, 2]
    dy = y2 - y1
    slanted = np.abs(dy) > 1e-12        # a vertical segment (a wall face seen edge-on) holds no ray
    y1, y2, z1, z2, dy, faces = y1[slanted], y2[slanted], z1[slanted], z2[slanted], dy[slanted], cut.face[slanted]
    y0 = float(y_mm[0])
    step = float(y_mm[1] - y_mm[0]) if y_mm.size > 1 else 1.0
    first = np.maximum(np.ceil((np.minimum(y1, y2) - y0) / step - 1e-12).astype(np.int64), 0)
    last = np.minimum(np.floor((np.maximum(y1, y2) - y0) / step + 1e-12).astype(np.int64), y_mm.size - 1)
    counts = np.maximum(last - first + 1, 0)
    total = int(counts.sum())
    if total == 0:
        return z_out, face_out
    seg = np.repeat(np.arange(counts.size), counts)
    ray = first[seg] + np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    s = np.clip((y_mm[ray] - y1[seg]) / dy[seg], 0.0, 1.0)
    z = z1[seg] + s * (z2[seg] - z1[seg])
    order = np.lexsort((-z, ray))                      # per ray, highest first
    ray_sorted = ray[order]
    pick = order[np.flatnonzero(np.r_[True, ray_sorted[1:] != ray_sorted[:-1]])]
    z_out[ray[pick]] = z[pick]
    face_out[ray[pick]] = faces[seg[pick]]
    return z_out, face_out


def top_surface(obj, max_tilt_deg: float, spacing_mm: float = DEFAULT_SPACING_MM) -> TopSurface:  # noqa: ANN001
    """The top of ``obj`` (a :class:`~elastoprobe.sim.objects.SimObject`) seen from above within
    ``max_tilt_deg`` of +z, sampled on a ``spacing_mm`` grid (module docstring)."""
    if not (0.0 < max_tilt_deg <= 90.0) or spacing_mm <= 0.0:
        raise ValueError("need 0 < max_tilt_deg <= 90 and spacing_mm > 0")
    mesh = obj.mesh
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    xs = math.floor(lo[0]) + (np.arange(int(math.ceil((hi[0] - math.floor(lo[0])) / spacing_mm))) + 0.5) * spacing_mm
    ys = math.floor(lo[1]) + (np.arange(int(math.ceil((hi[1] - math.floor(lo[1])) / spacing_mm))) + 0.5) * spacing_mm
    slicer = PlaneSlicer(mesh.vertices, mesh.faces)
    points, faces = [], []
    for x in xs:
        z, face = highest_hits(slicer, float(x), ys)
        hit = face >= 0
        points.append(np.column_stack([np.full(int(hit.sum()), x), ys[hit], z[hit]]))
        faces.append(face[hit])
    pts = np.vstack(points) if points else np.zeros((0, 3))
    face_idx = np.concatenate(faces) if faces else np.zeros(0, dtype=np.int64)
    normals = obj.surface_normals(pts, face_idx)
    keep = normals[:, 2] >= math.cos(math.radians(max_tilt_deg)) - 1e-12
    pts, normals, face_idx = pts[keep], normals[keep], face_idx[keep]
    # Near-vertical faces (only a plan allowing ~90 deg of tilt keeps them) would weigh without bound.
    area = spacing_mm * spacing_mm / np.maximum(normals[:, 2], MIN_COS_TILT)
    return TopSurface(pts, normals, obj.face_labels[face_idx].astype(int), area, float(spacing_mm),
                      float(max_tilt_deg))
