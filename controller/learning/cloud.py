"""Point clouds of the object: loading, table removal, normals, curvature, registration (docs/design.md §7).

Units and frames: points in mm (N,3) float arrays in whatever frame they were given
(base or object frame); normals are unit vectors in the same frame. Curvature is the
dimensionless PCA surface variation. Poses are ``elastoprobe.controller.core.geometry.Pose``
(``parent <- child``, mm).

Everything random takes a seed, so the same input gives the same bytes.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..core.errors import InputError
from ..core.geometry import Pose, rotvec_to_matrix

_PCA_CHUNK = 131_072  # neighbourhoods per chunk: bounds memory at ~chunk*k*3 doubles
# A neighbourhood whose second PCA eigenvalue is under this fraction of its largest is a
# line, not a patch of surface (see _local_pca); it is widened at most _MAX_WIDEN times.
_LINE_RATIO = 0.1
_MAX_WIDEN = 3


# --------------------------------------------------------------------------- loading

def load_cloud(path: str | Path, n_samples: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a cloud or mesh file -> (points_mm (N,3) float64, normals (N,3) or None).

    Meshes (PLY/STL/OBJ/...) are sampled uniformly by area to ``n_samples`` points
    with ``seed``; their normals are the sampled faces' normals. Point clouds
    (PLY without faces, XYZ with 3 or 6 columns) are returned as stored; an XYZ file
    with 6 columns carries normals. Coordinates are taken to be in mm.
    """
    import trimesh  # heavy import, only when a file is really read

    p = Path(path)
    if not p.exists():
        raise InputError("cloud file not found", path=str(p))
    if p.suffix.lower() == ".xyz":
        return _load_xyz(p)
    try:
        loaded = trimesh.load(str(p), process=False)
    except Exception as exc:  # trimesh raises many types for a broken file
        raise InputError(f"cannot read cloud/mesh: {exc}", path=str(p)) from exc
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) > 0:
        return sample_mesh(loaded, n_samples, seed)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
    if vertices.ndim != 2 or vertices.shape[0] == 0:
        raise InputError("file holds no points", path=str(p))
    return vertices, _ply_normals(loaded, vertices.shape[0])


def _load_xyz(p: Path) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        data = np.loadtxt(p, ndmin=2, comments="#", delimiter=None)
    except ValueError as exc:
        raise InputError(f"bad XYZ file: {exc}", path=str(p)) from exc
    if data.shape[0] == 0 or data.shape[1] not in (3, 6):
        raise InputError(f"XYZ needs 3 or 6 columns per line, found {data.shape[1]}", path=str(p), line=1, col=1)
    if data.shape[1] == 6:
        return data[:, :3].copy(), _unit_rows(data[:, 3:6])
    return data.copy(), None


def _ply_normals(loaded: object, n_points: int) -> np.ndarray | None:
    """Vertex normals stored in a PLY point cloud (nx, ny, nz properties), if any."""
    raw = getattr(loaded, "metadata", {}).get("_ply_raw", {}) if hasattr(loaded, "metadata") else {}
    vertex = raw.get("vertex", {}).get("data") if isinstance(raw, dict) else None
    # ASCII PLY gives a dict of columns, binary PLY a structured array.
    names = vertex.keys() if isinstance(vertex, dict) else getattr(getattr(vertex, "dtype", None), "names", None)
    if not names or not all(k in names for k in ("nx", "ny", "nz")):
        return None
    normals = np.column_stack([vertex["nx"], vertex["ny"], vertex["nz"]]).astype(float)
    return _unit_rows(normals) if normals.shape[0] == n_points else None


