"""Fast ray casting of a laser line scanner's fan against a triangle mesh (no rtree/embree).

Every ray of a line scanner lies in one plane (the laser plane). So instead of a 3D
ray/triangle search we:

1. slice the mesh with the laser plane once per plane (:class:`PlaneSlicer`): signed
   distances of all vertices, then the faces that straddle the plane, each giving one
   segment of the cut (vectorised, ~0.3 ms for 60k faces). While the scanner moves
   within its own plane (the probe pushes along d, which lies in that plane) the cut
   is reused as is;
2. intersect the fan with those segments in 2D (:func:`cast_fan`): each segment covers
   an interval of ray angles seen from the origin; only (segment, ray) pairs inside
   that interval are solved, and the nearest hit per ray is kept.

The result is exact for the triangle mesh (no height-field approximation), works for
any viewing direction, and costs O(faces) once per plane plus O(pairs) per profile.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PlaneCut:
    """Segments where a plane cuts a mesh: endpoints (M,3), the face of each segment (M,)."""

    p1: np.ndarray
    p2: np.ndarray
    face: np.ndarray


class PlaneSlicer:
    """Cuts a triangle mesh (vertices (V,3), faces (F,3)) with planes."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=float)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        self.centre = (lo + hi) / 2.0
        self.radius = float(np.linalg.norm(hi - lo) / 2.0)

    def cut(self, origin: np.ndarray, plane_normal: np.ndarray) -> PlaneCut:
        """Segments of the plane through ``origin`` with unit normal ``plane_normal``."""
        n = np.asarray(plane_normal, float)
        o = np.asarray(origin, float)
        if abs(float((self.centre - o) @ n)) > self.radius:
            empty = np.zeros((0, 3))
            return PlaneCut(empty, empty, np.zeros(0, dtype=np.int64))
        s = self.vertices @ n - float(o @ n)
        s[s == 0.0] = 1e-12            # a vertex exactly on the plane counts as above it
        sf = s[self.faces]
        pos = sf > 0.0
        count = pos.sum(axis=1)
        idx = np.flatnonzero((count == 1) | (count == 2))
        if idx.size == 0:
            empty = np.zeros((0, 3))
            return PlaneCut(empty, empty, np.zeros(0, dtype=np.int64))
        f = self.faces[idx]
        sv = sf[idx]
        pv = pos[idx]
        # The lone vertex (the one on its own side) and the two others, in order.
        lone_is_pos = count[idx] == 1
        lone = np.where(lone_is_pos, np.argmax(pv, axis=1), np.argmin(pv, axis=1))
        other1 = (lone + 1) % 3
        other2 = (lone + 2) % 3
        rows = np.arange(idx.size)
        a = self.vertices[f[rows, lone]]
        b1 = self.vertices[f[rows, other1]]
        b2 = self.vertices[f[rows, other2]]
        sa, s1, s2 = sv[rows, lone], sv[rows, other1], sv[rows, other2]
        t1 = sa / (sa - s1)
        t2 = sa / (sa - s2)
        p1 = a + t1[:, None] * (b1 - a)
        p2 = a + t2[:, None] * (b2 - a)
        return PlaneCut(p1, p2, idx)


