"""Survey sampling strategies, and the region map they lead to.

Where should the cheap survey probes go? Four answers, compared at the same number of
survey contacts by ``bench/sampling_efficiency.py``:

- **raster**: a regular grid over the object's top surfaces seen from above, coarse to
  fine (a hierarchy of grids whose spacing halves; the budget takes the first nodes);
- **random**: uniformly random points of the reachable surface (area-uniform cloud);
- **neural_gas**: the session's geometry-aware neural gas with one unit per contact;
- **densify**: a small neural-gas start, then rounds of ``densify.plan_round`` adding
  points where adjacent regions disagree.

Every strategy's points go through the same target rules as the session
(:func:`targets.make_targets`: edge clearance, tilt limit, support), so they are valid
probe targets. The region map is built as the session builds it (survey features from
the dent window, :func:`regions.cluster_regions` with target neighbours from the
surface graph) and spread over the surface as the session spreads it
(:func:`surface_map.labels_from_seeds`: nearest labelled target along the surface,
parts split at folds) when a surface graph is given, else by the nearest target in space.

Densify here uses a survey-data proxy instead of fitted region models:
:class:`SurveyMeanModel` predicts a region's mean survey profile (at the survey
settings, which are the only settings ``plan_round`` asks about) with a bootstrap
spread over the region's points. It needs no characterization probes and no training.

Frames and units: object frame, mm; normals unit, outward; ``up`` = +z (the side the
probe comes from); profiles are depths in mm along -n on a grid ``x_mm`` along t.
torch is imported only inside neural-gas training.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from elastoprobe.controller.learning import densify as dn
from elastoprobe.controller.learning import evaluate as ev
from elastoprobe.controller.learning import regions as rg
from elastoprobe.controller.learning import surface_map as sm
from elastoprobe.controller.learning import targets as tg

UP = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- the surface

@dataclass(frozen=True)
class SurveySurface:
    """The scanned object surface: ``points_mm`` (P,3), outward ``normals`` (P,3), PCA
    ``curvature`` (P,), and ``reachable`` (P,) True where the normal is within the tilt
    limit of ``up`` (the surface the region map is scored on)."""

    points_mm: np.ndarray
    normals: np.ndarray
    curvature: np.ndarray
    reachable: np.ndarray

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


def seen_from_above(points_mm: np.ndarray, normals: np.ndarray, cell_mm: float | None = None,
                    cover_tol_mm: float = 3.0) -> np.ndarray:
    """(P,) True for points a scanner sweeping from above can see.

    Drops downward-facing points (n_z < 0) and upward-facing points covered by other
    surface: a point is covered when its xy cell or one of the 8 around it (cells of
    ``cell_mm``, so a sparse cloud still has a covering point nearby) holds surface more
    than ``cover_tol_mm`` higher, e.g. the pillow's top under the box. Walls (n_z ~ 0) are
    kept: the tilted scanner sees them. Default ``cell_mm``: 3 median point spacings.
    """
    p = np.asarray(points_mm, dtype=float)
    nz = np.asarray(normals, dtype=float)[:, 2]
    if cell_mm is None:
        sub = p[np.random.default_rng(0).permutation(p.shape[0])[:5000]]
        cell_mm = 3.0 * float(np.median(cKDTree(p).query(sub, k=2)[0][:, 1]))
    cells = np.floor(p[:, :2] / cell_mm).astype(np.int64)
    cells -= cells.min(axis=0) - 1                     # a free border for the 3x3 neighbourhood
    shape = tuple(cells.max(axis=0) + 2)
    top = np.full(shape, -np.inf)
    np.maximum.at(top, (cells[:, 0], cells[:, 1]), p[:, 2])
    around = top.copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            around[1:-1, 1:-1] = np.maximum(around[1:-1, 1:-1], top[1 + di:shape[0] - 1 + di, 1 + dj:shape[1] - 1 + dj])
    covered = (nz > 0.3) & (p[:, 2] < around[cells[:, 0], cells[:, 1]] - cover_tol_mm)
    return (nz >= 0.0) & ~covered


def make_surface(points_mm: np.ndarray, normals: np.ndarray, max_tilt_deg: float, k: int = 16) -> SurveySurface:
    """A :class:`SurveySurface` from a cloud seen from above (curvature from k-NN PCA)."""
    from elastoprobe.controller.learning.cloud import curvature

    p = np.asarray(points_mm, dtype=float)
    n = np.asarray(normals, dtype=float)
    reach = n @ UP >= np.cos(np.radians(max_tilt_deg))
    return SurveySurface(p, n, curvature(p, k=k), reach)


# --------------------------------------------------------------------------- strategies

def _targets_prefix(found: tg.Targets, budget: int) -> tg.Targets:
    """The first ``budget`` targets (targets come back in their units' order)."""
    k = min(int(budget), len(found))
    return tg.Targets(found.points_mm[:k], found.normals[:k], found.t[:k], found.edge_flag[:k],
                      found.source_unit[:k])


def raster_candidates(surface: SurveySurface, finest_mm: float, levels: int, offset_mm: np.ndarray
                      ) -> np.ndarray:
    """Grid nodes on the top surfaces (C,3) mm in coarse-to-fine order.

    An xy grid of spacing ``finest_mm * 2**(levels-1)`` first, then the nodes each halving
    of the spacing adds; within a level, farthest-point order (so a partly refined level
    stays spread). Each node sits on the highest reachable surface point within half the
    finest spacing of it (the surface seen from above); nodes over no surface are skipped.
    """
    reach = surface.points_mm[surface.reachable]
    lo, hi = reach[:, :2].min(axis=0), reach[:, :2].max(axis=0)
    step = finest_mm * 2 ** (levels - 1)
    origin = lo + np.mod(np.asarray(offset_mm, dtype=float)[:2], step) - step
    n_xy = np.ceil((hi - origin) / finest_mm).astype(int) + 1
    ii, jj = np.meshgrid(np.arange(n_xy[0]), np.arange(n_xy[1]), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    xy = origin + finest_mm * np.column_stack([ii, jj])
    # The coarsest level whose grid holds the node: 0 = coarsest.
    level = np.full(ii.shape, levels - 1)
    for lv in range(levels - 2, -1, -1):
        k = 2 ** (levels - 1 - lv)
        level[(ii % k == 0) & (jj % k == 0)] = lv
    tree = cKDTree(reach[:, :2])
    near = tree.query_ball_point(xy, 0.5 * finest_mm)
    keep = [i for i, nb in enumerate(near) if nb]
    nodes = np.array([reach[near[i]][np.argmax(reach[near[i], 2])] for i in keep]).reshape(-1, 3)
    lev = level[keep]
    ordered: list[np.ndarray] = []
    for lv in range(levels):
        pts = nodes[lev == lv]
        ordered.append(pts[_farthest_order(pts, np.concatenate(ordered) if ordered else None)])
    return np.concatenate(ordered) if ordered else np.zeros((0, 3))


def _farthest_order(points: np.ndarray, taken: np.ndarray | None) -> np.ndarray:
    """Greedy farthest-point order of ``points`` given points already ``taken`` (xy distances)."""
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    xy = points[:, :2]
    if taken is not None and len(taken):
        dist = cKDTree(taken[:, :2]).query(xy)[0]
    else:
        dist = np.linalg.norm(xy - xy.mean(axis=0), axis=1)
        dist = dist.max() - dist          # start at the centre
    order = np.empty(n, dtype=np.int64)
    for k in range(n):
        i = int(np.argmax(dist))
        order[k] = i
        dist = np.minimum(dist, np.linalg.norm(xy - xy[i], axis=1))
        dist[i] = -1.0
    return order


def raster_targets(surface: SurveySurface, rules: tg.TargetRules, budget: int, seed: int = 0,
                   reference_dir: np.ndarray = np.array([0.0, 1.0, 0.0]), oversample: float = 2.5,
                   coarsest_nodes: float = 4.0) -> tg.Targets:
    """The first ``budget`` valid targets of a coarse-to-fine raster (grid offset drawn from ``seed``).

    The finest spacing is chosen so the finest grid holds about ``oversample`` x budget
    nodes over the reachable area, so the budget ends inside the last refinements; the
    coarsest grid holds about ``coarsest_nodes``. Any prefix of the result is itself a
    coarse-to-fine raster, so one call at the largest budget serves every smaller one.
    """
    area_mm2 = _reachable_area_mm2(surface)
    finest = float(np.sqrt(area_mm2 / (oversample * max(budget, 1))))
    coarsest = float(np.sqrt(area_mm2 / coarsest_nodes))
    levels = max(1, int(np.floor(np.log2(max(coarsest / finest, 1.0)))) + 1)
    offset = np.random.default_rng([seed, 31]).uniform(0.0, finest * 2 ** (levels - 1), 2)
    cand = raster_candidates(surface, finest, levels, offset)
    found = tg.make_targets(cand, surface.points_mm, surface.normals, surface.curvature, rules, reference_dir)
    return _targets_prefix(found, budget)


def _reachable_area_mm2(surface: SurveySurface, cell_mm: float = 4.0) -> float:
    """Area (mm^2) of the reachable surface projected on the table (occupied xy cells)."""
    xy = surface.points_mm[surface.reachable, :2]
    return float(np.unique(np.floor(xy / cell_mm).astype(np.int64), axis=0).shape[0] * cell_mm ** 2)


def random_targets(surface: SurveySurface, rules: tg.TargetRules, budget: int, seed: int = 0,
                   reference_dir: np.ndarray = np.array([0.0, 1.0, 0.0])) -> tg.Targets:
    """The first ``budget`` valid targets among uniformly random reachable surface points
    (the cloud is area-uniform, so a uniform draw of its points is uniform in area)."""
    idx = np.flatnonzero(surface.reachable)
    order = np.random.default_rng([seed, 41]).permutation(idx)
    # Enough candidates for the rules to drop some, without testing the whole cloud: draw
    # more (the same prefix, longer) until the budget is met.
    n_cand = 2 * budget + 20
    while True:
        cand = surface.points_mm[order[: min(order.size, n_cand)]]
        found = tg.make_targets(cand, surface.points_mm, surface.normals, surface.curvature, rules, reference_dir)
        if len(found) >= budget or n_cand >= order.size:
            return _targets_prefix(found, budget)
        n_cand *= 2


def neural_gas_targets(surface: SurveySurface, rules: tg.TargetRules, n_units: int, seed: int = 0,
                       reference_dir: np.ndarray = np.array([0.0, 1.0, 0.0]), geometry_weight: float = 1.0,
                       steps_per_unit: int = 200) -> tg.Targets:
    """Targets from geometry-aware neural gas with ``n_units`` units, as the session's sampling phase
    (trained on the probe-able surface, features xyz + scaled normals, curvature-weighted
    draws, 256-sample minibatches)."""
    from elastoprobe.controller.learning import neural_gas as ng

    where = tg.probeable(surface.points_mm, surface.normals, surface.curvature, rules)
    if np.count_nonzero(where) < n_units:
        where = np.ones(len(surface), bool)
    feats, weights = ng.geometry_aware_inputs(surface.points_mm[where], surface.normals[where],
                                              surface.curvature[where], normal_weight_mm=10.0 * geometry_weight)
    result = ng.train_neural_gas(feats, n_units=int(n_units), n_steps=max(200, n_units * steps_per_unit // 16),
                                 batch_size=256, seed=seed, sample_weights=weights)
    units = np.asarray(result.units)[:, :3].astype(np.float64)
    return tg.make_targets(units, surface.points_mm, surface.normals, surface.curvature, rules, reference_dir)


# --------------------------------------------------------------------------- regions

def dent_features(depth_mm: np.ndarray, x_mm: np.ndarray, forces_n: np.ndarray,
                  half_window_mm: float = 15.0) -> tuple[np.ndarray, list[str]]:
    """Survey features (N,D) from the dent window |x| <= ``half_window_mm`` of profiles (N,F,L)."""
    window = np.abs(np.asarray(x_mm, dtype=float)) <= half_window_mm
    return rg.survey_features(np.asarray(depth_mm, dtype=float)[:, :, window], np.asarray(x_mm)[window], forces_n)


def region_labels(points_mm: np.ndarray, normals: np.ndarray, depth_mm: np.ndarray, x_mm: np.ndarray,
                  forces_n: np.ndarray, seed: int = 0, half_window_mm: float = 15.0,
                  graph: sm.SurfaceGraph | None = None, noise_mm: float | None = None,
                  previous_labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, rg.RegionMap, np.ndarray]:
    """Regions of surveyed points as the session's regions phase finds them, seen points only.

    ``depth_mm`` (N,F,L): averaged survey profiles. A point whose dent window the scanner
    never saw at some survey force (e.g. occluded by a taller part) has no features and is
    left out instead of entering the clustering with made-up (mean) features.
    Neighbours: cells of the surface ``graph`` that touch (as the session), or without one
    a k-NN chord graph (:func:`targets.surface_graph`).
    ``noise_mm`` (the standard error of an averaged profile) and ``previous_labels`` (N,)
    (each point's region in the previous round, -1 if new) as the session passes them to
    :func:`regions.cluster_regions`.
    Returns (seen (N,) bool, labels (S,) of the seen points, the RegionMap, surface-graph
    edges (E,2) indexing the seen points).
    """
    feats, names = dent_features(depth_mm, x_mm, forces_n, half_window_mm)
    seen = np.all(np.isfinite(feats), axis=1)
    pts, nrm = np.asarray(points_mm)[seen], np.asarray(normals)[seen]
    if not seen.any():
        raise ValueError("no surveyed point has a measured dent: cannot find regions")
    if graph is not None:
        edges = np.asarray(sm.seed_neighbours(graph, sm.cells(graph, pts)), dtype=np.int64).reshape(-1, 2)
    else:
        edges = np.asarray(tg.surface_graph(pts, nrm), dtype=np.int64).reshape(-1, 2)
    prev = None if previous_labels is None else np.asarray(previous_labels, dtype=np.int64).reshape(-1)[seen]
    rmap = rg.cluster_regions(feats[seen], edges, names, seed=seed, noise_mm=noise_mm, previous_labels=prev)
    return seen, rmap.labels, rmap, edges


def map_error(target_points_mm: np.ndarray, target_labels: np.ndarray, eval_points_mm: np.ndarray,
              true_labels: np.ndarray, graph: sm.SurfaceGraph | None = None,
              eval_index: np.ndarray | None = None, seed_levels: np.ndarray | None = None) -> dict:
    """Scores (``evaluate.region_map_scores``) of the map spread from labelled targets to the
    evaluation points, against their true labels (equal area per point).

    With ``graph`` (over the surface) and ``eval_index`` (the evaluation points' indices in
    it): the session's map (:func:`surface_map.labels_from_seeds`, ``seed_levels`` (S,) each
    target's survey level as the session's final phase gives it); else the nearest target."""
    if graph is not None and eval_index is not None:
        pred = sm.labels_from_seeds(graph, target_points_mm, target_labels,
                                    seed_levels=seed_levels)[np.asarray(eval_index)]
    else:
        pred = rg.propagate_labels(target_points_mm, target_labels, eval_points_mm)
    return ev.region_map_scores(pred, true_labels, None, eval_points_mm)


# --------------------------------------------------------------------------- densify proxy

class SurveyMeanModel:
    """A region's survey profiles as a stand-in for its fitted model (densify's ProfileModel).

    ``predict_batch_mm(F, α)``: the mean profile (NaN-aware over points) of the survey force
    nearest F (α is ignored: the survey has one angle); ``predict_ensemble``: that mean and
    the spread of bootstrap means over the region's points — the disagreement a model
    ensemble bootstrapped over probe points would show. NaN samples count as 0 depth
    only where no point of the region saw them.
    """

    def __init__(self, depth_mm: np.ndarray, forces_n: np.ndarray, seed: int = 0, n_boot: int = 16) -> None:
        d = np.asarray(depth_mm, dtype=float)             # (M,F,L)
        self.forces_n = np.asarray(forces_n, dtype=float)
        self._mean = np.nan_to_num(_nanmean0(d))
        rng = np.random.default_rng([seed, 53])
        boots = np.stack([_nanmean0(d[rng.integers(0, d.shape[0], d.shape[0])]) for _ in range(n_boot)])
        self._spread = np.nan_to_num(np.nanstd(boots, axis=0))

    def _rows(self, force_n: np.ndarray) -> np.ndarray:
        f = np.asarray(force_n, dtype=float).reshape(-1)
        return np.argmin(np.abs(f[:, None] - self.forces_n[None, :]), axis=1)

    def predict_batch_mm(self, force_n: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        return self._mean[self._rows(force_n)]

    def predict_ensemble(self, force_n: np.ndarray, angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows = self._rows(force_n)
        return self._mean[rows], self._spread[rows]


def _nanmean0(d: np.ndarray) -> np.ndarray:
    """NaN-aware mean over axis 0; NaN where every row is NaN (no warning)."""
    ok = np.isfinite(d)
    count = ok.sum(axis=0)
    total = np.where(ok, d, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def densify_step(round_index: int, points_mm: np.ndarray, normals: np.ndarray, labels: np.ndarray,
                 edges: np.ndarray, depth_mm: np.ndarray, x_mm: np.ndarray, forces_n: np.ndarray,
                 angles_deg: np.ndarray, noise_mm: float, budget: int, min_spacing_mm: float,
                 resolution_mm: float, surface: SurveySurface, seed: int = 0,
                 half_window_mm: float = 15.0, graph: sm.SurfaceGraph | None = None
                 ) -> tuple[np.ndarray, np.ndarray, dn.DensifyRound]:
    """One densify round with :class:`SurveyMeanModel` per region (dent window only), the
    survey's own evidence (densify.survey_evidence) and, with the surface ``graph``, the
    border each edge's cells share (as the session's densify phase).

    Returns (new points (K,3) mm snapped to the reachable surface, their normals (K,3), the
    round record). New points are not run through the target rules (as in the session,
    which only checks their reachability).
    """
    window = np.abs(np.asarray(x_mm, dtype=float)) <= half_window_mm
    d = np.asarray(depth_mm, dtype=float)[:, :, window]
    lab = np.asarray(labels)
    models = {int(r): SurveyMeanModel(d[lab == r], forces_n, seed=seed + 7 * int(r)) for r in np.unique(lab)}
    reach_pts = surface.points_mm[surface.reachable]
    feats, names = dent_features(depth_mm, x_mm, forces_n, half_window_mm)
    rnd = dn.plan_round(round_index, points_mm, edges, lab, models, forces_n=np.asarray(forces_n, float),
                        angles_deg=np.asarray(angles_deg, float), noise_mm=noise_mm, budget=budget,
                        min_spacing_mm=min_spacing_mm, resolution_mm=resolution_mm, surface_points_mm=reach_pts,
                        border=None if graph is None else sm.shared_border(graph, sm.cells(graph, points_mm), edges),
                        **dn.survey_evidence(feats, names, lab, noise_mm))
    new = np.asarray(rnd.proposed_mm, dtype=float).reshape(-1, 3)
    if new.shape[0] == 0:
        return new, np.zeros((0, 3)), rnd
    _, idx = cKDTree(surface.points_mm).query(new)
    return new, surface.normals[idx], rnd
