"""Densification: probe again where adjacent region models disagree (docs/design.md §2, §7).

Score of a surface-graph edge whose ends carry different region labels: how far apart
the two regions' models put the profile at the survey probe settings, relative to what
the data can resolve:

    score = max over settings of RMS_roi(p_a − p_b) / sqrt(noise² + s_a² + s_b²)

with ``noise`` the standard error of averaged scans (mm, :func:`averaged_noise_mm`),
``s_a``, ``s_b`` the RMS ensemble spreads (bootstrap over probe points) and the RMS taken
over the samples where either profile is deeper than ``ROI_FRACTION`` of the deeper
peak. A score well above 1 (default threshold 3) means the boundary is real and
worth localising; below it the two regions are indistinguishable at survey settings.
A point whose features sit between two regions (ambiguity from the region map) scores
its ambiguity times the score of those two regions.

New survey points bisect the unresolved boundary: the midpoints of high-scoring edges
longer than ``resolution_mm`` (an edge already that short has located its piece of the
boundary; probing its midpoint again buys nothing), and of the edges around ambiguous
points, snapped to the measured surface if a cloud is given. They are accepted greedily,
longest edge first (the widest gap in which the boundary is still unknown: the most
mislabelled area at stake), ties by score, while keeping ``min_spacing_mm`` from every
existing and accepted point. All edges between the same two regions carry the same
score, so ordering by score alone took them in index order, often short edges before
long ones. Each round halves the gaps it splits: a bisection of every crossing edge down
to ``resolution_mm``. The boundary is resolved when every disagreeing edge is shorter than
``resolution_mm``. A midpoint is half an edge from its ends, so edges shorter than
2 x min_spacing_mm cannot be split: choose resolution_mm >= 2 x min_spacing_mm, or the
rounds end "spacing-limited" (``DensifyRound.stop`` with ``resolved`` False).

Before any edge: a ring of points around every point of a region with fewer than three
points (a small inclusion one survey probe landed on, kept by the regions' contrast rule),
at a quarter of the survey spacing there (:func:`ring_candidates`): an edge's midpoint,
half a spacing out, mostly misses an inclusion the survey could miss, and a material seen
at one point is the one a later round can lose.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol

import numpy as np
from scipy.spatial import cKDTree

from . import regions as rg
from . import surface_map as sm

ROI_FRACTION = 0.05
DEFAULT_THRESHOLD = 3.0
# Probing around a point (see :func:`ring_candidates`): the ring's radius as a fraction of
# the point's edges (the survey spacing around it), and how many directions it takes.
RING_FRACTION = 0.25
RING_DIRECTIONS = 6
# A region of fewer survey points is probed around: the regions' contrast rule holds a
# cluster this small to a contrast at every measured force (regions.MIN_POINTS_FOR_ONE_FORCE),
# and a probe on a small inclusion is usually alone there.
LONE_REGION_POINTS = rg.MIN_POINTS_FOR_ONE_FORCE
# Where a new probe goes on a crossing edge: a point within this many robust sigmas of its
# region's median counts as pure (surface_map.seam_fractions).
CROSSING_EDGE_SIGMAS = 3.0


class ProfileModel(Protocol):
    def predict_batch_mm(self, force_n: np.ndarray, angle_deg: np.ndarray) -> np.ndarray: ...

    def predict_ensemble(self, force_n: np.ndarray, angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def averaged_noise_mm(std_mm: np.ndarray, count: np.ndarray) -> float:
    """Typical standard error (mm) of averaged profiles: median over samples of std/sqrt(count).

    ``std_mm``, ``count``: as returned by :func:`profiles.average_profiles` (any shape).
    """
    s = np.asarray(std_mm, dtype=float)
    c = np.asarray(count, dtype=float)
    ok = np.isfinite(s) & (c > 1)
    if not ok.any():
        raise ValueError("no sample was seen by two scans: the noise cannot be estimated")
    return float(np.median(s[ok] / np.sqrt(c[ok])))


def model_distance(model_a: ProfileModel, model_b: ProfileModel, forces_n: np.ndarray,
                   angles_deg: np.ndarray) -> tuple[float, float]:
    """(RMS difference mm, RMS combined ensemble spread mm) at the setting where the two
    models differ most, over the region of interest of that setting."""
    f, a, pa, pb, sa, sb = _predictions(model_a, model_b, forces_n, angles_deg)
    best = (0.0, 0.0)
    for i in range(f.shape[0]):
        peak = max(float(np.max(pa[i])), float(np.max(pb[i])), 0.0)
        roi = np.maximum(pa[i], pb[i]) > ROI_FRACTION * peak
        if not roi.any():
            continue
        diff = float(np.sqrt(np.mean((pa[i, roi] - pb[i, roi]) ** 2)))
        spread = float(np.sqrt(np.mean(sa[i, roi] ** 2 + sb[i, roi] ** 2)))
        if diff >= best[0]:
            best = (diff, spread)
    return best


def peak_ratio_score(model_a: ProfileModel, model_b: ProfileModel, forces_n: np.ndarray,
                     angles_deg: np.ndarray, noise_mm: float) -> float:
    """How far apart two models put the dent's depth, as a ratio against what each knows
    of its own depth: the largest over settings of

        |log((P_a + n) / (P_b + n))| / sqrt((s_a / (P_a + n))^2 + (s_b / (P_b + n))^2 + ...)

    with P the peak of a model's profile, s its ensemble spread at that sample and n the
    averaged noise (mm), whose own relative share (n / (P + n))^2 joins the sum for each.
    Materials differ by factors: a sponge 20x deeper than an elastomer has an ensemble
    spread (bootstrap over a few probe points) that, in millimetres, is as large as the
    elastomer's whole dent, and the difference in millimetres (:func:`model_distance`)
    reads as barely resolved; as a ratio the two dents are many spreads apart.
    """
    _, _, pa, pb, sa, sb = _predictions(model_a, model_b, forces_n, angles_deg)
    n = max(float(noise_mm), 1e-6)
    best = 0.0
    for i in range(pa.shape[0]):
        ia, ib = int(np.argmax(pa[i])), int(np.argmax(pb[i]))
        da, db = max(float(pa[i, ia]), 0.0) + n, max(float(pb[i, ib]), 0.0) + n
        rel = np.sqrt((sa[i, ia] / da) ** 2 + (sb[i, ib] / db) ** 2 + (n / da) ** 2 + (n / db) ** 2)
        best = max(best, abs(float(np.log(da / db))) / float(rel))
    return best


def _predictions(model_a: ProfileModel, model_b: ProfileModel, forces_n: np.ndarray, angles_deg: np.ndarray
                 ) -> tuple[np.ndarray, ...]:
    """Settings (f, a) and both models' profiles and ensemble spreads (Q,L) at them."""
    f, a = np.meshgrid(np.asarray(forces_n, dtype=float), np.asarray(angles_deg, dtype=float), indexing="ij")
    f, a = f.ravel(), a.ravel()
    pa, pb = model_a.predict_batch_mm(f, a), model_b.predict_batch_mm(f, a)
    return f, a, pa, pb, _spread(model_a, f, a, pa.shape), _spread(model_b, f, a, pb.shape)


