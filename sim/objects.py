"""Simulated objects: geometry, regions, materials, and their ground truth (docs/design.md §8).

Object frame: mm, z up, the table is the plane z = 0 and the object rests on it
(z >= 0); the mesh is the undeformed outer surface without the table.

Object files (``config/objects/*.yaml``) name exactly one shape section and the
materials; each material is one region (label = its position in ``materials:``):

- ``ball: {radius_mm, material}``: a solid ball resting on the table.
- ``composite: {box: {size_mm, centre_mm, material}, pillow: {size_mm, edge_radius_mm,
  material}}``: a box (plate_on_foam) centred on a pillow (foam) with rounded edges.
- ``mesh: {file, scale_mm_per_unit, regions: [{material, face_color_rgb}], default_material}``:
  a user mesh (PLY/STL/OBJ, relative to the YAML), faces assigned to regions by colour.

``blend_width_mm`` (default 6): near a region boundary the contact is the blend
w_other = smoothstep(1/2 - s / blend_width_mm) of the two materials, s the exact
distance to the boundary (1-Lipschitz), so across it
|d peak / d s| <= 1.5 / blend_width_mm * max_x |profile_A - profile_B| + max(|d peak_A/ds|, |d peak_B/ds|)
(smoothstep's slope is at most 1.5; the peak of a blend moves by at most the sup-norm
difference of the profiles per unit of weight).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh
from pydantic import Field, StringConstraints
from scipy.spatial import cKDTree

from elastoprobe.controller.core.errors import InputError, InputErrors
from elastoprobe.controller.core.geometry import push_direction, unit
from elastoprobe.controller.core.meshcheck import drop_degenerate_faces, mesh_findings, read_mesh
from elastoprobe.controller.core.meshes import sphere_on_table
from elastoprobe.controller.core.yamlio import Spec, YamlDoc, load_validated

from .materials import Material, MaterialSpec, material_from_spec
from .physics import (Component, ContactModel, FoamResponse, HertzResponse, LocalResponse, PlateResponse,
                      SupportSink, hertz_contact_radius_mm)

Name = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_-]{0,39}$")]
Size3 = tuple[Annotated[float, Field(gt=0, le=5000)], Annotated[float, Field(gt=0, le=5000)],
              Annotated[float, Field(gt=0, le=5000)]]
RGB = tuple[Annotated[int, Field(ge=0, le=255)], Annotated[int, Field(ge=0, le=255)],
            Annotated[int, Field(ge=0, le=255)]]
CACHE_SIZE = 4096
BOUNDARY_CHUNK_ELEMENTS = 2_000_000     # point x segment pairs per chunk (~150 MB of temporaries)
CLOSEST_CHUNK_PAIRS = 500_000           # point x candidate face pairs measured at once (~0.4 GB of temporaries)
CLOSEST_CHUNK_POINTS = 4096             # points whose wider search (a ball of candidate faces) is listed at once


# --------------------------------------------------------------------------- schema

class BallSpec(Spec):
    radius_mm: float = Field(gt=0, le=2000)
    material: Name
    subdivisions: int = Field(4, ge=1, le=6)


class BoxPartSpec(Spec):
    size_mm: Size3
    centre_mm: tuple[float, float] = (0.0, 0.0)
    material: Name


class PillowSpec(Spec):
    size_mm: Size3
    edge_radius_mm: float = Field(ge=0, le=500)
    material: Name


class CompositeSpec(Spec):
    box: BoxPartSpec
    pillow: PillowSpec


class MeshRegionSpec(Spec):
    material: Name
    face_color_rgb: RGB


class MeshSpec(Spec):
    file: str
    scale_mm_per_unit: float = Field(1.0, gt=0, le=1e4)
    place_on_table: bool = True
    regions: list[MeshRegionSpec] = []
    default_material: Name | None = None


class ObjectSpec(Spec):
    """One object file (units in key names: mm)."""

    name: Name
    description: str = ""
    ball: BallSpec | None = None
    composite: CompositeSpec | None = None
    mesh: MeshSpec | None = None
    blend_width_mm: float = Field(6.0, gt=0, le=100)
    materials: dict[Name, MaterialSpec]


# --------------------------------------------------------------------------- helpers

def smoothstep(u: np.ndarray | float) -> np.ndarray:
    """3u^2 - 2u^3 on [0, 1], clamped (slope at most 1.5)."""
    v = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    return v * v * (3.0 - 2.0 * v)


def point_segment_distance_mm(points_mm: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray) -> np.ndarray:
    """Distances (N, S) from points (N,3) to segments a->b (S,3)."""
    p = np.asarray(points_mm, dtype=float)[:, None, :]
    ab = seg_b - seg_a
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    s = np.clip(np.einsum("nsj,sj->ns", p - seg_a[None], ab) / length2, 0.0, 1.0)
    nearest = seg_a[None] + s[..., None] * ab[None]
    return np.linalg.norm(p - nearest, axis=2)


def rounded_box_mesh(size_mm: np.ndarray, radius_mm: float) -> trimesh.Trimesh:
    """A box with all edges rounded by ``radius_mm`` sitting on z = 0 (convex hull of corner spheres)."""
    half = np.asarray(size_mm, dtype=float) / 2.0
    r = min(radius_mm, float(half.min()) - 1e-3)
    if r <= 0.5:
        mesh = trimesh.creation.box(extents=size_mm)
    else:
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=r).vertices
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * (half - r)
        mesh = trimesh.convex.convex_hull(np.concatenate([c + sphere for c in corners]))
    mesh.apply_translation([0.0, 0.0, half[2]])
    return mesh


def drop_table_faces(mesh: trimesh.Trimesh, tol_mm: float = 1e-3) -> trimesh.Trimesh:
    """Remove faces lying on the table (z = 0, facing down): the mesh excludes the table."""
    on_table = (mesh.triangles[:, :, 2].max(axis=1) < tol_mm) & (mesh.face_normals[:, 2] < -0.99)
    out = mesh.copy()
    out.update_faces(~on_table)
    out.remove_unreferenced_vertices()
    return out


class SurfaceIndex:
    """Exact closest points on a triangle set without rtree: a KD-tree over face centroids gives an
    upper bound, then every face whose bounding sphere could beat it is checked exactly."""

    def __init__(self, triangles_mm: np.ndarray) -> None:
        self.triangles = np.asarray(triangles_mm, dtype=float)
        self.centroids = self.triangles.mean(axis=1)
        self.radii = np.linalg.norm(self.triangles - self.centroids[:, None, :], axis=2).max(axis=1)
        self.max_radius = float(self.radii.max())
        self.tree = cKDTree(self.centroids)

    def closest(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(closest points (N,3), distances (N,), face indices (N,)).

        Memory is bounded whatever N: candidates are measured ``CLOSEST_CHUNK_PAIRS`` at a
        time, the wider searches listed ``CLOSEST_CHUNK_POINTS`` points at a time (one pass
        over an 84 000-point truth surface of a 350 mm composite with large faces held 16 GB)."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
        k = min(16, len(self.triangles))
        centre_dist, near = self.tree.query(pts, k=k)
        centre_dist, near = centre_dist.reshape(-1, k), near.reshape(-1, k)
        out_pts, out_dist, out_face = self._best(pts, np.repeat(np.arange(pts.shape[0]), k), near.ravel())
        # A face outside the k nearest centroids can only be closer if its bounding sphere
        # reaches inside the current best: check those points exhaustively around them.
        unsure = np.flatnonzero(centre_dist[:, -1] - self.max_radius < out_dist)
        for start in range(0, unsure.size, CLOSEST_CHUNK_POINTS):
            part = unsure[start:start + CLOSEST_CHUNK_POINTS]
            balls = self.tree.query_ball_point(pts[part], out_dist[part] + self.max_radius + 1e-9)
            counts = np.array([len(b) for b in balls])
            faces = np.fromiter((f for b in balls for f in b), dtype=int, count=int(counts.sum()))
            p2, d2, f2 = self._best(pts[part], np.repeat(np.arange(part.size), counts), faces)
            out_pts[part], out_dist[part], out_face[part] = p2, d2, f2
        return out_pts, out_dist, out_face

    def _best(self, pts: np.ndarray, rows: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each point, the nearest of its candidate faces (rows[i] is the point of faces[i];
        rows ascending, every point with a candidate)."""
        n = pts.shape[0]
        if rows.size <= CLOSEST_CHUNK_PAIRS:
            return self._best_of(pts, rows, faces)
        out_pts, out_dist, out_face = np.empty((n, 3)), np.empty(n), np.empty(n, dtype=faces.dtype)
        ends = np.cumsum(np.bincount(rows, minlength=n))
        first = 0
        while first < n:
            begin = ends[first - 1] if first else 0
            last = max(first + 1, int(np.searchsorted(ends, begin + CLOSEST_CHUNK_PAIRS, side="right")))
            pairs = slice(begin, ends[last - 1])
            p, d, f = self._best_of(pts[first:last], rows[pairs] - first, faces[pairs])
            out_pts[first:last], out_dist[first:last], out_face[first:last] = p, d, f
            first = last
        return out_pts, out_dist, out_face

    def _best_of(self, pts: np.ndarray, rows: np.ndarray, faces: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cand = trimesh.triangles.closest_point(self.triangles[faces], pts[rows])
        dist = np.linalg.norm(cand - pts[rows], axis=1)
        order = np.lexsort((dist, rows))           # per point, nearest first
        first = order[np.searchsorted(rows[order], np.arange(pts.shape[0]))]
        return cand[first], dist[first], faces[first]


def subdivide_labelled(mesh: trimesh.Trimesh, labels: np.ndarray, max_edge_mm: float) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Split faces until no edge exceeds ``max_edge_mm``; labels follow their faces."""
    v, f, index = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge_mm,
                                                   max_iter=20, return_index=True)
    return trimesh.Trimesh(v, f, process=False), np.asarray(labels)[index]


@dataclass(frozen=True)
class Dent:
    """A permanent dent: centre (object frame, mm), residual depth and radius (mm)."""

    centre_mm: np.ndarray
    depth_mm: float
    radius_mm: float


# --------------------------------------------------------------------------- the object

class SimObject:
    """A simulated object: mesh, region labels per face, materials, contact physics, ground truth.

    Subclasses give the shape-specific parts: analytic normals, the plate span of a
    cardboard face, the rigid sink of the whole body, the region boundaries.
    """

    def __init__(self, name: str, mesh: trimesh.Trimesh, face_labels: np.ndarray, region_names: list[str],
                 materials: list[Material], blend_width_mm: float = 6.0) -> None:
        self.name = name
        self.mesh = mesh
        self.face_labels = np.asarray(face_labels, dtype=int)
        self.region_names = list(region_names)
        self.materials = list(materials)
        self.blend_width_mm = float(blend_width_mm)
        self.load_warnings: list[str] = []        # what the user should know of the file (holes, ...)
        self._cache: dict[tuple, ContactModel] = {}
        self._dents: list[Dent] = []
        self._index = SurfaceIndex(mesh.triangles)
        self._region_index: dict[int, tuple[SurfaceIndex, np.ndarray]] = {}
        self._boundary_a, self._boundary_b, self._boundary_labels = self._boundaries()

    # -- geometry queries
    def closest_surface(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(closest surface points (N,3) mm, outward unit normals (N,3), region labels (N,)) of points (N,3)."""
        closest, _, faces = self._index.closest(points_mm)
        return closest, self._normals(closest, faces), self.face_labels[faces]

    def region_of(self, points_mm: np.ndarray) -> np.ndarray:
        """True region label (int) of the nearest surface point of each point (N,3)."""
        return self.closest_surface(points_mm)[2]

    def _normals(self, closest_mm: np.ndarray, faces: np.ndarray) -> np.ndarray:
        return self.mesh.face_normals[faces]

    def surface_normals(self, points_mm: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Outward unit normals (N,3) at surface points (N,3) lying on the given faces (N,)."""
        return self._normals(np.atleast_2d(points_mm), np.asarray(faces, dtype=np.int64))

    def _closest_on_region(self, point_mm: np.ndarray, label: int) -> tuple[np.ndarray, np.ndarray]:
        """Closest point and its normal on the faces of one region."""
        if label not in self._region_index:
            idx = np.flatnonzero(self.face_labels == label)
            self._region_index[label] = (SurfaceIndex(self.mesh.triangles[idx]), idx)
        index, idx = self._region_index[label]
        closest, _, faces = index.closest(point_mm[None])
        return closest[0], self._normals(closest, idx[faces])[0]

    def _boundaries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segments (a, b, (label, label)) between regions: mesh edges whose faces differ."""
        if len(self.region_names) < 2:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2), dtype=int)
        pairs = self.mesh.face_adjacency
        la, lb = self.face_labels[pairs[:, 0]], self.face_labels[pairs[:, 1]]
        differ = la != lb
        edges = self.mesh.face_adjacency_edges[differ]
        v = self.mesh.vertices
        return v[edges[:, 0]], v[edges[:, 1]], np.column_stack([la[differ], lb[differ]])

    def boundary_distance_mm(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance (N,) to the nearest region boundary in mm, index of that segment); inf if none.
        Exact (every segment); in chunks, so many points against a long seam stay within memory."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
        if self._boundary_a.shape[0] == 0:
            return np.full(pts.shape[0], np.inf), np.zeros(pts.shape[0], dtype=int)
        dist_out = np.empty(pts.shape[0])
        seg_out = np.empty(pts.shape[0], dtype=int)
        rows = max(1, BOUNDARY_CHUNK_ELEMENTS // self._boundary_a.shape[0])
        for start in range(0, pts.shape[0], rows):
            dist = point_segment_distance_mm(pts[start:start + rows], self._boundary_a, self._boundary_b)
            seg = np.argmin(dist, axis=1)
            dist_out[start:start + rows] = dist[np.arange(seg.shape[0]), seg]
            seg_out[start:start + rows] = seg
        return dist_out, seg_out

    # -- shape-specific physics (overridden)
    def _plate_span_mm(self, point_mm: np.ndarray, normal: np.ndarray, material: Material) -> float:
        return material.plate_radius_mm

    def _support(self, label: int, normal: np.ndarray, d: np.ndarray) -> SupportSink | None:
        return None

    def _body_radius_mm(self, label: int) -> float:
        return self.materials[label].body_radius_mm

    # -- contact
    def _response(self, label: int, point_mm: np.ndarray, normal: np.ndarray, tip_radius_mm: float) -> LocalResponse:
        m = self.materials[label]
        if m.kind == "elastic":
            body = self._body_radius_mm(label)
            r_eff = tip_radius_mm if body <= 0 else 1.0 / (1.0 / tip_radius_mm + 1.0 / body)
            return HertzResponse(m, r_eff, tip_radius_mm)
        if m.kind == "foam":
            return FoamResponse(m, tip_radius_mm)
        span = self._plate_span_mm(point_mm, normal, m)
        soft = self._dent_softening(point_mm)
        if soft > 0:
            # Crushed flutes under an old dent: the local through-thickness modulus drops.
            m = Material(**{**m.__dict__, "local_E_mpa": m.local_E_mpa / (1.0 + soft)})
        return PlateResponse(m, tip_radius_mm, span)

    def _blend(self, point_mm: np.ndarray, label: int) -> list[tuple[int, float]]:
        """[(label, weight)]: the region under the tip, plus the neighbour within the blend width."""
        dist, seg = self.boundary_distance_mm(point_mm[None])
        d = float(dist[0])
        if not math.isfinite(d):
            return [(label, 1.0)]
        pair = self._boundary_labels[int(seg[0])]
        other = int(pair[1] if pair[0] == label else pair[0])
        w_other = float(smoothstep(0.5 - d / self.blend_width_mm))
        if w_other <= 1e-12 or other == label:
            return [(label, 1.0)]
        return [(label, 1.0 - w_other), (other, w_other)]

    def contact_model(self, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, angle_deg: float,
                      tip_radius_mm: float) -> ContactModel:
        """The contact at ``point_mm`` (object frame) probed at ``angle_deg`` in the (t, n) plane.

        ``normal`` and ``t`` are the true outward normal and the scan direction there (the
        profile's frame); the point is first moved onto the surface. Cached per arguments.
        """
        key = (tuple(np.round(np.asarray(point_mm, dtype=float), 6)), tuple(np.round(normal, 9)),
               tuple(np.round(t, 9)), round(float(angle_deg), 9), round(float(tip_radius_mm), 9), len(self._dents))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        n, tt = unit(normal), unit(t)
        surf, _, labels = self.closest_surface(np.asarray(point_mm, dtype=float)[None])
        p = surf[0]
        label = int(labels[0])
        d = push_direction(tt, n, angle_deg)
        components = []
        for lab, weight in self._blend(p, label):
            q, nq = (p, n) if lab == label else self._closest_on_region(p, lab)
            # Each material is evaluated where it is (its own nearest point and normal), so the
            # blend stays continuous across a corner where the two regions meet.
            components.append(Component(weight, self._response(lab, q, nq, tip_radius_mm), self._support(lab, nq, d)))
        residual = self._residual_fn(p, tt, n)
        model = ContactModel(components, angle_deg, self.materials[label], label, residual)
        if len(self._cache) >= CACHE_SIZE:
            self._cache.clear()
        self._cache[key] = model
        return model

    def true_profile_mm(self, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, force_n: float,
                        angle_deg: float, x_mm: np.ndarray, tip_radius_mm: float) -> np.ndarray:
        """Ground truth: noise-free equilibrium depth (mm along -n, > 0 into the object) at point + x t
        under |F| = ``force_n`` at ``angle_deg``, relative to the unloaded surface as it is now
        (a permanent dent is already in the zero-force reference, so it is not part of the profile)."""
        model = self.contact_model(point_mm, normal, t, angle_deg, tip_radius_mm)
        x = np.asarray(x_mm, dtype=float)
        return model.depth_profile_mm(x, force_n) - model.depth_profile_mm(x, 0.0)

    # -- permanent dents
    def add_permanent_dent(self, point_mm: np.ndarray, normal: np.ndarray, force_n: float,
                           tip_radius_mm: float = 5.0) -> None:
        """Record the dent left by the largest load ``force_n`` (N) pressed at a point, if its material
        yields there (``yield_force_n``); depth ``dent_mm_per_n`` per newton above yield, radius the
        local contact radius + 1 mm. Later profiles near it include the residual dent (in
        ``depth_profile_mm``, at every force) and a softer local response (crushed flutes)."""
        surf, _, labels = self.closest_surface(np.asarray(point_mm, dtype=float)[None])
        m = self.materials[int(labels[0])]
        if m.yield_force_n is None or force_n <= m.yield_force_n:
            return
        depth = m.dent_mm_per_n * (force_n - m.yield_force_n)
        radius = float(hertz_contact_radius_mm(force_n, tip_radius_mm, m.local_E_mpa / (1 - m.nu ** 2))) + 1.0
        if len(self._dents) < 10_000:
            self._dents.append(Dent(surf[0], depth, radius))

    def reset_history(self) -> None:
        """Forget permanent dents (a fresh object)."""
        self._dents.clear()
        self._cache.clear()

    def _dent_softening(self, point_mm: np.ndarray) -> float:
        """Local crush: 1 per 0.5 mm of residual dent, fading over twice the dent radius."""
        total = 0.0
        for dent in self._dents:
            dist = float(np.linalg.norm(point_mm - dent.centre_mm))
            total += dent.depth_mm / 0.5 * math.exp(-(dist / (2.0 * dent.radius_mm)) ** 2)
        return total

    def _residual_fn(self, p: np.ndarray, t: np.ndarray, n: np.ndarray):
        near = [dent for dent in self._dents if np.linalg.norm(np.cross(dent.centre_mm - p, t)) < 4 * dent.radius_mm + 50]
        if not near:
            return None
        centres = np.array([dent.centre_mm for dent in near])
        depths = np.array([dent.depth_mm for dent in near])
        radii = np.array([dent.radius_mm for dent in near])

        def residual(x_mm: np.ndarray) -> np.ndarray:
            pts = p[None, :] + np.asarray(x_mm, dtype=float)[:, None] * t[None, :]
            dist2 = np.sum((pts[:, None, :] - centres[None]) ** 2, axis=2)
            return np.sum(depths[None] * np.exp(-dist2 / radii[None] ** 2), axis=1)
        return residual

    # -- self-check
    def validity_points(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(point, normal) samples, a few per region, where validity is checked."""
        out = []
        centroids, normals = self.mesh.triangles_center, self.mesh.face_normals
        for label in range(len(self.region_names)):
            idx = np.flatnonzero(self.face_labels == label)
            if idx.size == 0:
                continue
            pick = idx[np.linspace(0, idx.size - 1, min(12, idx.size)).astype(int)]
            out.extend((centroids[i], normals[i]) for i in pick)
        return out

    def validity_report(self, max_force_n: float, tip_radius_mm: float) -> list[str]:
        """Physics self-check at the plan's largest force, pressing along the normal (the largest
        normal load): a/R (Hertz), depth/(eps_D h) (foam), plate deflection/thickness.
        Returns [] when every model is within its validity, else one line per problem."""
        problems: list[str] = []
        for point, normal in self.validity_points():
            t = np.cross(normal, [0.0, 0.0, 1.0])
            if np.linalg.norm(t) < 1e-6:
                t = np.array([1.0, 0.0, 0.0])
            model = self.contact_model(point, normal, unit(t), 90.0, tip_radius_mm)
            for problem in model.validity_problems(max_force_n):
                kind = " ".join(problem.split(" ")[:3])      # e.g. "foam: foam depth", one line each
                if kind not in {" ".join(p.split(" ")[:3]) for p in problems}:
                    problems.append(problem)
        return problems


class BallObject(SimObject):
    """A solid elastic ball of radius R resting on the table at its lowest point."""

    def __init__(self, name: str, radius_mm: float, material: Material, subdivisions: int = 4) -> None:
        self.radius_mm = float(radius_mm)
        self.centre_mm = np.array([0.0, 0.0, self.radius_mm])
        mesh = sphere_on_table(self.radius_mm, subdivisions)
        super().__init__(name, mesh, np.zeros(len(mesh.faces), dtype=int), [material.name], [material])

    def closest_surface(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Analytic: the true sphere, not its facets."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
        v = pts - self.centre_mm
        norm = np.linalg.norm(v, axis=1, keepdims=True)
        normals = np.where(norm > 1e-9, v / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))
        return self.centre_mm + self.radius_mm * normals, normals, np.zeros(pts.shape[0], dtype=int)

    def _body_radius_mm(self, label: int) -> float:
        return self.radius_mm

    def _normals(self, closest_mm: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Analytic: the true sphere's normal, not its facet's."""
        v = np.atleast_2d(closest_mm) - self.centre_mm
        return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)

    def _support(self, label: int, normal: np.ndarray, d: np.ndarray) -> SupportSink | None:
        """The ball flattens on the rigid table too (Hertz, ball radius): the whole ball sinks."""
        e = np.array([0.0, 0.0, -1.0])
        m = self.materials[0]
        radius, e_star = self.radius_mm, m.reduced_modulus_mpa

        def sink(load_n: np.ndarray) -> np.ndarray:
            a = hertz_contact_radius_mm(load_n, radius, e_star)
            return a * a / radius
        return SupportSink(sink, max(0.0, float(d @ e)), float(d @ e), float(-(normal @ e)))


