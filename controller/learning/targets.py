"""From neural gas units to probe targets on the surface (docs/design.md §2, §3, §7).

A unit is a point in space near the cloud. Its target is a point ON the surface with
an outward normal and a scan direction t. Units on a sharp edge mark where to look,
but the normal is undefined there and the tip would slip, so the target moves along
the surface onto the face beside the edge, ``edge_clearance_radii`` tip radii from it.
A unit where the tip does not fit (the foot of a wall: the ball would meet the wall
before the point, see :meth:`_Surface.tip_fits`) moves the same way. Targets on steep
(tilted beyond ``max_tilt_deg`` from ``up``), sparse or open-border parts of the cloud
are dropped.

Frames and units: everything in the cloud's frame (object frame), mm; normals and t
are unit vectors; ``up`` is the direction the probe comes from (+z of the object
frame by default).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.geometry import scan_direction
from . import survey_density
from .cloud import local_plane
from .profiles import MAX_FACE_SLOPE

# Cloud points that must stand inside the tip's ball before it does not fit: a wall or a step
# is a row of them, one scanner sample beyond its noise is not.
TIP_INTRUDING_POINTS = 3


@dataclass(frozen=True)
class Targets:
    """Probe targets (T of them): points (T,3) mm on the surface, outward unit normals
    (T,3), scan directions t (T,3) in the tangent planes, ``edge_flag`` (T,) True where
    the target was moved off a sharp edge or a wall's foot, ``source_unit`` (T,) index of
    its unit."""

    points_mm: np.ndarray
    normals: np.ndarray
    t: np.ndarray
    edge_flag: np.ndarray
    source_unit: np.ndarray

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


@dataclass(frozen=True)
class TargetRules:
    """Where a probe may touch.

    tip_radius_mm: probe tip radius; edge_clearance_radii: keep targets this many tip
    radii from any sharp edge; edge_curvature: PCA surface variation above which a cloud
    point is on a sharp edge (flat ~0, a 90-degree edge ~0.05-0.15); max_tilt_deg: largest
    angle between a target normal and ``up``; density_radius_mm / min_neighbours: a target
    needs this many cloud points within this radius; border_offset: a target whose
    neighbourhood centroid lies more than this fraction of the radius away sits on an open
    border of the cloud; plane_k: neighbours of the local plane fit; max_shift_mm: how far
    an edge unit's target may move (default 2 x clearance); min_spacing_mm: targets closer
    than this are merged (default 2 tip radii); tip_intrusion_mm: how far the cloud may rise
    into the tip's ball resting on a target before the tip does not fit there (default a tenth
    of the tip radius; see :meth:`_Surface.tip_fits`).
    """

    tip_radius_mm: float = 2.5
    edge_clearance_radii: float = 3.0
    edge_curvature: float = 0.02
    max_tilt_deg: float = 60.0
    density_radius_mm: float = 5.0
    min_neighbours: int = 10
    border_offset: float = 0.35
    plane_k: int = 16
    max_shift_mm: float | None = None
    min_spacing_mm: float | None = None
    tip_intrusion_mm: float | None = None

    @property
    def clearance_mm(self) -> float:
        return self.edge_clearance_radii * self.tip_radius_mm

    @property
    def shift_mm(self) -> float:
        return 2.0 * self.clearance_mm if self.max_shift_mm is None else self.max_shift_mm

    @property
    def spacing_mm(self) -> float:
        return 2.0 * self.tip_radius_mm if self.min_spacing_mm is None else self.min_spacing_mm

    @property
    def intrusion_mm(self) -> float:
        return 0.1 * self.tip_radius_mm if self.tip_intrusion_mm is None else self.tip_intrusion_mm


def rules_for_plan(tip_radius_mm: float, edge_clearance_mm: float, max_tilt_deg: float,
                   min_feature_mm: float | None = None) -> TargetRules:
    """The rules a plan's ``sampling`` sets (its edge clearance and tilt in mm and degrees, the
    cell's tip radius in mm); a ``min_feature_mm`` survey merges targets only closer than
    half its spacing (learning.survey_density)."""
    return TargetRules(tip_radius_mm=tip_radius_mm, edge_clearance_radii=edge_clearance_mm / tip_radius_mm,
                       max_tilt_deg=max_tilt_deg,
                       min_spacing_mm=survey_density.merge_spacing_mm(2.0 * tip_radius_mm, min_feature_mm))


class _Surface:
    """The cloud with its normals and edges, and the per-point tests a target must pass."""

    def __init__(self, cloud_mm: np.ndarray, normals: np.ndarray, curvature: np.ndarray, rules: TargetRules,
                 up: np.ndarray) -> None:
        self.points = np.asarray(cloud_mm, dtype=float)
        self.normals = np.asarray(normals, dtype=float)
        self.rules = rules
        self.up = up / np.linalg.norm(up)
        self.tree = cKDTree(self.points)
        edge = np.asarray(curvature) > rules.edge_curvature
        self.edge_tree = cKDTree(self.points[edge]) if edge.any() else None
        # The edge is known only to within the point spacing: keep that much more clearance.
        self.spacing_mm = self._spacing_mm()
        self.guard_mm = rules.clearance_mm + self.spacing_mm
        self._plan_tree: cKDTree | None = None   # the cloud seen from up, built on first use

    def _spacing_mm(self, n_probe: int = 20_000) -> float:
        """Median nearest-neighbour distance of the cloud (on a fixed subsample)."""
        rng = np.random.default_rng(0)
        probe = self.points[rng.choice(self.points.shape[0], min(n_probe, self.points.shape[0]), replace=False)]
        dist, _ = self.tree.query(probe, k=2)
        return float(np.median(dist[:, 1]))

    def near_edge(self, idx: np.ndarray, clearance_mm: float | None = None) -> np.ndarray:
        """True where a sharp edge lies within the clearance (the rules', unless given) plus
        the point spacing."""
        if self.edge_tree is None:
            return np.zeros(len(idx), dtype=bool)
        guard = self.guard_mm if clearance_mm is None else clearance_mm + self.spacing_mm
        dist, _ = self.edge_tree.query(self.points[idx], distance_upper_bound=guard)
        return np.isfinite(dist)

    def tip_fits(self, idx: np.ndarray, chunk: int = 20_000) -> np.ndarray:
        """True where the tip, a ball of ``tip_radius_mm`` resting on cloud point i along its
        normal, is clear of the rest of the cloud: fewer than ``TIP_INTRUDING_POINTS`` points
        rise more than ``rules.intrusion_mm`` into it.

        Seen from ``up`` the object is solid below every cloud point (a scanner above sees
        no overhang), so the ball meets the object wherever a point within one tip radius of
        its centre, across ``up``, stands higher than the ball's lower surface there. A
        tangent plane never rises into the ball, nor does a hollow wider than the tip; the
        foot of a wall does, and the cloud need not hold the wall itself (a scanner above
        barely sees it): the top beside it stands just as high. The sharp-edge test misses
        such a foot: the floor's curvature beside it stays low. On a generated gel pillow
        with a 10.7 mm elastomer plate, 23 survey targets 3.4-5.0 mm from the plate's side
        read the gel stiff and were mapped as plate.
        """
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        out = np.ones(idx.size, dtype=bool)
        if idx.size == 0:
            return out
        r = self.rules.tip_radius_mm
        if self._plan_tree is None:
            self._across = _across_basis(self.up)
            self._plan_tree = cKDTree(self.points @ self._across.T)
            self._height = self.points @ self.up
        for lo in range(0, idx.size, chunk):
            part = idx[lo:lo + chunk]
            centre = self.points[part] + r * self.normals[part]
            c_flat, c_up = centre @ self._across.T, centre @ self.up
            near = self._plan_tree.query_ball_point(c_flat, r, return_sorted=False)
            counts = np.fromiter((len(v) for v in near), dtype=np.int64, count=len(near))
            if counts.sum() == 0:
                continue
            owner = np.repeat(np.arange(part.size), counts)
            q = np.concatenate([np.asarray(v, dtype=np.int64) for v in near])
            flat2 = np.sum((self._plan_tree.data[q] - c_flat[owner]) ** 2, axis=1)
            lower = c_up[owner] - np.sqrt(np.maximum(r * r - flat2, 0.0))
            into = np.bincount(owner[self._height[q] - lower > self.rules.intrusion_mm], minlength=part.size)
            out[lo:lo + part.size] = into < TIP_INTRUDING_POINTS
        return out

    def tilt_ok(self, idx: np.ndarray) -> np.ndarray:
        return self.normals[idx] @ self.up >= np.cos(np.radians(self.rules.max_tilt_deg))

    def supported(self, i: int) -> bool:
        """Dense enough around point i, and not on an open border of the cloud."""
        r = self.rules.density_radius_mm
        nb = self.tree.query_ball_point(self.points[i], r)
        if len(nb) < self.rules.min_neighbours:
            return False
        offset = self.points[nb].mean(axis=0) - self.points[i]
        offset -= (offset @ self.normals[i]) * self.normals[i]
        return float(np.linalg.norm(offset)) <= self.rules.border_offset * r

    def plane_at(self, i: int, near_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project ``near_mm`` on the local plane fit around cloud point i -> (point, normal).

        The neighbourhood is widened as the cloud's normals are (cloud._local_pca): the
        ``plane_k`` nearest points of a laser-line raster can all lie on one profile, and a
        line has no plane — its smallest-variance direction is any direction across it. On
        the loopback plan's ball a target got the normal (0, -1, 0), the sweep direction,
        from a point whose cloud normal was right: the 90 deg probe was planned horizontal,
        the descent to it refused (probe within 1.4 mm of the object) and the session
        aborted for 3 of 7 seeds in process."""

        centroid, _, vecs = local_plane(self.points, self.tree, i, self.rules.plane_k)
        n = vecs[:, 0]
        if n @ self.normals[i] < 0:  # keep the cloud's outward orientation
            n = -n
        return near_mm - ((near_mm - centroid) @ n) * n, n


def probeable(cloud_mm: np.ndarray, normals: np.ndarray, curvature: np.ndarray, rules: TargetRules = TargetRules(),
              up: "np.ndarray | tuple" = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(P,) True for cloud points a target could sit on: tilted less than ``max_tilt_deg``,
    clear of every sharp edge by the edge clearance (plus the point spacing), with at
    least ``min_neighbours`` cloud points within ``density_radius_mm``, and where the tip
    fits (:meth:`_Surface.tip_fits`).

    The survey's neural gas is trained on these points only. Trained on the whole cloud,
    its units follow the walls, the rounded rims and the steep flanks of a dome, where no
    target may go: on a dome whose top is probe-able within 44 mm of its apex, 26 units
    gave 2 targets; on a block with rounded shoulders 23 units gave 9.
    """
    surf = _Surface(cloud_mm, normals, curvature, rules, np.asarray(up, dtype=float))
    return _probeable_within(surf, rules.clearance_mm)


def probeable_and_rim_band(cloud_mm: np.ndarray, normals: np.ndarray, curvature: np.ndarray,
                           rules: TargetRules, band_clearance_mm: float,
                           up: "np.ndarray | tuple" = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """(P,) :func:`probeable` with ``rules``, and (P,) the rim band: the points that pass every
    test with the edge clearance cut to ``band_clearance_mm`` (mm) but are too near an edge for
    the rules' own. Empty when ``band_clearance_mm`` is not below the rules' clearance, and
    along a rim where the cloud shows no sharp edge (a wall the sweep did not see: survey
    targets stand near such a rim already)."""
    surf = _Surface(cloud_mm, normals, curvature, rules, np.asarray(up, dtype=float))
    near = _probeable_within(surf, min(float(band_clearance_mm), rules.clearance_mm))
    far = near & ~surf.near_edge(np.arange(surf.points.shape[0]))
    return far, near & ~far


def _probeable_within(surf: _Surface, clearance_mm: float) -> np.ndarray:
    """(P,) the :func:`probeable` tests, keeping ``clearance_mm`` (plus the spacing) from edges."""
    rules = surf.rules
    idx = np.arange(surf.points.shape[0])
    ok = surf.tilt_ok(idx) & ~surf.near_edge(idx, clearance_mm)
    if ok.any():
        counts = surf.tree.query_ball_point(surf.points[ok], rules.density_radius_mm, return_length=True)
        ok[np.flatnonzero(ok)[np.asarray(counts) < rules.min_neighbours]] = False
    if ok.any():
        ok[np.flatnonzero(ok)[~surf.tip_fits(np.flatnonzero(ok))]] = False
    return ok


def make_targets(units_mm: np.ndarray, cloud_mm: np.ndarray, normals: np.ndarray, curvature: np.ndarray,
                 rules: TargetRules = TargetRules(), reference_dir: "np.ndarray | tuple" = (1.0, 0.0, 0.0),
                 up: "np.ndarray | tuple" = (0.0, 0.0, 1.0)) -> Targets:
    """Units (M,3) mm -> Targets on the cloud (with its outward normals and curvature).

    Each unit goes to its nearest cloud point. If that point is within the edge
    clearance (plus the cloud's median point spacing, the uncertainty of where the
    edge is) of a sharp edge, or the tip does not fit there, the target moves to the
    nearest cloud point (at most ``rules.shift_mm`` away) that is clear of every edge,
    tilted less than ``max_tilt_deg``, supported and where the tip fits — along the
    surface, onto the face beside the edge or away from the wall.
    A unit whose point fails for any other reason is dropped. The target is the unit
    projected on the local plane fit there; t = ``reference_dir`` projected on its
    tangent plane. Targets closer than ``rules.spacing_mm`` are merged (units that were
    not moved are kept first).
    """
    surf = _Surface(cloud_mm, normals, curvature, rules, np.asarray(up, dtype=float))
    units = np.asarray(units_mm, dtype=float)[:, :3]
    _, nearest = surf.tree.query(units, workers=-1)
    on_edge = surf.near_edge(nearest) | ~surf.tip_fits(nearest)
    chosen: list[tuple[int, int, bool]] = []  # (unit, cloud point, moved)
    for u, (i, edge) in enumerate(zip(nearest, on_edge)):
        if edge:
            j = _clear_point_nearby(surf, units[u])
        else:
            j = int(i) if surf.tilt_ok(np.array([i]))[0] and surf.supported(int(i)) else None
        if j is not None:
            chosen.append((u, j, bool(edge)))
    chosen.sort(key=lambda c: c[2])  # unmoved targets win the merge
    pts, nrms, flags, src = [], [], [], []
    for u, j, moved in chosen:
        p, n = surf.plane_at(j, units[u] if not moved else surf.points[j])
        if pts and np.min(np.linalg.norm(np.asarray(pts) - p, axis=1)) < rules.spacing_mm:
            continue
        pts.append(p)
        nrms.append(n)
        flags.append(moved)
        src.append(u)
    order = np.argsort(src, kind="stable")  # back in unit order
    points = np.asarray(pts, dtype=float).reshape(-1, 3)[order]
    nrm = np.asarray(nrms, dtype=float).reshape(-1, 3)[order]
    return Targets(points, nrm, scan_frames(nrm, reference_dir), np.asarray(flags, dtype=bool)[order],
                   np.asarray(src, dtype=np.int64)[order])


def _clear_point_nearby(surf: _Surface, unit_mm: np.ndarray) -> int | None:
    """Nearest cloud point to the unit that is clear of edges, not too steep, supported and
    where the tip fits."""
    cand = np.asarray(surf.tree.query_ball_point(unit_mm, surf.rules.shift_mm), dtype=np.int64)
    if cand.size == 0:
        return None
    cand = cand[surf.tilt_ok(cand) & ~surf.near_edge(cand)]
    # Nearest first; the density test is the expensive one, run it only until one passes.
    for j in cand[np.argsort(np.linalg.norm(surf.points[cand] - unit_mm, axis=1))]:
        if surf.supported(int(j)) and surf.tip_fits(np.array([j]))[0]:
            return int(j)
    return None


def _across_basis(up: np.ndarray) -> np.ndarray:
    """(2,3) orthonormal directions across the unit vector ``up``."""
    e1 = scan_direction(up, np.array([1.0, 0.0, 0.0]))   # falls back to a stable perpendicular
    return np.vstack([e1, np.cross(up, e1)])


def scan_frames(normals: np.ndarray, reference_dir: np.ndarray) -> np.ndarray:
    """Scan directions t (N,3): the reference direction (3,) or per target (N,3) projected
    on each tangent plane (geometry.scan_direction, the fixed rule of docs/design.md §3)."""
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    ref = np.broadcast_to(np.asarray(reference_dir, dtype=float), nrm.shape)
    return np.array([scan_direction(n, r) for n, r in zip(nrm, ref)]).reshape(-1, 3)


def face_runs_mm(cloud_mm: np.ndarray, points_mm: np.ndarray, normals: np.ndarray, directions: np.ndarray,
                 half_span_mm: float, strip_mm: float, bin_mm: float, max_slope: float,
                 max_gap_mm: float, cloud_tree: cKDTree | None = None) -> np.ndarray:
    """(T,2) how far (mm, capped at ``half_span_mm``) a scan line through each target along
    +d and -d stays on the target's face, judged on the cloud before any probe is planned.

    The cloud points within ``strip_mm`` of the line (measured in the tangent plane, across
    d) are binned ``bin_mm`` apart along d, each bin keeping its highest point along n (what
    a scanner looking down n sees). Walking out from the target, the face ends where the
    height steps by more than ``max_slope`` (rise over run: a rim rounding down into a
    wall, or a wall rising) or where the strip holds no point for more than ``max_gap_mm``
    (the cloud ends: an open border, a wall the sweep did not see; a narrower hole is the
    spacing of the sweep's lines). The same test the step
    measurement applies to the reference scan (profiles.probed_face), applied to the cloud.
    """
    cloud = np.asarray(cloud_mm, dtype=float)
    tree = cKDTree(cloud) if cloud_tree is None else cloud_tree
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    dirs = np.asarray(directions, dtype=float).reshape(-1, 3)
    n_bins = int(np.ceil(half_span_mm / bin_mm))
    runs = np.zeros((len(pts), 2))
    near = tree.query_ball_point(pts, half_span_mm + strip_mm) if len(pts) else []
    for i, idx in enumerate(near):
        rel = cloud[np.asarray(idx, dtype=np.int64)] - pts[i]
        across = np.cross(nrm[i], dirs[i])
        along = rel @ dirs[i]
        keep = np.abs(rel @ across) <= strip_mm
        for side, sign in enumerate((1.0, -1.0)):
            s = sign * along[keep]
            h = rel[keep] @ nrm[i]
            inside = (s >= 0.0) & (s < half_span_mm)
            runs[i, side] = _walk_face(s[inside], h[inside], bin_mm, n_bins, max_slope, max_gap_mm, half_span_mm)
    return runs


def _walk_face(s_mm: np.ndarray, h_mm: np.ndarray, bin_mm: float, n_bins: int, max_slope: float,
               max_gap_mm: float, half_span_mm: float) -> float:
    """One side of :func:`face_runs_mm`: the distance along the line to the face's last bin."""
    top = np.full(n_bins, -np.inf)
    np.maximum.at(top, np.minimum((s_mm / bin_mm).astype(np.int64), n_bins - 1), h_mm)
    seen = np.flatnonzero(np.isfinite(top))
    if seen.size == 0 or seen[0] * bin_mm > max_gap_mm:
        return 0.0
    last = seen[0]
    for k in seen[1:]:
        if (k - last - 1) * bin_mm > max_gap_mm or abs(top[k] - top[last]) > max_slope * (k - last) * bin_mm:
            return float(last * bin_mm)
        last = k
    return half_span_mm if (n_bins - 1 - last) * bin_mm <= max_gap_mm else float(last * bin_mm)


def border_scan_frames(cloud_mm: np.ndarray, points_mm: np.ndarray, normals: np.ndarray,
                       reference_dir: np.ndarray, half_span_mm: float, window_mm: float, strip_mm: float,
                       bin_mm: float, max_slope: float, max_gap_mm: float) -> np.ndarray:
    """Scan directions t (T,3): the fixed rule's (:func:`scan_frames`), turned a quarter turn
    about the normal where the line along it leaves the face within ``window_mm`` of the
    contact (the dent's window) and the line across it stays on longer (docs/design.md §3,
    "at a border the line turns").

    A line that runs off a rim within the dent's window keeps a few samples on one side:
    the reference is seen on one side only and the dent reads up to several times deeper
    than it is. Along the rim the same line stays on the face. Each direction is judged by
    its shorter side (:func:`face_runs_mm`); the turn is taken only when it gains more than
    ``strip_mm``, the width over which the cloud is pooled (the resolution of the
    judgement). A line that holds the window keeps the rule: a turned line meets the
    surface's own shape instead (an undulating sheet's troughs, seen along the waves, lost
    their dents at 7.5 N on 12 of 77 points of suite object 1008, where the rule's lines,
    leaving the face 14-31 mm out, saw them).
    """
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    t_ref = scan_frames(nrm, reference_dir)
    if len(nrm) == 0:
        return t_ref
    t_turn = np.cross(nrm, t_ref)
    tree = cKDTree(np.asarray(cloud_mm, dtype=float))
    runs_ref = face_runs_mm(cloud_mm, points_mm, nrm, t_ref, half_span_mm, strip_mm, bin_mm, max_slope,
                            max_gap_mm, tree)
    runs_turn = face_runs_mm(cloud_mm, points_mm, nrm, t_turn, half_span_mm, strip_mm, bin_mm, max_slope,
                             max_gap_mm, tree)
    short_ref = runs_ref.min(axis=1)
    turn = (short_ref < window_mm) & (runs_turn.min(axis=1) > short_ref + strip_mm)
    return np.where(turn[:, None], t_turn, t_ref)


def scan_frames_on_face(cloud_mm: np.ndarray, points_mm: np.ndarray, normals: np.ndarray,
                        reference_dir: np.ndarray, tip_radius_mm: float, half_span_mm: float,
                        window_mm: float) -> np.ndarray:
    """:func:`border_scan_frames` judged at the probe's scale: a strip and a gap allowance of
    one tip radius, bins of a fifth of it (the models' basis spacing), the measurement's
    face limit (profiles.MAX_FACE_SLOPE); ``half_span_mm`` is the profile's half-span,
    ``window_mm`` the half-width the survey's dent features are read over."""
    return border_scan_frames(cloud_mm, points_mm, normals, reference_dir, half_span_mm=half_span_mm,
                              window_mm=window_mm, strip_mm=tip_radius_mm, bin_mm=tip_radius_mm / 5.0,
                              max_slope=MAX_FACE_SLOPE, max_gap_mm=tip_radius_mm)


def surface_graph(targets_mm: np.ndarray, normals: np.ndarray, k: int = 6, radius_mm: float | None = None,
                  max_angle_deg: float = 30.0, cloud_mm: np.ndarray | None = None,
                  gap_mm: float = 3.0) -> list[tuple[int, int]]:
    """Neighbour pairs (i, j), i < j, of a k-NN graph that stays on the surface.

    A pair is kept when the normals agree within ``max_angle_deg``, the chord between
    the points runs along both tangent planes (its angle to each plane at most
    ``max_angle_deg``: no step from the box top down to the pillow), it is no longer
    than ``radius_mm`` (if given) and, with ``cloud_mm``, the points a quarter, half
    and three quarters along it lie within ``gap_mm`` of the cloud (no jump over a gap).
    """
    pts = np.asarray(targets_mm, dtype=float)
    nrm = np.asarray(normals, dtype=float)
    if pts.shape[0] < 2:
        return []
    kk = min(k + 1, pts.shape[0])
    dist, idx = cKDTree(pts).query(pts, k=kk)
    i = np.repeat(np.arange(pts.shape[0]), kk - 1)
    j = idx[:, 1:].ravel()
    d = dist[:, 1:].ravel()
    ok = np.isfinite(d) & (d > 0)
    if radius_mm is not None:
        ok &= d <= radius_mm
    cos_max, sin_max = np.cos(np.radians(max_angle_deg)), np.sin(np.radians(max_angle_deg))
    chord = pts[j] - pts[i]
    ok &= np.einsum("ij,ij->i", nrm[i], nrm[j]) >= cos_max
    ok &= np.abs(np.einsum("ij,ij->i", chord, nrm[i])) <= sin_max * d
    ok &= np.abs(np.einsum("ij,ij->i", chord, nrm[j])) <= sin_max * d
    if cloud_mm is not None:
        cloud_tree = cKDTree(np.asarray(cloud_mm, dtype=float))
        for f in (0.25, 0.5, 0.75):
            gap, _ = cloud_tree.query(pts[i] + f * chord, distance_upper_bound=gap_mm)
            ok &= np.isfinite(gap)
    pairs = {(int(min(a, b)), int(max(a, b))) for a, b in zip(i[ok], j[ok])}
    return sorted(pairs)