def cast_fan(cut: PlaneCut, origin: np.ndarray, x_axis: np.ndarray, z_axis: np.ndarray,
             angles_rad: np.ndarray, max_range_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray ``origin + r (sin a x + cos a z)`` with the cut's segments.

    ``angles_rad`` must be increasing and evenly spaced. Returns (range (N,) mm, inf
    where nothing is hit within ``max_range_mm``; face index (N,), -1 where nothing).
    """
    n_rays = angles_rad.shape[0]
    rng = np.full(n_rays, np.inf)
    face = np.full(n_rays, -1, dtype=np.int64)
    if cut.p1.shape[0] == 0:
        return rng, face
    o = np.asarray(origin, float)
    x1 = (cut.p1 - o) @ x_axis
    z1 = (cut.p1 - o) @ z_axis
    x2 = (cut.p2 - o) @ x_axis
    z2 = (cut.p2 - o) @ z_axis
    eps = 1e-6
    keep = (z1 > eps) | (z2 > eps)
    if not keep.any():
        return rng, face
    x1, z1, x2, z2 = x1[keep], z1[keep], x2[keep], z2[keep]
    faces = cut.face[keep]
    # Clip segments to the half plane in front of the scanner (z > eps).
    lo1 = z1 <= eps
    lo2 = z2 <= eps
    if lo1.any() or lo2.any():
        t = (eps - z1) / np.where(z2 - z1 == 0.0, 1e-300, z2 - z1)
        xc = x1 + t * (x2 - x1)
        x1 = np.where(lo1, xc, x1)
        z1 = np.where(lo1, eps, z1)
        x2 = np.where(lo2, xc, x2)
        z2 = np.where(lo2, eps, z2)
    a1 = np.arctan2(x1, z1)
    a2 = np.arctan2(x2, z2)
    a0 = float(angles_rad[0])
    step = float(angles_rad[1] - angles_rad[0]) if n_rays > 1 else 1.0
    first = np.ceil((np.minimum(a1, a2) - a0) / step - 1e-9).astype(np.int64)
    last = np.floor((np.maximum(a1, a2) - a0) / step + 1e-9).astype(np.int64)
    first = np.maximum(first, 0)
    last = np.minimum(last, n_rays - 1)
    counts = np.maximum(last - first + 1, 0)
    total = int(counts.sum())
    if total == 0:
        return rng, face
    seg = np.repeat(np.arange(counts.size), counts)
    offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    ray = first[seg] + offsets
    ang = angles_rad[ray]
    ux, uz = np.sin(ang), np.cos(ang)
    dx = x2[seg] - x1[seg]
    dz = z2[seg] - z1[seg]
    # r u = P1 + s D  ->  r = cross(P1, D) / cross(u, D), cross(a, b) = a_x b_z - a_z b_x
    denom = ux * dz - uz * dx
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (x1[seg] * dz - z1[seg] * dx) / denom
    ok = np.isfinite(r) & (r > 0.0) & (r <= max_range_mm)
    if not ok.any():
        return rng, face
    ray, r, seg = ray[ok], r[ok], seg[ok]
    # The nearest hit per ray; of equal nearest hits (a ray through a vertex two segments
    # share), the first segment's face.
    np.minimum.at(rng, ray, r)
    nearest = np.flatnonzero(r == rng[ray])
    _, first = np.unique(ray[nearest], return_index=True)
    pick = nearest[first]
    face[ray[pick]] = faces[seg[pick]]
    return rng, face


def plane_hits(origin: np.ndarray, directions: np.ndarray, plane_point: np.ndarray, plane_normal: np.ndarray,
               max_range_mm: float) -> np.ndarray:
    """Range (N,) of rays to a plane seen from its front side; inf where missed."""
    denom = directions @ plane_normal
    with np.errstate(divide="ignore", invalid="ignore"):
        r = ((plane_point - origin) @ plane_normal) / denom
    ok = (denom < -1e-12) & (r > 0.0) & (r <= max_range_mm)
    return np.where(ok, r, np.inf)


def segments_to_segment_distance(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N,) between segments p_i q_i (N,3) and one segment a b (vectorised, clamped)."""
    d1 = q - p
    d2 = b - a
    r = p - a
    aa = np.einsum("ij,ij->i", d1, d1)
    ee = float(d2 @ d2)
    ff = r @ d2
    cc = np.einsum("ij,ij->i", d1, r)
    bb = d1 @ d2
    denom = aa * ee - bb * bb
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, np.clip((bb * ff - cc * ee) / denom, 0.0, 1.0), 0.0)
    t = (bb * s + ff) / ee if ee > 0 else np.zeros_like(s)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(t < 0.0, np.clip(-cc / np.where(aa > 0, aa, 1.0), 0.0, 1.0), s)
        s = np.where(t > 1.0, np.clip((bb - cc) / np.where(aa > 0, aa, 1.0), 0.0, 1.0), s)
    t = np.clip(t, 0.0, 1.0)
    c1 = p + s[:, None] * d1
    c2 = a + t[:, None] * d2
    return np.linalg.norm(c1 - c2, axis=1)


def segments_to_point_distance(p: np.ndarray, q: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance (N,) from a point c to segments p_i q_i (N,3)."""
    d = q - p
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.where(dd > 0, ((c - p) * d).sum(axis=1) / dd, 0.0), 0.0, 1.0)
    return np.linalg.norm(p + s[:, None] * d - c, axis=1)


def segments_blocked(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, radius_mm: float) -> np.ndarray:
    """Which segments p_i q_i (N,3) pass within ``radius_mm`` of the segment a b (a capsule).

    Exact; an axis-aligned bounding-box test first, so only the few candidate rows get
    the segment-to-segment distance.
    """
    lo = np.minimum(p, q)
    hi = np.maximum(p, q)
    cap_lo = np.minimum(a, b) - radius_mm
    cap_hi = np.maximum(a, b) + radius_mm
    cand = np.flatnonzero(np.all((hi >= cap_lo) & (lo <= cap_hi), axis=1))
    out = np.zeros(p.shape[0], dtype=bool)
    if cand.size:
        if np.allclose(a, b):
            out[cand] = segments_to_point_distance(p[cand], q[cand], a) < radius_mm
        else:
            out[cand] = segments_to_segment_distance(p[cand], q[cand], a, b) < radius_mm
    return out