def reference_sphere(radius_mm: float) -> BallObject:
    """The calibration's reference sphere: acetal, rigid enough that a 0.4 N touch dents it by
    ~1 um, so the touches and scans see its nominal radius (mm)."""
    acetal = Material(name="acetal", kind="elastic", E_mpa=3000.0, nu=0.35, friction_mu=0.2,
                      scanner_noise_mm=0.01, noise_corr_floor_mm=0.002, dropout_prob=0.01, steep_incidence_deg=80.0)
    return BallObject("reference-sphere", radius_mm, acetal)


class CompositeObject(SimObject):
    """A cardboard box (plate_on_foam) centred on a foam pillow with rounded edges."""

    def __init__(self, name: str, spec: CompositeSpec, box_material: Material, pillow_material: Material,
                 blend_width_mm: float) -> None:
        pillow_size = np.array(spec.pillow.size_mm)
        box_size = np.array(spec.box.size_mm)
        pillow = drop_table_faces(rounded_box_mesh(pillow_size, spec.pillow.edge_radius_mm))
        box = trimesh.creation.box(extents=box_size)
        z0 = float(pillow_size[2])
        cx, cy = spec.box.centre_mm
        box.apply_translation([cx, cy, z0 + box_size[2] / 2.0])
        keep = box.face_normals[:, 2] > -0.99          # the bottom rests on the pillow: not surface
        box.update_faces(keep)
        box.remove_unreferenced_vertices()
        mesh = trimesh.util.concatenate([box, pillow])
        labels = np.concatenate([np.zeros(len(box.faces), dtype=int), np.ones(len(pillow.faces), dtype=int)])
        mesh, labels = subdivide_labelled(mesh, labels, 12.0)
        self.box_min_mm = np.array([cx, cy, z0 + box_size[2] / 2.0]) - box_size / 2.0
        self.box_max_mm = self.box_min_mm + box_size
        self.pillow_top_mm = z0
        self._pillow_material = pillow_material
        self._box_area_mm2 = float(box_size[0] * box_size[1])
        self._box_perimeter_mm = float(2.0 * (box_size[0] + box_size[1]))
        super().__init__(name, mesh, labels, [box_material.name, pillow_material.name],
                         [box_material, pillow_material], blend_width_mm)

    def _boundaries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The box's footprint on the pillow (its bottom edges) separates cardboard from foam."""
        lo, hi, z = self.box_min_mm, self.box_max_mm, self.pillow_top_mm
        corners = np.array([[lo[0], lo[1], z], [hi[0], lo[1], z], [hi[0], hi[1], z], [lo[0], hi[1], z]])
        return corners, np.roll(corners, -1, axis=0), np.tile([0, 1], (4, 1))

    def _plate_span_mm(self, point_mm: np.ndarray, normal: np.ndarray, material: Material) -> float:
        """Clamped span radius b of the box face at a point: the stiff box edges clamp the face, so
        b = (mean of 1/d_i^2 over the distances d_i to the face's four edges)^(-1/2) (80 mm at the
        centre of a 160 mm face, shrinking toward the edges: stiffer there)."""
        axis = int(np.argmax(np.abs(normal)))
        in_plane = [i for i in range(3) if i != axis]
        d = []
        for i in in_plane:
            d += [point_mm[i] - self.box_min_mm[i], self.box_max_mm[i] - point_mm[i]]
        d_arr = np.maximum(np.asarray(d), 1.0)
        return float(np.mean(1.0 / d_arr ** 2) ** -0.5)

    def _support(self, label: int, normal: np.ndarray, d: np.ndarray) -> SupportSink | None:
        """The whole box sinks into the pillow: a rigid footing on the Winkler-Pasternak layer,
        stiffness k0 (A + lambda * perimeter), k0 = E/h (the small sink keeps it linear)."""
        if label != 0:
            return None
        f = self._pillow_material
        k0 = f.E_mpa / f.thickness_mm
        stiffness = k0 * (self._box_area_mm2 + f.decay_length_mm * self._box_perimeter_mm)
        e = np.array([0.0, 0.0, -1.0])
        return SupportSink(lambda load_n: np.asarray(load_n, dtype=float) / stiffness,
                           max(0.0, float(d @ e)), float(d @ e), float(-(normal @ e)))

    def validity_points(self) -> list[tuple[np.ndarray, np.ndarray]]:
        top_centre = np.array([(self.box_min_mm[0] + self.box_max_mm[0]) / 2,
                               (self.box_min_mm[1] + self.box_max_mm[1]) / 2, self.box_max_mm[2]])
        return [(top_centre, np.array([0.0, 0.0, 1.0]))] + super().validity_points()


