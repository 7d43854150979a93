"""Honest metrics against the simulator's ground truth.

Profiles: RMSE in mm against the noise-free truth over a region of interest (ROI):
by default, per profile, the samples where the true depth exceeds ``ROI_FRACTION``
of that profile's true peak (the dent and its rim; the flat far field would dilute
the error), or any mask the caller passes (e.g. a fixed |x| window). The noise floor
is the same RMSE of the averaged measured profiles themselves, the best a model
trained on them can be expected to reach.

Region maps: scored over the points the caller passes, after optimal matching of
predicted to true labels (Hungarian, maximising the matched area). The reference is the
object's true top (:func:`truth_surface_scores`: samples of the true surface at a fixed
density, the session's labels carried onto them, coverage beside); the same scores over
the reachable scanned cloud itself remain a secondary figure.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
from scipy.optimize import linear_sum_assignment

from .profiles import MAX_FACE_SLOPE, mirror, mirror_angle_deg

ROI_FRACTION = 0.05


def roi_mask(truth_mm: np.ndarray, fraction: float = ROI_FRACTION) -> np.ndarray:
    """(K,L) True where the true depth exceeds ``fraction`` of that profile's true peak."""
    t = np.atleast_2d(np.asarray(truth_mm, dtype=float))
    peak = np.nanmax(np.where(np.isfinite(t), t, -np.inf), axis=1, keepdims=True)
    return np.isfinite(t) & (t > fraction * np.maximum(peak, 0.0)) & (peak > 0)


def profile_face_mask(truth: Any, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, x_mm: np.ndarray,
                      max_slope: float = MAX_FACE_SLOPE) -> np.ndarray:
    """(L,) where a profile's true surface is defined: the samples x along the line
    point + x t whose nearest true surface is the contact's own material, facing within
    atan(``max_slope``) of its normal, reached from the contact without a step steeper
    than ``max_slope`` (the same rule the measurement uses for the probed face).

    Past the object's rim, or where the line runs onto another part (a box on a
    pillow), the analytic dent of the contact says nothing true: those samples are not
    scored (their share is reported). ``truth`` needs ``closest_surface(points) ->
    (points, normals, labels)``.
    """
    p = np.asarray(point_mm, dtype=float)
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    tt = np.asarray(t, dtype=float) / np.linalg.norm(t)
    x = np.asarray(x_mm, dtype=float)
    closest, normals, labels = truth.closest_surface(p[None, :] + x[:, None] * tt[None, :])
    _, _, own = truth.closest_surface(p[None, :])
    h = (closest - p) @ n
    facing = normals @ n >= 1.0 / np.sqrt(1.0 + max_slope ** 2)
    ok = (labels == own[0]) & facing & np.isfinite(h)
    out = np.zeros(x.shape, dtype=bool)
    start = int(np.argmin(np.abs(x)))
    if not ok[start]:
        return out
    out[start] = True
    for step in (1, -1):
        k = start
        while 0 <= k + step < x.size and ok[k + step] and abs(h[k + step] - h[k]) <= max_slope * abs(x[k + step] - x[k]):
            k += step
            out[k] = True
    return out


def window_mask(x_mm: np.ndarray, half_width_mm: float) -> np.ndarray:
    """(L,) a fixed ROI |x| <= half_width_mm."""
    return np.abs(np.asarray(x_mm, dtype=float)) <= half_width_mm


def _rms(diff: np.ndarray, mask: np.ndarray) -> float | None:
    ok = mask & np.isfinite(diff)
    if not ok.any():
        return None
    return float(np.sqrt(np.mean(diff[ok] ** 2)))


def profile_rmse_mm(predicted_mm: np.ndarray, truth_mm: np.ndarray,
                    roi: np.ndarray | None = None) -> float | None:
    """RMSE (mm) of predicted (K,L) against noise-free truth (K,L) over the ROI.

    ``roi`` (K,L) or (L,) boolean; default :func:`roi_mask` of the truth. Samples where
    the prediction is NaN are excluded (report coverage beside the RMSE when predictions
    can be NaN, e.g. averaged measurements). None if nothing is left to score.
    """
    p = np.atleast_2d(np.asarray(predicted_mm, dtype=float))
    t = np.atleast_2d(np.asarray(truth_mm, dtype=float))
    mask = roi_mask(t) if roi is None else np.broadcast_to(np.asarray(roi, dtype=bool), t.shape)
    return _rms(p - t, mask)