def sample_mesh(mesh: object, n_samples: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples of a trimesh mesh -> (points_mm (n,3), face normals (n,3))."""
    import trimesh

    points, face_idx = trimesh.sample.sample_surface(mesh, int(n_samples), seed=seed)
    return np.asarray(points, dtype=float), np.asarray(mesh.face_normals, dtype=float)[face_idx]


def cloud_hash(points: np.ndarray) -> str:
    """Stable sha256 (hex) of the points' little-endian float32 bytes, C order."""
    data = np.ascontiguousarray(np.asarray(points), dtype="<f4")
    return hashlib.sha256(data.tobytes()).hexdigest()


# --------------------------------------------------------------------------- table

def fit_plane(points_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through points -> (unit normal, offset_mm) with n . x = offset."""
    centroid = points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(points_mm - centroid, full_matrices=False)
    normal = vt[-1]
    return normal, float(normal @ centroid)


def remove_table(points_mm: np.ndarray, distance_threshold_mm: float = 2.0, n_iter: int = 256,
                 seed: int = 0, up: np.ndarray | None = None, max_tilt_deg: float = 30.0,
                 min_height_mm: float | None = None, n_score: int = 20_000
                 ) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
    """Find the table by RANSAC and keep what stands on it.

    Returns (object_points (M,3) mm, (normal, offset_mm)) with ``normal . x = offset``
    on the table and the normal pointing to the object's side. The table is taken to
    be the plane with the most inliers (within ``distance_threshold_mm``); with ``up``
    given, only planes within ``max_tilt_deg`` of it are accepted and the normal is
    turned toward it. Kept points lie more than ``min_height_mm`` (default: the
    threshold) above the plane. Deterministic for a given ``seed``.
    """
    pts = np.asarray(points_mm, dtype=float)
    if pts.shape[0] < 3:
        raise ValueError("need at least 3 points to find a plane")
    rng = np.random.default_rng(seed)
    # Score candidate planes on a fixed random subset: counts are then comparable and cheap.
    score_pts = pts[rng.choice(pts.shape[0], size=min(n_score, pts.shape[0]), replace=False)]
    triples = pts[rng.integers(0, pts.shape[0], size=(n_iter, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9
    normals[ok] /= norm[ok, None]
    if up is not None:
        up_dir = np.asarray(up, dtype=float) / np.linalg.norm(up)
        ok &= np.abs(normals @ up_dir) >= np.cos(np.radians(max_tilt_deg))
    if not ok.any():
        raise ValueError("no plane candidate found (degenerate points or tilt limit)")
    offsets = np.einsum("ij,ij->i", normals, triples[:, 0])
    inlier_counts = (np.abs(score_pts @ normals.T - offsets) < distance_threshold_mm).sum(axis=0)
    counts = np.where(ok, inlier_counts, -1)
    best = int(np.argmax(counts))
    inliers = np.abs(pts @ normals[best] - offsets[best]) < distance_threshold_mm
    normal, offset = fit_plane(pts[inliers])
    signed = pts @ normal - offset
    outside = np.abs(signed) >= distance_threshold_mm
    if up is not None:
        flip = normal @ up_dir < 0
    else:
        # Without a hint, the object is on the side where most of the other points are.
        flip = outside.any() and np.sum(signed[outside] > 0) < np.sum(signed[outside] < 0)
    if flip:
        normal, offset, signed = -normal, -offset, -signed
    height = distance_threshold_mm if min_height_mm is None else min_height_mm
    return pts[signed > height], (normal, float(offset))


def standing_on_table(points_mm: np.ndarray, height_mm: np.ndarray, clear_mm: float, link_mm: float) -> np.ndarray:
    """(N,) which points belong to what stands on the table, given each point's height above
    the table plane (mm): those higher than ``clear_mm``, and the lower ones the object
    reaches down to, the foot of a face sloping onto the table.

    A point within ``clear_mm`` of the plane is kept when it lies above the table's own
    scatter and is joined to a point above ``clear_mm`` by a chain of such points, each
    within ``link_mm`` of the next. A sloped face reaches the table along a band of points
    rising steadily from it; the table's rare high readings lie apart, joined to nothing.
    Without the foot, a face meeting the table at 25 degrees loses a band 4 mm wide all
    along its rim (the suite's dome 1007: 7.5 % of its top).

    The table's level and scatter: the plane was fitted to every point within
    ``clear_mm``, the object's foot among them, which lifts it; the level is the median
    of the readings within 4 robust sigmas of it (three passes), and the scatter is read
    below the level, where only the table lies: twice the depth that all but 0.1 % of
    those readings stay above (a lone spike does not set it).
    """
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    h = np.asarray(height_mm, dtype=float).reshape(-1)
    clear = h > clear_mm
    near = h[np.abs(h) < clear_mm]
    if near.size == 0:
        return clear
    level = float(np.median(near))
    for _ in range(3):
        sigma = 1.4826 * float(np.median(np.abs(near - level)))
        level = float(np.median(near[np.abs(near - level) <= max(4.0 * sigma, 1e-9)]))
    below = level - near[near < level]
    floor_mm = level + 2.0 * float(np.quantile(below, 0.999)) if below.size else clear_mm
    low = np.flatnonzero(~clear & (h > floor_mm))
    keep = clear.copy()
    if low.size == 0 or not clear.any():
        return keep
    # The chain graph over the low points and the clear points within reach of one.
    high = np.flatnonzero(clear)
    to_low_mm, _ = cKDTree(pts[low]).query(pts[high], distance_upper_bound=link_mm)
    high = high[np.isfinite(to_low_mm)]
    nodes = np.concatenate([low, high])
    pairs = cKDTree(pts[nodes]).query_pairs(link_mm, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(nodes), len(nodes)))
    _, component = connected_components(graph, directed=False)
    grounded = np.zeros(component.max() + 1, dtype=bool)
    grounded[component[low.size:]] = True
    keep[low[grounded[component[:low.size]]]] = True
    return keep


# --------------------------------------------------------------------------- local geometry

def _unit_rows(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def _pca_of_neighbourhoods(pts: np.ndarray, tree: cKDTree, rows: np.ndarray, k: int,
                           evals: np.ndarray, normals: np.ndarray) -> None:
    """k-NN covariance eigenvalues (ascending) and smallest eigenvectors of ``pts[rows]``, in place."""
    for start in range(0, rows.size, _PCA_CHUNK):
        sel = rows[start:start + _PCA_CHUNK]
        _, idx = tree.query(pts[sel], k=k, workers=-1)
        nb = pts[idx]
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred) / k
        w, v = np.linalg.eigh(cov)
        evals[sel] = np.clip(w, 0.0, None)
        normals[sel] = v[:, :, 0]


def _local_pca(points_mm: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (N,3) ascending and smallest-eigenvalue eigenvectors (N,3) of k-NN covariances.

    A laser-line raster samples the surface far more densely along a profile (~0.5 mm)
    than across profiles (the sweep spacing, ~4 mm): the k nearest neighbours of a point
    can all lie on its own profile line. A line has no normal — the smallest-variance
    direction is then any direction across it (on the demo's box top, mostly the sweep
    direction: a horizontal "normal" that made the top count as a wall). Such a
    neighbourhood (second eigenvalue under ``_LINE_RATIO`` of the largest: a spread
    across the line under ~1/3 of the spread along it) is widened, doubling k up to
    ``_MAX_WIDEN`` times, until it reaches the neighbouring lines.
    """
    pts = np.asarray(points_mm, dtype=float)
    k = int(min(max(k, 3), pts.shape[0]))
    tree = cKDTree(pts)
    evals = np.empty((pts.shape[0], 3))
    normals = np.empty((pts.shape[0], 3))
    rows = np.arange(pts.shape[0])
    _pca_of_neighbourhoods(pts, tree, rows, k, evals, normals)
    for _ in range(_MAX_WIDEN):
        rows = rows[evals[rows, 1] < _LINE_RATIO * evals[rows, 2]]
        if rows.size == 0 or k >= pts.shape[0]:
            break
        k = int(min(2 * k, pts.shape[0]))
        _pca_of_neighbourhoods(pts, tree, rows, k, evals, normals)
    return evals, normals


def local_plane(points_mm: np.ndarray, tree: cKDTree, i: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane fit to the k nearest points of point i, widened as :func:`_local_pca` widens a
    neighbourhood that is one profile line -> (centroid (3,), eigenvalues (3,) ascending,
    eigenvectors (3,3) as columns; the first is the plane's normal, unoriented)."""
    n_pts = points_mm.shape[0]
    k = min(k, n_pts)
    for widen in range(_MAX_WIDEN + 1):
        _, nb = tree.query(points_mm[i], k=k)
        pts = points_mm[np.atleast_1d(nb)]
        centroid = pts.mean(axis=0)
        vals, vecs = np.linalg.eigh(np.cov((pts - centroid).T))
        if vals[1] >= _LINE_RATIO * vals[2] or k >= n_pts or widen == _MAX_WIDEN:
            break
        k = min(2 * k, n_pts)
    return centroid, vals, vecs


def orient_normals(points_mm: np.ndarray, normals: np.ndarray, viewpoint_mm: np.ndarray | None = None
                   ) -> np.ndarray:
    """Flip normals toward ``viewpoint_mm`` or, without one, away from the points' centroid."""
    if viewpoint_mm is not None:
        toward = np.asarray(viewpoint_mm, dtype=float) - points_mm
    else:
        toward = points_mm - points_mm.mean(axis=0)
    sign = np.where(np.einsum("ij,ij->i", normals, toward) < 0, -1.0, 1.0)
    return normals * sign[:, None]


def local_geometry(points_mm: np.ndarray, k: int = 16, viewpoint_mm: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Normals and curvature from one k-NN PCA pass -> (normals (N,3) oriented, curvature (N,))."""
    evals, normals = _local_pca(points_mm, k)
    return orient_normals(np.asarray(points_mm, float), normals, viewpoint_mm), _surface_variation(evals)


def _surface_variation(evals: np.ndarray) -> np.ndarray:
    total = evals.sum(axis=1)
    return np.where(total > 0, evals[:, 0] / np.where(total > 0, total, 1.0), 0.0)


def estimate_normals(points_mm: np.ndarray, k: int = 16, viewpoint_mm: np.ndarray | None = None) -> np.ndarray:
    """PCA normals (N,3), unit, oriented toward ``viewpoint_mm`` or outward from the centroid."""
    return local_geometry(points_mm, k, viewpoint_mm)[0]


def curvature(points_mm: np.ndarray, k: int = 16) -> np.ndarray:
    """Surface variation lambda0 / (lambda0 + lambda1 + lambda2) of k-NN covariances (N,), in [0, 1/3]."""
    return _surface_variation(_local_pca(points_mm, k)[0])


# --------------------------------------------------------------------------- registration

def _kabsch(src: np.ndarray, dst: np.ndarray) -> Pose:
    """Least-squares rigid ``dst <- src`` for paired points."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    h = (src - cs).T @ (dst - cd)
    u, _, vt = np.linalg.svd(h)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ s @ u.T
    return Pose(cd - r @ cs, r)


def _point_to_plane_step(src: np.ndarray, dst: np.ndarray, nrm: np.ndarray) -> Pose:
    """One linearised point-to-plane step: small rotation w and translation t minimising
    sum(((I + [w]x) p + t - q) . n)^2."""
    a = np.hstack([np.cross(src, nrm), nrm])
    b = -np.einsum("ij,ij->i", src - dst, nrm)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    return Pose(x[3:], rotvec_to_matrix(x[:3]))


def icp(source_points: np.ndarray, target_points: np.ndarray, init: Pose | None = None, max_iter: int = 50,
        tol: float = 1e-4, target_normals: np.ndarray | None = None, trim_fraction: float = 0.1,
        max_distance_mm: float | None = None, tree: cKDTree | None = None) -> tuple[Pose, float, int]:
    """Rigid ICP -> (Pose target <- source, rms_mm, iterations).

    Point-to-plane when ``target_normals`` are given, point-to-point (Kabsch) otherwise.
    Each iteration pairs every source point with its nearest target point (cKDTree),
    drops the worst ``trim_fraction`` of the pairs and any farther than
    ``max_distance_mm`` (outliers, parts only one cloud has), and solves. Stops when the
    step moves less than ``tol`` (mm, and rad x 100 mm). ``rms_mm`` is over the kept
    pairs: point-to-plane distances with normals, point-to-point otherwise.
    """
    src = np.asarray(source_points, dtype=float)
    dst = np.asarray(target_points, dtype=float)
    kd = tree if tree is not None else cKDTree(dst)
    pose = init if init is not None else Pose.identity()
    rms = float("inf")
    it = 0
    for it in range(1, max_iter + 1):
        moved = pose.apply(src)
        dist, idx = kd.query(moved, workers=-1)
        keep = _trimmed(dist, trim_fraction, max_distance_mm)
        if keep.sum() < 6:
            break
        if target_normals is not None:
            step = _point_to_plane_step(moved[keep], dst[idx[keep]], target_normals[idx[keep]])
        else:
            step = _kabsch(moved[keep], dst[idx[keep]])
        pose = step.compose(pose)
        shift_mm, turn_deg = step.distance_to(Pose.identity())
        if shift_mm + np.radians(turn_deg) * 100.0 < tol:
            break
    moved = pose.apply(src)
    dist, idx = kd.query(moved, workers=-1)
    keep = _trimmed(dist, trim_fraction, max_distance_mm)
    if target_normals is not None:
        res = np.einsum("ij,ij->i", moved[keep] - dst[idx[keep]], target_normals[idx[keep]])
    else:
        res = dist[keep]
    if res.size:
        rms = float(np.sqrt(np.mean(res**2)))
    return pose, rms, it


def _trimmed(dist: np.ndarray, trim_fraction: float, max_distance_mm: float | None) -> np.ndarray:
    keep = np.ones(dist.shape[0], dtype=bool)
    if trim_fraction > 0:
        keep &= dist <= np.quantile(dist, 1.0 - trim_fraction)
    if max_distance_mm is not None:
        keep &= dist <= max_distance_mm
    return keep


def _pca_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((points - c).T))
    vecs = vecs[:, ::-1]  # major axis first
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] *= -1
    return c, vecs


REGISTRATION_GATE_MM = 3.0     # a scanned point farther than this from the mesh is not on it


def truncated_cost_mm2(points: np.ndarray, mesh_from_cloud: Pose, mesh_pts: np.ndarray, mesh_nrm: np.ndarray,
                       tree: cKDTree, gate_mm: float = REGISTRATION_GATE_MM) -> float:
    """How well a placement fits every scanned point (mm^2): the mean over ``points`` of the squared
    point-to-plane distance, capped at ``gate_mm`` squared for points off the mesh. Unlike a trimmed
    RMS, a pose that leaves a few constraining points (an edge, a wall) off the surface pays for them."""
    moved = mesh_from_cloud.apply(points)
    dist, idx = tree.query(moved, workers=-1)
    plane = np.einsum("ij,ij->i", moved - mesh_pts[idx], mesh_nrm[idx])
    return float(np.mean(np.where(dist < gate_mm, plane**2, gate_mm**2)))


def refine_untrimmed(points: np.ndarray, mesh_pts: np.ndarray, mesh_nrm: np.ndarray, tree: cKDTree,
                     mesh_from_cloud: Pose, max_iter: int = 60, gate_mm: float = REGISTRATION_GATE_MM) -> Pose:
    """Point-to-plane ICP from a pose already near the answer, pairing every point within ``gate_mm``
    (none trimmed): the last refinement after trimmed ICP has found the basin."""
    pose, _, _ = icp(points, mesh_pts, mesh_from_cloud, max_iter, 1e-6, mesh_nrm, 0.0, gate_mm, tree=tree)
    return pose


def register_mesh_to_cloud(mesh: object, cloud_points: np.ndarray, init: Pose | None = None,
                           n_mesh_samples: int = 60_000, n_cloud_samples: int = 20_000, seed: int = 0,
                           max_iter: int = 60, trim_fraction: float = 0.2) -> tuple[Pose, float]:
    """Pose of a trimesh mesh in the cloud's frame -> (Pose cloud <- mesh, rms_mm).

    The cloud (often a partial, top-down view) is registered onto dense samples of
    the whole mesh, point-to-plane with the face normals, so mesh parts the scanner
    never saw cost nothing. Starts tried: ``init``, the centroid shift, and the
    four proper PCA-axis alignments; a short ICP from each, the best refined.
    """
    mesh_pts, mesh_nrm = sample_mesh(mesh, n_mesh_samples, seed)
    cloud = np.asarray(cloud_points, dtype=float)
    rng = np.random.default_rng(seed)
    cloud = cloud[rng.permutation(cloud.shape[0])[:n_cloud_samples]]
    tree = cKDTree(mesh_pts)
    c_mesh, e_mesh = _pca_frame(mesh_pts)
    c_cloud, e_cloud = _pca_frame(cloud)
    starts: list[Pose] = [] if init is None else [init.inverse()]  # mesh <- cloud
    starts.append(Pose(c_mesh - c_cloud, np.eye(3)))
    for signs in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1)):
        r = e_mesh @ np.diag(signs) @ e_cloud.T
        starts.append(Pose(c_mesh - r @ c_cloud, r))
    # Coarse trials on a few thousand points: far-off starts make k-d tree queries slow.
    coarse = cloud[: min(cloud.shape[0], 3_000)]  # already in random order
    trials = [icp(coarse, mesh_pts, s, 15, 1e-3, mesh_nrm, trim_fraction, tree=tree) for s in starts]
    best_start = min(trials, key=lambda tr: tr[1])[0]
    pose, rms, _ = icp(cloud, mesh_pts, best_start, max_iter, 1e-5, mesh_nrm, trim_fraction, tree=tree)
    # Trimming keeps parts only the cloud has (table remnants, clutter) out of the fit, but
    # on a scene of large planes it can also drop the few edge points that stop a slide
    # along them: the fit then rests at a pose slid along the planes (7.7 mm on the box on
    # the pillow) with a trimmed RMS nearly as good. Refine again with every point within
    # the gate, and keep whichever pose fits every point better.
    refined = refine_untrimmed(cloud, mesh_pts, mesh_nrm, tree, pose, max_iter)
    if truncated_cost_mm2(cloud, refined, mesh_pts, mesh_nrm, tree) < truncated_cost_mm2(cloud, pose, mesh_pts,
                                                                                         mesh_nrm, tree):
        pose = refined
        _, rms, _ = icp(cloud, mesh_pts, pose, 0, 1e-5, mesh_nrm, trim_fraction, tree=tree)
    return pose.inverse(), rms


# --------------------------------------------------------------------------- synthetic surface

def box_on_pillow_mesh(pillow_mm: tuple[float, float, float] = (400.0, 300.0, 80.0),
                       box_mm: tuple[float, float, float] = (150.0, 100.0, 60.0),
                       grid_mm: float = 5.0, box_centre_mm: tuple[float, float] = (0.0, 0.0)) -> object:
    """A composite-like test surface (trimesh): a cardboard box resting on a foam pillow.

    Object frame: table at z = 0, +z up, pillow centred on the origin with a flat-ish
    top of height ``pillow_mm[2]`` falling steeply to the table at its rim
    (z = H * sqrt(1 - u^4) * sqrt(1 - v^4)); a box of ``box_mm`` (x, y, height) on
    top centred at ``box_centre_mm`` (x, y; off-centre breaks the symmetry that would make
    a registration ambiguous), its walls sunk a little into the pillow. Open surface as a top-down scanner
    sees it (no underside); face normals point outward. For tests and benches.
    """
    import trimesh

    a, b, h = (0.5 * pillow_mm[0], 0.5 * pillow_mm[1], pillow_mm[2])
    bx, by, bh = 0.5 * box_mm[0], 0.5 * box_mm[1], box_mm[2]
    cx, cy = box_centre_mm

    def pillow_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        fx = np.sqrt(np.clip(1.0 - (x / a) ** 4, 0.0, None))
        fy = np.sqrt(np.clip(1.0 - (y / b) ** 4, 0.0, None))
        return h * fx * fy

    xs = np.linspace(-a, a, int(round(2 * a / grid_mm)) + 1)
    ys = np.linspace(-b, b, int(round(2 * b / grid_mm)) + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    verts = np.column_stack([gx.ravel(), gy.ravel(), pillow_z(gx, gy).ravel()])
    nx = xs.size
    i, j = np.meshgrid(np.arange(ys.size - 1), np.arange(nx - 1), indexing="ij")
    v00 = (i * nx + j).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx, v00 + nx + 1
    faces = np.vstack([np.column_stack([v00, v10, v11]), np.column_stack([v00, v11, v01])])  # CCW from above
    centres = verts[faces].mean(axis=1)
    under_box = (np.abs(centres[:, 0] - cx) < bx) & (np.abs(centres[:, 1] - cy) < by)
    pillow = trimesh.Trimesh(verts, faces[~under_box], process=False)

    corners_x, corners_y = np.array([cx - bx, cx + bx]), np.array([cy - by, cy + by])
    seat = float(pillow_z(*np.meshgrid(corners_x, corners_y)).min())  # lowest pillow point under the box
    top = float(h + bh)
    box = trimesh.creation.box(bounds=[[cx - bx, cy - by, seat - 1.0], [cx + bx, cy + by, top]])
    keep = box.face_normals[:, 2] > -0.5  # drop the bottom: it lies inside the pillow
    box = trimesh.Trimesh(box.vertices, box.faces[keep], process=False)
    return trimesh.util.concatenate([pillow, box])