class MeshObject(SimObject):
    """A user mesh whose faces are assigned to regions by colour."""


# --------------------------------------------------------------------------- loading

def _materials(spec: ObjectSpec) -> tuple[list[str], list[Material]]:
    names = list(spec.materials)
    return names, [material_from_spec(n, spec.materials[n]) for n in names]


def _key_error(doc: YamlDoc, loc: tuple, message: str) -> InputError:
    """An error at the key that opens ``loc`` (for problems with a whole section)."""
    if loc in doc.key_positions:
        line, col = doc.key_positions[loc]
        return InputError(message, path=doc.path, line=line, col=col)
    return doc.error(loc, message)


def _check_refs(spec: ObjectSpec, doc: YamlDoc) -> None:
    errors: list[InputError] = []
    sections = [k for k in ("ball", "composite", "mesh") if getattr(spec, k) is not None]
    if len(sections) != 1:
        where = (sections[1],) if len(sections) > 1 else ()
        errors.append(_key_error(doc, where, "an object needs exactly one of 'ball', 'composite', 'mesh'"))
    refs: list[tuple[tuple, str, str | None]] = []
    if spec.ball is not None:
        refs.append((("ball", "material"), spec.ball.material, "elastic"))
    if spec.composite is not None:
        refs.append((("composite", "box", "material"), spec.composite.box.material, "plate_on_foam"))
        refs.append((("composite", "pillow", "material"), spec.composite.pillow.material, "foam"))
        c = spec.composite
        if c.box.size_mm[0] + 2 * abs(c.box.centre_mm[0]) > c.pillow.size_mm[0] - 2 * c.pillow.edge_radius_mm or \
                c.box.size_mm[1] + 2 * abs(c.box.centre_mm[1]) > c.pillow.size_mm[1] - 2 * c.pillow.edge_radius_mm:
            errors.append(doc.error(("composite", "box", "size_mm"), "the box must rest on the flat top of the pillow"))
    if spec.mesh is not None:
        for i, region in enumerate(spec.mesh.regions):
            refs.append((("mesh", "regions", i, "material"), region.material, None))
        if spec.mesh.default_material is not None:
            refs.append((("mesh", "default_material"), spec.mesh.default_material, None))
    used = set()
    for loc, name, kind in refs:
        used.add(name)
        if name not in spec.materials:
            errors.append(doc.error(loc, f"unknown material {name!r} (defined: {', '.join(spec.materials)})"))
        elif kind is not None and spec.materials[name].kind != kind:
            errors.append(doc.error(loc, f"material {name!r} is {spec.materials[name].kind!r}, here it must be {kind!r}"))
        elif spec.mesh is not None and spec.materials[name].kind == "plate_on_foam" \
                and spec.materials[name].plate_radius_mm <= 0:
            errors.append(_key_error(doc, ("materials", name), "a plate_on_foam on a mesh needs plate_radius_mm > 0"))
    for name in spec.materials:
        if name not in used:
            errors.append(_key_error(doc, ("materials", name), f"material {name!r} is not used by any region"))
    if errors:
        raise InputErrors(errors)