def _spread(model: Any, f: np.ndarray, a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if hasattr(model, "predict_ensemble"):
        return np.asarray(model.predict_ensemble(f, a)[1], dtype=float).reshape(shape)
    return np.zeros(shape)


def survey_pair_scores(log_depth: np.ndarray, labels: np.ndarray, rel_noise: np.ndarray
                       ) -> dict[tuple[int, int], float]:
    """Score of every pair of regions (a < b) from the survey itself: the largest over survey
    forces of |median_a - median_b| of the points' log peak depths (N,F), over its standard
    error sqrt(v_a / n_a + v_b / n_b), v a region's robust variance (1.4826 MAD)^2, at least
    its points' mean squared relative noise ``rel_noise`` (N,F) (noise / depth).

    Every survey point of a region votes, not just the few that were characterized: two
    regions whose dents differ by a factor are told apart here even when their models,
    bootstrapped over two or three points, are not yet sure of their own depth.
    """
    y = np.asarray(log_depth, dtype=float)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    rn = np.asarray(rel_noise, dtype=float)
    regions = sorted(int(v) for v in np.unique(lab))
    stats = {}
    for r in regions:
        m = lab == r
        with np.errstate(all="ignore"):
            med = np.nanmedian(y[m], axis=0)
            mad = 1.4826 * np.nanmedian(np.abs(y[m] - med), axis=0)
            var = np.maximum(np.nan_to_num(mad) ** 2, np.nanmean(rn[m] ** 2, axis=0))
        stats[r] = (med, var, int(m.sum()))
    out: dict[tuple[int, int], float] = {}
    for i, ra in enumerate(regions):
        for rb in regions[i + 1:]:
            (ma, va, na), (mb, vb, nb) = stats[ra], stats[rb]
            with np.errstate(all="ignore"):
                z = np.abs(ma - mb) / np.sqrt(va / na + vb / nb)
            out[(ra, rb)] = float(np.nanmax(np.where(np.isfinite(z), z, 0.0), initial=0.0))
    return out


def survey_evidence(features: np.ndarray, feature_names: list[str], labels: np.ndarray, noise_mm: float,
                    min_contrast: float = rg.MIN_CONTRAST,
                    far_field_mm: np.ndarray | None = None) -> dict[str, Any]:
    """What the survey itself says, as :func:`plan_round`'s keyword arguments: the pair scores
    of the regions' dents (:func:`survey_pair_scores`), each point's misfit to its region
    (regions.survey_misfit) and its level (mean over survey forces of log(peak + noise)).

    ``features`` (N,D) and ``feature_names``: the survey features of the labelled points
    (regions.survey_features); ``noise_mm``: the standard error of an averaged profile;
    ``far_field_mm`` (N,2): what their profiles read far from the contact (the regions
    step's input), from which the misfit measures each region's peak scatter.
    """
    log_depth, rel_noise = rg.log_peaks(features, feature_names, noise_mm)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    return {"survey_scores": survey_pair_scores(log_depth, lab, rel_noise),
            "misfit": rg.survey_misfit(features, lab, feature_names, noise_mm, min_contrast,
                                       far_field_mm=far_field_mm),
            "levels": log_depth.mean(axis=1)}


def pair_scores(labels_present: np.ndarray, models: Mapping[int, ProfileModel], forces_n: np.ndarray,
                angles_deg: np.ndarray, noise_mm: float, missing_score: float = np.inf,
                survey: Mapping[tuple[int, int], float] | None = None) -> dict[tuple[int, int], float]:
    """Score of every pair of regions (a < b): the larger of the models' difference in mm
    over noise and spreads (:func:`model_distance`) and as a ratio of depths
    (:func:`peak_ratio_score`), and of the ``survey`` score when given
    (:func:`survey_pair_scores`); a region without a model scores ``missing_score``."""
    regions = sorted(int(v) for v in np.unique(labels_present))
    out: dict[tuple[int, int], float] = {}
    for i, ra in enumerate(regions):
        for rb in regions[i + 1:]:
            if ra not in models or rb not in models:
                out[(ra, rb)] = missing_score
                continue
            diff, spread = model_distance(models[ra], models[rb], forces_n, angles_deg)
            score = max(diff / float(np.sqrt(noise_mm ** 2 + spread ** 2)),
                        peak_ratio_score(models[ra], models[rb], forces_n, angles_deg, noise_mm))
            if survey is not None:
                score = max(score, survey.get((ra, rb), 0.0))
            out[(ra, rb)] = score
    return out


def _pair(scores: Mapping[tuple[int, int], float], a: int, b: int) -> float:
    return 0.0 if a == b else scores[(min(a, b), max(a, b))]


def edge_scores(edges: np.ndarray, labels: np.ndarray, scores: Mapping[tuple[int, int], float]) -> np.ndarray:
    """(E,) score of each surface-graph edge: 0 within a region, the pair score across regions."""
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    lab = np.asarray(labels)
    return np.array([_pair(scores, int(lab[i]), int(lab[j])) for i, j in e], dtype=float)


def point_scores(posterior: np.ndarray, scores: Mapping[tuple[int, int], float]) -> np.ndarray:
    """(N,) ambiguity x pair score of each point's two most likely regions.

    ``posterior`` (N,K): region probabilities from the features (``RegionMap.posterior``).
    """
    p = np.asarray(posterior, dtype=float)
    if p.ndim != 2 or p.shape[1] < 2:
        return np.zeros(p.shape[0])
    order = np.argsort(-p, axis=1, kind="stable")
    top = np.take_along_axis(p, order[:, :2], axis=1)
    ambiguity = 1.0 - (top[:, 0] - top[:, 1])
    return np.array([amb * _pair(scores, int(o[0]), int(o[1])) for amb, o in zip(ambiguity, order)])


def snap_to_surface(points_mm: np.ndarray, surface_points_mm: np.ndarray) -> np.ndarray:
    """Each point moved to its nearest measured surface point (object frame, mm)."""
    surf = np.asarray(surface_points_mm, dtype=float)
    _, idx = cKDTree(surf).query(np.asarray(points_mm, dtype=float).reshape(-1, 3))
    return surf[idx]


def candidate_points(positions_mm: np.ndarray, edges: np.ndarray, edge_score: np.ndarray,
                     point_score: np.ndarray | None = None, surface_points_mm: np.ndarray | None = None,
                     min_length_mm: float = 0.0, return_lengths: bool = False,
                     fraction: np.ndarray | None = None, return_edges: bool = False,
                     end_clearance_mm: float = 0.0) -> tuple[np.ndarray, ...]:
    """Candidate new survey points (C,3) and their scores (C,) [and edge lengths (C,) mm]
    [and the index (C,) of each one's edge].

    Points on edges longer than ``min_length_mm`` (a shorter edge has already placed its
    piece of the boundary within that length) with a positive score: their own (a crossing
    edge), or the larger ``point_score`` of their two ends (a ring around a doubtful point:
    ambiguous features, or a misfit of its region). Each lies ``fraction`` (E,) of the way
    from the edge's first end to its second (default 0.5, the midpoint), moved in to keep
    ``end_clearance_mm`` from both ends (:func:`_clear_of_ends`).
    """
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    s = np.asarray(edge_score, dtype=float).copy()
    lengths = np.linalg.norm(pos[e[:, 0]] - pos[e[:, 1]], axis=1) if e.shape[0] else np.zeros(0)
    if point_score is not None:
        ps = np.asarray(point_score, dtype=float)
        s = np.maximum(s, np.maximum(ps[e[:, 0]], ps[e[:, 1]]))
    s[lengths <= min_length_mm] = 0.0
    keep = s > 0
    t = np.full(e.shape[0], 0.5) if fraction is None else np.asarray(fraction, dtype=float).reshape(-1)
    t = _clear_of_ends(t, lengths, end_clearance_mm)
    mids = pos[e[keep, 0]] + t[keep, None] * (pos[e[keep, 1]] - pos[e[keep, 0]])
    if surface_points_mm is not None and mids.shape[0]:
        mids = snap_to_surface(mids, surface_points_mm)
    out = (mids, s[keep]) + ((lengths[keep],) if return_lengths else ())
    return out + ((np.flatnonzero(keep),) if return_edges else ())


def _tangent_frames(points_mm: np.ndarray, surface_points_mm: np.ndarray | None, k: int = 16
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (M,3), (M,3) spanning the surface's tangent plane at each point: the
    plane of its ``k`` nearest surface points (PCA), the horizontal plane without a surface.
    The first lies along the plane's projection of x (of y where x is near its normal), so
    a ring's directions do not depend on the PCA's sign."""
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    normals = np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1))
    if surface_points_mm is not None and len(surface_points_mm) >= 3:
        surf = np.asarray(surface_points_mm, dtype=float).reshape(-1, 3)
        _, idx = cKDTree(surf).query(pts, k=min(k, surf.shape[0]))
        for i, nb in enumerate(np.atleast_2d(idx)):
            q = surf[nb] - surf[nb].mean(axis=0)
            normals[i] = np.linalg.eigh(q.T @ q)[1][:, 0]
    ex = np.array([1.0, 0.0, 0.0])
    axis = np.where(np.abs(normals @ ex)[:, None] > 0.9, np.array([0.0, 1.0, 0.0]), ex)
    u = axis - np.sum(axis * normals, axis=1, keepdims=True) * normals
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(normals, u)


def ring_candidates(positions_mm: np.ndarray, edges: np.ndarray, centres: np.ndarray,
                    min_spacing_mm: float, resolution_mm: float,
                    surface_points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points (C,3) around each of ``centres`` (indices into ``positions_mm``), and the centre
    (C,) each belongs to: ``RING_DIRECTIONS`` points on a circle in the surface's tangent
    plane, snapped to the surface.

    The radius is ``RING_FRACTION`` of the median length of the centre's edges (the survey
    spacing around it), at least ``min_spacing_mm``. Why a quarter: the survey misses an
    inclusion narrower than about its spacing s (planrule: one unit per s^2), so a probe
    that did land on one lies within s/2 of its centre, typically 2/3 of its radius off
    it; the midpoints of the probe's edges, s/2 away, then mostly fall outside it, while a
    ring at s/4 puts two or three points inside an inclusion s/2 to s across, away from
    its seam, where they read its material unblended. A centre whose edges are all within
    ``resolution_mm`` is already surrounded; it gets no ring.
    """
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    lengths = np.linalg.norm(pos[e[:, 0]] - pos[e[:, 1]], axis=1) if e.size else np.zeros(0)
    out, owner = [], []
    for c in np.asarray(centres, dtype=np.int64).reshape(-1):
        own = lengths[(e[:, 0] == c) | (e[:, 1] == c)] if e.size else lengths
        if own.size == 0 or float(np.median(own)) <= resolution_mm:
            continue
        radius = max(RING_FRACTION * float(np.median(own)), float(min_spacing_mm))
        u, v = _tangent_frames(pos[c][None], surface_points_mm)
        angles = 2.0 * np.pi * np.arange(RING_DIRECTIONS) / RING_DIRECTIONS
        out.append(pos[c] + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v))
        owner.append(np.full(RING_DIRECTIONS, c, dtype=np.int64))
    if not out:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    ring = np.concatenate(out)
    if surface_points_mm is not None:
        ring = snap_to_surface(ring, surface_points_mm)
    return ring, np.concatenate(owner)


def rim_candidates(positions_mm: np.ndarray, edges: np.ndarray, edge_score: np.ndarray, labels: np.ndarray,
                   band_points_mm: np.ndarray | None, threshold: float = DEFAULT_THRESHOLD,
                   survey_area_mm: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points (C,3) in the rim band beyond a seam's outermost probes, their scores (C,), the
    area (C,) mm^2 each speaks for, and the point (C,) each steps out from.

    The survey keeps its edge clearance from a sharp edge, so between a seam's outermost
    probes and the rim lies a band (``band_points_mm``: where densify may still probe, the
    tip on the face, but the survey did not go) that the map fills from the nearest probe:
    an inclusion near the rim is drawn out to it. Each end of a crossing edge scoring at
    least ``threshold`` that lies within its survey spacing (the median length of its edges)
    of the band gets one candidate: a spacing from it toward the band's nearest point,
    snapped to the band, unless a probe already stands within half a spacing of that. Its
    score is the end's best crossing edge; its area the spacing times the band's depth
    beyond it (what the nearest-probe rule would otherwise extrapolate).
    An end standing in the band itself (nearer a band point than any point of
    ``survey_area_mm``, the surface the survey may probe: an earlier round's rim point) steps
    the same spacing away from the survey area (from the mean of its points within a
    spacing), where the band goes on and the map would extrapolate the end's label. Without
    ``survey_area_mm`` every end steps toward its nearest band point (none when it stands
    on one).
    """
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    empty = (np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    if band_points_mm is None or len(band_points_mm) == 0 or e.shape[0] == 0:
        return empty
    band = np.asarray(band_points_mm, dtype=float).reshape(-1, 3)
    lab = np.asarray(labels)
    es = np.asarray(edge_score, dtype=float)
    hot = (lab[e[:, 0]] != lab[e[:, 1]]) & (np.nan_to_num(es, nan=-np.inf) >= threshold)
    if not hot.any():
        return empty
    lengths = np.linalg.norm(pos[e[:, 0]] - pos[e[:, 1]], axis=1)
    band_tree, probes = cKDTree(band), cKDTree(pos)
    area_tree = (cKDTree(np.asarray(survey_area_mm, dtype=float).reshape(-1, 3))
                 if survey_area_mm is not None and len(survey_area_mm) else None)
    out, scores, areas, source = [], [], [], []
    for k in np.unique(e[hot].ravel()):
        mine = (e[:, 0] == k) | (e[:, 1] == k)
        step = float(np.median(lengths[mine]))
        dist, b = band_tree.query(pos[k])
        if area_tree is not None and dist < area_tree.query(pos[k])[0]:
            # In the band: toward its nearest point is any way at all (a sideways step
            # lands beside a probe and is refused, and the band beyond stays unprobed).
            inside = area_tree.query_ball_point(pos[k], step)
            away = pos[k] - area_tree.data[inside].mean(axis=0) if inside else np.zeros(3)
            away_mm = float(np.linalg.norm(away))
            if not away_mm > 0.0:
                continue
            u, dist = away / away_mm, 0.0
        elif 0.0 < dist <= step:
            u = (band[b] - pos[k]) / dist
        else:
            continue
        _, c = band_tree.query(pos[k] + step * u)
        if probes.query(band[c])[0] < 0.5 * step:
            continue
        rel = band - pos[k]
        along = rel @ u
        beside = np.linalg.norm(rel - along[:, None] * u, axis=1) <= 0.5 * step
        out.append(band[c])
        scores.append(float(np.max(es[mine & hot])))
        areas.append(step * float(np.max(along[beside & (along > 0)], initial=dist)))
        source.append(int(k))
    if not out:
        return empty
    return np.asarray(out), np.asarray(scores), np.asarray(areas), np.asarray(source, dtype=np.int64)


def lone_points(labels: np.ndarray, min_points: int = LONE_REGION_POINTS) -> np.ndarray:
    """(N,) True for the points of a region with fewer than ``min_points`` points."""
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    if lab.size == 0:
        return np.zeros(0, dtype=bool)
    _, inverse, counts = np.unique(lab, return_inverse=True, return_counts=True)
    return counts[inverse.reshape(-1)] < min_points


def propose_points(candidates_mm: np.ndarray, scores: np.ndarray, existing_mm: np.ndarray, budget: int,
                   min_spacing_mm: float, min_score: float = DEFAULT_THRESHOLD,
                   priority: np.ndarray | None = None) -> np.ndarray:
    """Indices (K,) into ``candidates_mm`` of the new survey points, in acceptance order.

    Greedy: candidates scoring at least ``min_score`` in decreasing ``priority`` (default:
    the score), then decreasing score, then index, each accepted only if it keeps
    ``min_spacing_mm`` from every existing point and every point already accepted; at
    most ``budget`` points.
    """
    cand = np.asarray(candidates_mm, dtype=float).reshape(-1, 3)
    sc = np.asarray(scores, dtype=float).reshape(-1)
    key_score = -np.nan_to_num(sc, nan=-np.inf)
    key_priority = key_score if priority is None else -np.nan_to_num(
        np.asarray(priority, dtype=float).reshape(-1), nan=-np.inf)
    order = [int(i) for i in np.lexsort((np.arange(sc.size), key_score, key_priority)) if sc[i] >= min_score]
    taken = [np.asarray(p, dtype=float) for p in np.asarray(existing_mm, dtype=float).reshape(-1, 3)]
    accepted: list[int] = []
    for i in order:
        if len(accepted) >= budget:
            break
        if taken:
            d = np.linalg.norm(np.asarray(taken) - cand[i], axis=1)
            if float(d.min()) < min_spacing_mm - 1e-9:      # exactly the spacing keeps it
                continue
        accepted.append(i)
        taken.append(cand[i])
    return np.asarray(accepted, dtype=np.int64)


def boundaries_resolved(positions_mm: np.ndarray, edges: np.ndarray, edge_score: np.ndarray,
                        resolution_mm: float, threshold: float = DEFAULT_THRESHOLD) -> tuple[bool, str]:
    """Stop rule: (resolved, reason). Resolved when no edge disagrees beyond ``threshold``
    or every disagreeing edge is shorter than ``resolution_mm``."""
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    hot = np.asarray(edge_score, dtype=float) >= threshold
    if not hot.any():
        return True, f"no adjacent regions disagree beyond {threshold:g} x noise"
    lengths = np.linalg.norm(pos[e[hot, 0]] - pos[e[hot, 1]], axis=1)
    longest = float(lengths.max())
    if longest <= resolution_mm:
        return True, f"all {int(hot.sum())} disagreeing edges are within {resolution_mm:g} mm (longest {longest:.1f} mm)"
    return False, (f"{int(np.sum(lengths > resolution_mm))} of {int(hot.sum())} disagreeing edges are longer "
                   f"than {resolution_mm:g} mm (longest {longest:.1f} mm)")


@dataclass
class DensifyRound:
    """One densification round, as journaled: what was scored, what was proposed, and why."""

    round_index: int
    n_points: int
    n_regions: int
    noise_mm: float
    threshold: float
    pair_scores: dict[str, float | None]
    disagreeing_edges: list[list[int]]
    disagreeing_scores: list[float | None]
    proposed_mm: list[list[float]]
    proposed_scores: list[float | None]
    resolved: bool
    reason: str
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def stop(self) -> bool:
        """True when densifying should end: resolved, or nothing could be placed (spacing)."""
        return self.resolved or not self.proposed_mm

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items()}
        out["stop"] = self.stop
        return out


def _crossing_fraction(edges: np.ndarray, labels: np.ndarray, levels: np.ndarray,
                       clip: tuple[float, float] = (0.2, 0.8)) -> np.ndarray:
    """(E,) where along each crossing edge the interpolated level crosses midway between its
    two regions (0.5 on edges within a region or when the regions' levels overlap). Each
    region's level range is read on its interior points (those whose neighbours along
    ``edges`` are all of its region), as the final map reads it: on a small inclusion the
    points already on its seam are most of the region, and a range read on them overlaps
    the neighbour's (surface_map.seam_fractions)."""
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    out = np.full(e.shape[0], 0.5)
    cross = np.flatnonzero(np.asarray(labels)[e[:, 0]] != np.asarray(labels)[e[:, 1]])
    if cross.size == 0:
        return out
    # Log levels and 3-sigma edges, where the final map now reads mm halfway between the
    # medians: this places probes, and changing it moves every run's probing (not measured).
    s_a, s_b, usable = sm.seam_fractions(levels, labels, e[cross, 0], e[cross, 1], sm.interior_seeds(labels, e),
                                         edge_sigmas=CROSSING_EDGE_SIGMAS)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(s_b - s_a) > 1e-9, (0.5 - s_a) / (s_b - s_a), 0.5)
    out[cross] = np.where(usable, np.clip(t, *clip), 0.5)
    return out


def _clear_of_ends(fraction: np.ndarray, lengths_mm: np.ndarray, min_spacing_mm: float) -> np.ndarray:
    """(E,) each edge's ``fraction`` moved in until the point keeps ``min_spacing_mm`` from both
    ends of its edge (``lengths_mm`` (E,)); the midpoint where the edge is shorter than twice that.

    A point nearer an end than the spacing is refused (:func:`propose_points`), and its edge,
    the seam still unknown along it, got no probe at all: the false-position step clipped to
    a fifth of the edge puts it 1.2-3 mm from an end on the 6-15 mm edges a second round
    works on (unseen 1812: round 2 proposed 3 points for 20 such edges, and the hard-rubber
    ellipse kept its survey's 6-12 mm gaps). A point at the spacing still splits the edge on
    the side the levels put the seam."""
    margin = np.clip(float(min_spacing_mm) / np.maximum(np.asarray(lengths_mm, dtype=float), 1e-9), 0.0, 0.5)
    return np.clip(np.asarray(fraction, dtype=float), margin, 1.0 - margin)


def _across_from_label(edges: np.ndarray, labels: np.ndarray, levels: np.ndarray,
                       scores: Mapping[tuple[int, int], float]) -> np.ndarray:
    """(E,) the pair score on each edge within one region A whose one end stands beside a
    region B (a crossing edge to it) and reads past the halfway from A's level toward B's
    (surface_map.reads_other_side), its other end not: the seam runs along that edge, though
    both ends carry A's label. 0 elsewhere.

    Such a point's tip pressed more of B than of A; the clustering kept it with A on its
    neighbours. Scored only on the crossing edges, densify then splits the edges between it
    and B's interior, where the seam is not, and never the edge beyond it, where it is (suite
    slab 1012 seed 2: four probes just inside a hard-rubber ellipse read past the halfway
    toward it and were labelled elastomer; the rounds split the ellipse's interior while the
    true seam lay on the 5-10 mm edges out to the elastomer, and the final map cut the
    ellipse along them)."""
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    out = np.zeros(e.shape[0])
    inner = sm.interior_seeds(lab, e)
    crossing = lab[e[:, 0]] != lab[e[:, 1]]
    over = np.full(lab.size, -1, dtype=np.int64)           # the region each point reads past the halfway to
    pairs = {(int(lab[i]), int(lab[j])) for i, j in e[crossing]}
    for a, b in sorted(pairs | {(b, a) for a, b in pairs}):
        beside = np.unique(np.concatenate([e[crossing & (lab[e[:, 0]] == a) & (lab[e[:, 1]] == b), 0],
                                           e[crossing & (lab[e[:, 1]] == a) & (lab[e[:, 0]] == b), 1]]))
        past = sm.reads_other_side(levels[:, None], lab, inner, beside, b)
        over[beside[past & (over[beside] < 0)]] = b
    across = ~crossing & ((over[e[:, 0]] >= 0) != (over[e[:, 1]] >= 0))
    far_end = np.where(over[e[:, 0]] >= 0, e[:, 0], e[:, 1])
    for k in np.flatnonzero(across):
        out[k] = _pair(scores, int(lab[far_end[k]]), int(over[far_end[k]]))
    return out


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def plan_round(round_index: int, positions_mm: np.ndarray, edges: np.ndarray, labels: np.ndarray,
               models: Mapping[int, ProfileModel], forces_n: np.ndarray, angles_deg: np.ndarray,
               noise_mm: float, budget: int, min_spacing_mm: float, resolution_mm: float,
               threshold: float = DEFAULT_THRESHOLD, posterior: np.ndarray | None = None,
               surface_points_mm: np.ndarray | None = None,
               survey_scores: Mapping[tuple[int, int], float] | None = None,
               misfit: np.ndarray | None = None, levels: np.ndarray | None = None,
               border: np.ndarray | None = None, band_points_mm: np.ndarray | None = None,
               survey_area_mm: np.ndarray | None = None) -> DensifyRound:
    """Score the current map, apply the stop rule and propose the next survey points.

    ``forces_n``, ``angles_deg``: the survey probe settings; ``posterior`` (N,K) optional
    feature posteriors for ambiguous points; ``surface_points_mm``: the surface to snap to
    (where a target may go); ``survey_scores``: pair scores from the survey itself
    (:func:`survey_pair_scores`); ``misfit`` (N,): how far each point lies beyond what its
    region explains (regions.survey_misfit; > 1: maybe another material): when all its
    neighbours share its region, its ring of edges scores ``threshold`` x misfit;
    ``levels`` (N,): each point's dent on the scale the regions differ on (mean log peak
    depth): a crossing edge is then split where the level interpolated between its ends
    crosses midway (surface_map.seam_fractions; a false-position step, clipped to the
    middle 60 % of the edge and to ``min_spacing_mm`` from its ends), the midpoint when both
    ends are pure; and an edge within a region one of whose ends reads past the halfway
    toward a region it borders scores as a crossing edge to it (:func:`_across_from_label`);
    ``border`` (E,): the length of the border between each edge's two cells
    (surface_map.shared_border). Candidates are taken in decreasing edge length x border
    (the area whose label is unresolved; length alone without ``border``).
    ``band_points_mm``: the rim band, where densify may probe and the survey did not go
    (:func:`rim_candidates`): a seam whose crossing edges end beside it is followed out;
    ``survey_area_mm``: the surface the survey may probe (beside ``band_points_mm``, it tells
    a point in the band which way the band goes on).
    When resolved, nothing is proposed; when nothing can be placed (spacing), the reason
    says so.
    """
    lab = np.asarray(labels)
    pscores = pair_scores(lab if posterior is None else np.arange(np.asarray(posterior).shape[1]),
                          models, forces_n, angles_deg, noise_mm, survey=survey_scores)
    es = edge_scores(edges, lab, pscores)
    ps = point_scores(posterior, pscores) if posterior is not None else np.zeros(lab.shape[0])
    odd = np.zeros(lab.shape[0], dtype=bool)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if misfit is not None:
        # A misfit beside another region is the seam's blend, which the crossing edges
        # already follow; one surrounded by its own region is unexplained.
        on_seam = np.zeros(lab.shape[0], dtype=bool)
        crossing = lab[e[:, 0]] != lab[e[:, 1]]
        on_seam[e[crossing].ravel()] = True
        mf = np.nan_to_num(np.asarray(misfit, dtype=float).reshape(-1))
        odd = (mf > 1.0) & ~on_seam
        ps = np.maximum(ps, np.where(odd, threshold * mf, 0.0))
    if levels is not None and e.size:
        es = es + _across_from_label(e, lab, np.asarray(levels, dtype=float).reshape(-1), pscores)
    resolved, reason = boundaries_resolved(positions_mm, edges, es, resolution_mm, threshold)
    where = None if levels is None else _crossing_fraction(edges, lab, levels)
    cand, cs, gap_mm, used = candidate_points(positions_mm, edges, es, ps, surface_points_mm,
                                              min_length_mm=resolution_mm, return_lengths=True,
                                              fraction=where, return_edges=True, end_clearance_mm=min_spacing_mm)
    area = gap_mm if border is None else gap_mm * np.maximum(np.asarray(border, dtype=float)[used], 1.0)
    # Around a region's lone points (a small inclusion one survey probe landed on): a ring at
    # a quarter of the survey spacing (ring_candidates), ahead of every edge: a material seen
    # at one point is the one a round can lose. Not around a misfit: the contrast rule has not
    # called it another material, and a ring of points reading alike makes a region of what
    # may be geometry (suite 1011: a ring around the plate's one misfit became a third region,
    # map error 0 -> 0.8 %); its edges' midpoints look half a spacing out.
    lone = lone_points(lab) if np.unique(lab).size > 1 else np.zeros(lab.shape[0], dtype=bool)
    ring, owner = ring_candidates(positions_mm, e, np.flatnonzero(lone), min_spacing_mm, resolution_mm,
                                  surface_points_mm)
    # A lone point scores what its crossing edges score (its region against its neighbours').
    doubt = ps.copy()
    if e.size:
        np.maximum.at(doubt, e[:, 0], np.where(lone[e[:, 0]], es, 0.0))
        np.maximum.at(doubt, e[:, 1], np.where(lone[e[:, 1]], es, 0.0))
    cand, cs = np.vstack([ring, cand]), np.concatenate([doubt[owner], cs])
    area = np.concatenate([np.full(owner.size, np.inf), area])
    if resolved and np.any(cs >= threshold):
        resolved = False
        reason += (f"; around {int(np.sum(doubt >= threshold))} points that their region explains badly, that lie "
                   f"between regions or that are their region's only ones, edges longer than {resolution_mm:g} mm "
                   "remain")
    rim, rim_scores, rim_area, rim_from = rim_candidates(positions_mm, e, es, lab, band_points_mm, threshold,
                                                         survey_area_mm)
    if rim_scores.size:
        resolved = False
        reason += f"; {rim_scores.size} seam ends beside the rim band, unprobed beyond them"
        cand, cs, area = np.vstack([cand, rim]), np.concatenate([cs, rim_scores]), np.concatenate([area, rim_area])
    proposed = np.zeros((0, 3))
    proposed_scores = np.zeros(0)
    if not resolved:
        idx = propose_points(cand, cs, positions_mm, budget, min_spacing_mm, threshold, priority=area)
        proposed, proposed_scores = cand[idx], cs[idx]
        if idx.size == 0:
            reason += f"; no candidate keeps {min_spacing_mm:g} mm from existing points"
    hot = es >= threshold
    return DensifyRound(
        round_index=round_index, n_points=int(lab.shape[0]), n_regions=int(np.unique(lab).shape[0]),
        noise_mm=float(noise_mm), threshold=float(threshold),
        pair_scores={f"{a}-{b}": _finite_or_none(v) for (a, b), v in pscores.items()},
        disagreeing_edges=e[hot].tolist(), disagreeing_scores=[_finite_or_none(v) for v in es[hot]],
        proposed_mm=proposed.tolist(), proposed_scores=[_finite_or_none(v) for v in proposed_scores],
        resolved=resolved, reason=reason, extra={"misfit_points": np.flatnonzero(odd).tolist(),
                                                      "ring_around": sorted(set(owner.tolist())),
                                                      "rim_from": rim_from.tolist()})