def noise_floor_mm(averaged_mm: np.ndarray, truth_mm: np.ndarray, roi: np.ndarray | None = None) -> float | None:
    """RMS (mm) of the averaged measured profiles against the truth over the ROI (NaN ignored)."""
    return profile_rmse_mm(averaged_mm, truth_mm, roi)


def _predict(model: Any, forces_n: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    if callable(model) and not hasattr(model, "predict_batch_mm"):
        return np.asarray(model(forces_n, angles_deg), dtype=float)
    return model.predict_batch_mm(forces_n, angles_deg)


def mirror_residuals(model: Any, forces_n: np.ndarray, angles_deg: np.ndarray,
                     x_mm: np.ndarray | None = None) -> np.ndarray:
    """(F,A) relative mirror residuals: RMS over the grid of p(F, α) − mirror(p(F, 180° − α))
    divided by the larger peak depth of the two profiles (unitless; 0 = perfect mirror).

    ``model``: a RegionModel, or a callable (forces (Q,), angles (Q,)) -> (Q,L) with ``x_mm``.
    """
    x = np.asarray(x_mm if x_mm is not None else model.x_mm, dtype=float)
    f = np.asarray(forces_n, dtype=float).reshape(-1)
    a = np.asarray(angles_deg, dtype=float).reshape(-1)
    ff, aa = np.meshgrid(f, a, indexing="ij")
    p = _predict(model, ff.ravel(), aa.ravel())
    q = mirror(_predict(model, ff.ravel(), mirror_angle_deg(aa.ravel())), x)
    peak = np.maximum(np.nanmax(p, axis=1), np.nanmax(q, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.sqrt(np.nanmean((p - q) ** 2, axis=1)) / peak
    rel = np.where(peak > 0, rel, np.nan)
    return rel.reshape(ff.shape)


def mirror_residual(model: Any, forces_n: np.ndarray, angles_deg: np.ndarray,
                    x_mm: np.ndarray | None = None) -> float:
    """The mean of :func:`mirror_residuals` (unitless)."""
    return float(np.nanmean(mirror_residuals(model, forces_n, angles_deg, x_mm)))


def depth_monotone_in_force(model: Any, forces_n: np.ndarray, angles_deg: np.ndarray,
                            tol_mm: float = 1e-3, roi_fraction: float = 0.25,
                            x_mm: np.ndarray | None = None) -> dict[str, float]:
    """Does depth grow with force? For each angle, over increasing ``forces_n``:

    ``peak_fraction``: share of consecutive force pairs whose peak depth does not drop by
    more than ``tol_mm``; ``sample_fraction``: the same per sample, over the samples where
    the deepest-force profile exceeds ``roi_fraction`` of its peak (the dent itself: the
    rim may legitimately move as a tangential load shifts the dent).
    """
    f = np.sort(np.asarray(forces_n, dtype=float).reshape(-1))
    a = np.asarray(angles_deg, dtype=float).reshape(-1)
    ok_peak = ok_samples = n_peak = n_samples = 0
    for ang in a:
        p = _predict(model, f, np.full_like(f, ang))
        peaks = np.nanmax(p, axis=1)
        ok_peak += int(np.sum(np.diff(peaks) >= -tol_mm))
        n_peak += f.shape[0] - 1
        roi = p[-1] > roi_fraction * peaks[-1]
        step = np.diff(p[:, roi], axis=0)
        ok_samples += int(np.sum(step >= -tol_mm))
        n_samples += step.size
    return {"peak_fraction": ok_peak / n_peak if n_peak else 1.0,
            "sample_fraction": ok_samples / n_samples if n_samples else 1.0}


def unseen_force_between(model: Any, trained_forces_n: np.ndarray, angles_deg: np.ndarray,
                         roi: Callable[[float, float, np.ndarray], np.ndarray] | None = None,
                         tol_mm: float = 0.0, x_mm: np.ndarray | None = None) -> dict[str, Any]:
    """Does a profile predicted at an unseen force lie between the profiles at the two
    trained forces around it, at every sample of the region of interest?

    For each angle and each consecutive pair of ``trained_forces_n``, the midpoint force's
    prediction is compared sample by sample with the lower and upper forces' predictions
    over ``roi(force_mid, angle, upper_profile) -> (L,) bool`` (default: the upper
    profile deeper than ``ROI_FRACTION`` of its peak). A sample is between when
    min(lo, hi) − tol ≤ mid ≤ max(lo, hi) + tol. Returns ``fraction`` of ROI samples
    between, ``worst_mm`` (largest excursion outside, mm), ``cases`` checked and
    ``failed_cases`` [(force_mid, angle, samples outside)].
    """
    f = np.sort(np.asarray(trained_forces_n, dtype=float).reshape(-1))
    inside = total = 0
    worst = 0.0
    failed: list[tuple[float, float, int]] = []
    cases = 0
    for ang in np.asarray(angles_deg, dtype=float).reshape(-1):
        for lo_f, hi_f in zip(f, f[1:]):
            mid_f = 0.5 * (lo_f + hi_f)
            p = _predict(model, np.array([lo_f, mid_f, hi_f]), np.full(3, ang))
            mask = (roi(mid_f, float(ang), p[2]) if roi is not None
                    else roi_mask(p[2][None, :])[0])
            low, high = np.minimum(p[0], p[2]), np.maximum(p[0], p[2])
            excursion = np.maximum(low - p[1], p[1] - high)[mask]
            out = int(np.sum(excursion > tol_mm))
            inside += int(mask.sum()) - out
            total += int(mask.sum())
            worst = max(worst, float(excursion.max(initial=0.0)))
            cases += 1
            if out:
                failed.append((float(mid_f), float(ang), out))
    return {"fraction": inside / total if total else 1.0, "worst_mm": worst, "cases": cases,
            "failed_cases": failed}


# -- region maps ---------------------------------------------------------------------------------

def boundary_points(labels: np.ndarray, positions_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Indices of points with a differently-labelled point within ``radius_mm``."""
    from scipy.spatial import cKDTree

    lab = np.asarray(labels)
    pos = np.asarray(positions_mm, dtype=float)
    tree = cKDTree(pos)
    pairs = tree.query_pairs(radius_mm, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros(0, dtype=np.int64)
    diff = pairs[lab[pairs[:, 0]] != lab[pairs[:, 1]]]
    return np.unique(diff.ravel())


def default_radius_mm(positions_mm: np.ndarray) -> float:
    """1.5 x the median nearest-neighbour spacing of the points."""
    from scipy.spatial import cKDTree

    pos = np.asarray(positions_mm, dtype=float)
    d, _ = cKDTree(pos).query(pos, k=2)
    return 1.5 * float(np.median(d[:, 1]))


def region_map_scores(pred_labels: np.ndarray, true_labels: np.ndarray, area_weights: np.ndarray | None,
                      positions_mm: np.ndarray, radius_mm: float | None = None) -> dict[str, Any]:
    """Score a predicted region map against the true material labels.

    All arrays are over the same points (the reachable scanned surface only); ``area_weights``
    (P,) the surface area each point stands for (None = equal). Predicted labels are matched
    to true ones by the assignment maximising the matched area; unmatched predicted regions
    (more predicted than true) count as mislabelled, unmatched true regions get IoU 0.

    Returns ``mislabelled_fraction`` (area), ``per_region_iou`` {true label: IoU},
    ``worst_region_iou``, ``matching`` {pred: true}, and the boundary distance in mm both
    ways (every predicted boundary point to the nearest true one and vice versa, pooled):
    ``boundary_mm_mean``, ``boundary_mm_p90`` — 0 when neither map has a boundary, None
    when only one has. A boundary point has a differently-labelled point within
    ``radius_mm`` (default 1.5 x the median point spacing), so distances resolve no finer
    than the point spacing.
    """
    from scipy.spatial import cKDTree

    pred = np.asarray(pred_labels).reshape(-1)
    true = np.asarray(true_labels).reshape(-1)
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    w = np.ones(pred.shape[0]) if area_weights is None else np.asarray(area_weights, dtype=float).reshape(-1)
    if not (pred.shape == true.shape == w.shape) or pos.shape[0] != pred.shape[0]:
        raise ValueError("labels, weights and positions must cover the same points")
    p_ids, p_inv = np.unique(pred, return_inverse=True)
    t_ids, t_inv = np.unique(true, return_inverse=True)
    overlap = np.zeros((p_ids.size, t_ids.size))
    np.add.at(overlap, (p_inv, t_inv), w)
    rows, cols = linear_sum_assignment(overlap, maximize=True)
    total = float(w.sum())
    matched = float(overlap[rows, cols].sum())
    area_p = overlap.sum(axis=1)
    area_t = overlap.sum(axis=0)
    per_iou: dict[Any, float] = {t.item(): 0.0 for t in t_ids}
    for r, c in zip(rows, cols):
        inter = overlap[r, c]
        union = area_p[r] + area_t[c] - inter
        per_iou[t_ids[c].item()] = float(inter / union) if union > 0 else 0.0

    radius = default_radius_mm(pos) if radius_mm is None else float(radius_mm)
    bp = boundary_points(pred, pos, radius)
    bt = boundary_points(true, pos, radius)
    if bp.size == 0 and bt.size == 0:
        b_mean: float | None = 0.0
        b_p90: float | None = 0.0
    elif bp.size == 0 or bt.size == 0:
        b_mean = b_p90 = None
    else:
        d_pt, _ = cKDTree(pos[bt]).query(pos[bp])
        d_tp, _ = cKDTree(pos[bp]).query(pos[bt])
        both = np.concatenate([d_pt, d_tp])
        b_mean, b_p90 = float(both.mean()), float(np.percentile(both, 90))
    return {
        "mislabelled_fraction": max(0.0, (total - matched) / total) if total > 0 else None,
        "worst_region_iou": min(per_iou.values()) if per_iou else None,
        "per_region_iou": per_iou,
        "matching": {p_ids[r].item(): t_ids[c].item() for r, c in zip(rows, cols)},
        "n_pred_regions": int(p_ids.size),
        "n_true_regions": int(t_ids.size),
        "boundary_mm_mean": b_mean,
        "boundary_mm_p90": b_p90,
        "boundary_radius_mm": radius,
    }


# -- region maps on the true surface --------------------------------------------------------------

COVERED_MM = 2.0              # a surface point this close to a cloud point counts as scanned
CARRY_MAX_ANGLE_DEG = 20.0    # labels come from cloud points facing within this of the surface point
CARRY_K = 16                  # nearest cloud points tried before the per-orientation search
_NORMAL_BIN = 0.1             # per-orientation search: surface normals binned by (n_x, n_y) in steps of this
# Uncovered samples take labels along the surface over steps up to this many sample spacings:
# neighbouring samples of a face tilted up to 60 degrees (sqrt(2) / cos 60 = 2.8), not a wall.
SPREAD_STEP_SPACINGS = 3.0


def carry_labels(surface_points_mm: np.ndarray, surface_normals: np.ndarray, cloud_points_mm: np.ndarray,
                 cloud_normals: np.ndarray, cloud_labels: np.ndarray,
                 max_angle_deg: float = CARRY_MAX_ANGLE_DEG) -> tuple[np.ndarray, np.ndarray]:
    """The map a user holds, read at surface points: (labels (S,), distance (S,) mm to the cloud
    point each label was carried from).

    Each surface point takes the label of the nearest cloud point (in space) whose normal
    lies within ``max_angle_deg`` of the surface point's own: a point of the same face.
    At a fold the cloud's PCA normals blend the two faces over a few points, and those
    points lie nearer to the foot of a wall than the top's next sweep profile does; the
    session's own map never carries a label across a fold (learning/surface_map.py), and
    neither does this. 20 degrees is about four times the normal noise of the darkest
    shipped material's cloud (0.12 mm over a 3 mm neighbourhood) and far below the turn
    of a fold. Every surface point gets a label, however far its source (an unscanned
    band is labelled from the nearest scanned point of its face); the distance says how
    far that was. The nearest ``CARRY_K`` cloud points are tried first; a point with no
    such neighbour (beside a wall, all its neighbours on the wall) is searched among the
    cloud points facing within ``max_angle_deg`` of its orientation bin (surface normals
    binned by (n_x, n_y), steps of 0.1: the angle holds to about +-3 degrees there), and
    among all cloud points when none faces that way.
    """
    from scipy.spatial import cKDTree

    sp = np.asarray(surface_points_mm, dtype=float).reshape(-1, 3)
    sn = np.asarray(surface_normals, dtype=float).reshape(-1, 3)
    cloud = np.asarray(cloud_points_mm, dtype=float).reshape(-1, 3)
    cn = np.asarray(cloud_normals, dtype=float).reshape(-1, 3)
    labels_in = np.asarray(cloud_labels).reshape(-1)
    cos_max = float(np.cos(np.radians(max_angle_deg)))
    k = min(CARRY_K, cloud.shape[0])
    dist, idx = cKDTree(cloud).query(sp, k=k)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    facing = np.einsum("skj,sj->sk", cn[idx], sn) >= cos_max
    found = facing.any(axis=1)
    first = np.argmax(facing, axis=1)
    rows = np.arange(sp.shape[0])
    out_idx = idx[rows, first]
    out_dist = dist[rows, first]
    rest = np.flatnonzero(~found)
    if rest.size:
        bins, which = np.unique(np.round(sn[rest, :2] / _NORMAL_BIN).astype(np.int64), axis=0, return_inverse=True)
        for b in range(bins.shape[0]):
            members = rest[which.reshape(-1) == b]
            centre = sn[members].mean(axis=0)
            centre /= max(float(np.linalg.norm(centre)), 1e-12)
            source = np.flatnonzero(cn @ centre >= cos_max)
            if source.size == 0:
                source = np.arange(cloud.shape[0])
            d, i = cKDTree(cloud[source]).query(sp[members])
            out_idx[members], out_dist[members] = source[i], d
    return labels_in[out_idx], out_dist


def spread_along_surface(points_mm: np.ndarray, labels: np.ndarray, known: np.ndarray,
                         step_mm: float) -> np.ndarray:
    """Labels (P,) where every point not ``known`` takes the label of the nearest known point
    ALONG the sampled surface: a walk over neighbouring samples (closer than ``step_mm`` in
    space), which cannot climb a wall higher than that. Points with no known point on their
    piece of surface keep their own label."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    out = np.asarray(labels).reshape(-1).copy()
    sources = np.flatnonzero(known)
    if sources.size == 0 or sources.size == pts.shape[0]:
        return out
    pairs = cKDTree(pts).query_pairs(step_mm, output_type="ndarray")
    length = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
    n = pts.shape[0]
    graph = coo_matrix((np.concatenate([length, length]), (np.concatenate([pairs[:, 0], pairs[:, 1]]),
                                                           np.concatenate([pairs[:, 1], pairs[:, 0]]))),
                       shape=(n, n)).tocsr()
    _, _, nearest = dijkstra(graph, indices=sources, min_only=True, return_predecessors=True)
    reached = (nearest >= 0) & ~np.asarray(known, bool)
    out[reached] = out[nearest[reached]]
    return out


def carried_sources(surface_points_mm: np.ndarray, surface_normals: np.ndarray, cloud_points_mm: np.ndarray,
                    cloud_normals: np.ndarray, spacing_mm: float, covered_mm: float = COVERED_MM
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Which cloud point each surface sample takes its label from, as :func:`truth_surface_scores`
    carries a map: (source index (S,) into the cloud, distance (S,) mm from the sample to the
    cloud point :func:`carry_labels` chose for it; > ``covered_mm``: not covered).

    The label of a map over the cloud on the samples is ``cloud_labels[source]``: the
    sources depend on the cloud and the samples only, so scoring many maps of one cloud
    needs them once (bench/sampling_efficiency.py). An uncovered sample takes the source
    of the nearest covered sample along the surface (:func:`spread_along_surface`).
    """
    index = np.arange(np.asarray(cloud_points_mm).reshape(-1, 3).shape[0])
    source, dist = carry_labels(surface_points_mm, surface_normals, cloud_points_mm, cloud_normals, index)
    # An unscanned band takes its labels from its own edges, along the face it lies on: the
    # nearest scanned point in space may lie across a step (the pillow beside the box: the
    # box's top edge is nearer than the pillow beyond the scanner's shadow).
    source = spread_along_surface(surface_points_mm, source, dist <= covered_mm, SPREAD_STEP_SPACINGS * spacing_mm)
    return source, dist


def truth_surface_scores(surface_points_mm: np.ndarray, surface_normals: np.ndarray, true_labels: np.ndarray,
                         area_mm2: np.ndarray, cloud_points_mm: np.ndarray, cloud_normals: np.ndarray,
                         cloud_labels: np.ndarray, spacing_mm: float, covered_mm: float = COVERED_MM,
                         seam_distance_mm: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, Any]:
    """Score a session's region map (over its cloud) on samples of the object's true surface.

    The surface samples (S,3) carry their true normals and labels and the area (mm^2) each
    stands for (sim/truth_surface.py). The cloud's labels are carried onto them
    (:func:`carry_labels`: the nearest cloud point of the same face), those farther than
    ``covered_mm`` from it then from the covered samples along the surface
    (:func:`spread_along_surface`), and scored with :func:`region_map_scores`,
    area-weighted, boundary points within 1.5 sample spacings. ``coverage``: the area
    fraction within ``covered_mm`` of the cloud point its label came from. The uncovered
    part is scored too (the user receives a map there as well);
    ``error_covered`` / ``error_uncovered``: the mislabelled fraction of each part's own
    area (None for an empty part). ``wrong`` (S,) marks the mislabelled samples.

    Boundary distances: where the materials meet only off the sampled top (the composite's
    box and pillow meet at the foot of the box's wall), the truth has no boundary samples;
    a boundary the map draws there is then measured against the seam itself,
    ``seam_distance_mm(points) -> (N,)`` mm (the ground truth's), one way.
    """
    pts = np.asarray(surface_points_mm, dtype=float).reshape(-1, 3)
    true = np.asarray(true_labels).reshape(-1)
    w = np.asarray(area_mm2, dtype=float).reshape(-1)
    source, dist = carried_sources(pts, surface_normals, cloud_points_mm, cloud_normals, spacing_mm, covered_mm)
    covered = dist <= covered_mm
    carried = np.asarray(cloud_labels).reshape(-1)[source]
    radius = 1.5 * spacing_mm
    scores = region_map_scores(carried, true, w, pts, radius_mm=radius)
    if scores["boundary_mm_mean"] is None and seam_distance_mm is not None \
            and boundary_points(true, pts, radius).size == 0:
        drawn = boundary_points(carried, pts, radius)
        d = np.asarray(seam_distance_mm(pts[drawn]), dtype=float)
        if drawn.size and np.all(np.isfinite(d)):
            scores.update(boundary_mm_mean=float(d.mean()), boundary_mm_p90=float(np.percentile(d, 90)))
    ids, which = np.unique(carried, return_inverse=True)
    matched = np.array([scores["matching"].get(v.item(), -1) for v in ids], dtype=int)
    wrong = matched[which.reshape(-1)] != true if ids.size else np.zeros(0, bool)

    def error_of(part: np.ndarray) -> float | None:
        area = float(w[part].sum())
        return float(w[part & wrong].sum() / area) if area > 0 else None

    total = float(w.sum())
    return {**scores, "wrong": wrong, "carried_labels": carried, "carried_from_mm": dist,
            "coverage": float(w[covered].sum() / total) if total > 0 else None,
            "area_mm2": total, "uncovered_area_mm2": float(w[~covered].sum()),
            "error_covered": error_of(covered), "error_uncovered": error_of(~covered)}


def heldout_profile_rmse_mm(model: Any, forces_n: np.ndarray, angles_deg: np.ndarray,
                            truth_fn: Callable[[float, float], np.ndarray]) -> float | None:
    """RMSE (mm, default ROI) of a model at held-out (F, α) against ``truth_fn(F, α) -> (L,)``."""
    f = np.asarray(forces_n, dtype=float).reshape(-1)
    a = np.asarray(angles_deg, dtype=float).reshape(-1)
    truth = np.stack([truth_fn(float(fi), float(ai)) for fi, ai in zip(f, a)])
    return profile_rmse_mm(_predict(model, f, a), truth)