def _load_mesh_object(spec: ObjectSpec, doc: YamlDoc, path: Path) -> MeshObject:
    """A painted user mesh, checked (controller/core/meshcheck.py) before anything is computed from it."""
    ms = spec.mesh
    assert ms is not None
    file = (path.parent / ms.file).resolve()
    if not file.is_file():
        what = "is not a regular file" if file.exists() else "does not exist"
        raise doc.error(("mesh", "file"), f"mesh file {str(file)!r} {what}")
    try:
        loaded = read_mesh(file)
    except ValueError as exc:
        raise doc.error(("mesh", "file"), f"{file.name}: {exc}") from None
    mesh = loaded.copy()
    with np.errstate(over="ignore", invalid="ignore"):
        mesh.apply_scale(ms.scale_mm_per_unit)
        if not np.all(np.isfinite(mesh.vertices)):
            raise doc.error(("mesh", "scale_mm_per_unit"), f"{file.name}: coordinates times scale_mm_per_unit "
                                                           f"are not finite numbers (the mesh is far too large)")
        if ms.place_on_table:
            mesh.apply_translation([0.0, 0.0, -float(mesh.vertices[:, 2].min())])
        elif float(mesh.vertices[:, 2].min()) < -1e-6:
            raise doc.error(("mesh", "place_on_table"), "the mesh reaches below the table (z < 0)")
        findings = mesh_findings(mesh)
    if findings.errors:
        raise doc.error(("mesh", "file"), f"{file.name}: " + "; ".join(findings.errors))
    names, materials = _materials(spec)
    labels = _paint(spec, doc, loaded, names)
    mesh, kept = drop_degenerate_faces(mesh)
    labels = labels[kept]
    faces_keep = ~((mesh.triangles[:, :, 2].max(axis=1) < 1e-3) & (mesh.face_normals[:, 2] < -0.99))
    mesh.update_faces(faces_keep)
    labels = labels[faces_keep]
    mesh.remove_unreferenced_vertices()
    obj = MeshObject(spec.name, mesh, labels, names, materials, spec.blend_width_mm)
    obj.load_warnings = [f"{file}: {w}" for w in findings.warnings]
    return obj


def _paint(spec: ObjectSpec, doc: YamlDoc, loaded: trimesh.Trimesh, names: list[str]) -> np.ndarray:
    """Region label per face from the face colours; every region's colour must be on some face."""
    ms = spec.mesh
    assert ms is not None
    colors = np.asarray(loaded.visual.face_colors)[:, :3].astype(int) if loaded.visual.kind else \
        np.zeros((len(loaded.faces), 3), dtype=int)
    labels = np.full(len(loaded.faces), -1, dtype=int)
    for i, region in enumerate(ms.regions):
        match = np.all(colors == np.asarray(region.face_color_rgb), axis=1)
        if not match.any():
            present, count = np.unique(colors, axis=0, return_counts=True)
            order = np.argsort(-count)[:4]
            have = ", ".join(f"{present[k].tolist()} on {count[k]} faces" for k in order) \
                if loaded.visual.kind else "none: the file has no colours"
            raise doc.error(("mesh", "regions", i, "face_color_rgb"),
                            f"no face of the mesh has the colour {list(region.face_color_rgb)} "
                            f"(material {region.material!r}); the mesh's colours: {have}")
        labels[match & (labels < 0)] = names.index(region.material)
    if np.any(labels < 0):
        if ms.default_material is None:
            raise _key_error(doc, ("mesh", "regions"), f"{int(np.sum(labels < 0))} faces match no region colour "
                                                 f"(add default_material)")
        labels[labels < 0] = names.index(ms.default_material)
    return labels


def load_object(path: str | Path) -> SimObject:
    """Load and validate an object file; every problem is an InputError ``path:line:col: message``."""
    spec, doc = load_validated(path, ObjectSpec)
    _check_refs(spec, doc)
    if spec.ball is not None:
        names, materials = _materials(spec)
        return BallObject(spec.name, spec.ball.radius_mm, materials[0], spec.ball.subdivisions)
    if spec.composite is not None:
        names, materials = _materials(spec)
        box = materials[names.index(spec.composite.box.material)]
        pillow = materials[names.index(spec.composite.pillow.material)]
        if names.index(spec.composite.box.material) != 0:
            raise _key_error(doc, ("materials",), "list the box's material first (region 0), then the pillow's")
        return CompositeObject(spec.name, spec.composite, box, pillow, spec.blend_width_mm)
    return _load_mesh_object(spec, doc, Path(path))
