"""Gaussian-process active search: the palpation literature's answer to "where next?".

A peer for the survey strategies of :mod:`strategies` (compared by
``bench/sampling_efficiency.py``), after Garg et al. 2016 and Salman et al. 2018: a GP over
the surface models a scalar of each probe's dent, and each next probe goes where a
level-set acquisition is largest, i.e. where the GP is least sure on which side of a
level between materials the surface lies. Its map is the GP's own: each surface point
takes the region of the band its posterior mean falls in.

- The scalar (:func:`dent_level`): the mean over the survey forces of ln(peak dent / mm)
  in the dent window. A log, because materials differ by factors: a stiff inclusion and
  a soft matrix are as far apart on it as two soft materials of the same ratio.
- The GP (:func:`fit_surface_gp`): constant x squared-exponential covariance of the 3-D
  distance plus white noise, hyperparameters by maximum likelihood (scikit-learn's
  ``GaussianProcessRegressor``).
- The levels (:func:`region_levels`): midway between the mean scalar of neighbouring
  regions, as the session's clustering finds them among the probes so far.
- The acquisition (:func:`straddle`): kappa sigma - |mu - h| at the nearest level h
  (Bryan et al. 2005); with one region so far, sigma alone (explore).

Frames and units: object frame, mm; depths in mm along -n on a grid ``x_mm`` along t.
"""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from bench.strategies import SurveySurface, raster_candidates
from elastoprobe.controller.learning import targets as tg

# The straddle's confidence multiplier (Bryan et al. 2005, as used for level-set estimation
# by Gotovos et al. 2013 and the palpation papers): a candidate scores kappa*sigma - |mu - h|.
STRADDLE_KAPPA = 1.96
# Peaks below this are noise (~ the averaged profile's noise): floored so ln stays finite.
PEAK_FLOOR_MM = 0.01


def candidates(surface: SurveySurface, rules: tg.TargetRules, spacing_mm: float,
               reference_dir: np.ndarray = np.array([0.0, 1.0, 0.0])) -> tg.Targets:
    """Every valid target on an xy grid of ``spacing_mm`` (mm) over the reachable top: where the
    search may probe next (the same target rules as every strategy, targets at least
    0.95 ``spacing_mm`` apart)."""
    nodes = raster_candidates(surface, float(spacing_mm), 1, np.zeros(2))
    dense = replace(rules, min_spacing_mm=0.95 * float(spacing_mm))
    return tg.make_targets(nodes, surface.points_mm, surface.normals, surface.curvature, dense, reference_dir)


def dent_level(depth_mm: np.ndarray, x_mm: np.ndarray, half_window_mm: float = 15.0,
               floor_mm: float = PEAK_FLOOR_MM) -> np.ndarray:
    """(N,) the scalar the GP models: the mean over forces of ln(peak depth / mm) within
    |x| <= ``half_window_mm`` of profiles ``depth_mm`` (N,F,L) mm on ``x_mm`` (L,) mm, peaks
    floored at ``floor_mm``; NaN where some force's dent window was never seen."""
    d = np.asarray(depth_mm, dtype=float)
    window = np.abs(np.asarray(x_mm, dtype=float)) <= half_window_mm
    w = d[:, :, window]
    seen = np.isfinite(w).any(axis=2)                         # (N,F)
    peaks = np.where(seen, np.max(np.where(np.isfinite(w), w, -np.inf), axis=2), np.nan)
    level = np.log(np.maximum(np.where(seen, peaks, 1.0), floor_mm)).mean(axis=1)
    return np.where(seen.all(axis=1), level, np.nan)


def fit_surface_gp(points_mm: np.ndarray, values: np.ndarray, seed: int = 0) -> GaussianProcessRegressor:
    """A GP of ``values`` (N,) over ``points_mm`` (N,3) mm, by maximum likelihood.

    Length scale bounded to [2 mm, 1 m], starting from the mean spacing of the points
    (the square root of their bounding box's area per point); white noise from 1e-4 to 1
    of the normalised variance."""
    p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    span_mm2 = float(np.prod(np.maximum(np.ptp(p[:, :2], axis=0), 1.0)))
    start_mm = float(np.clip(np.sqrt(span_mm2 / max(len(p), 1)), 2.0, 1000.0))
    kernel = (ConstantKernel(1.0, (1e-3, 1e3)) * RBF(start_mm, (2.0, 1000.0))
              + WhiteKernel(1e-2, (1e-4, 1.0)))
    gp = GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=1, random_state=seed)
    with warnings.catch_warnings():
        # A bound reached (a plain object: the longest length scale) is an answer, not an error.
        warnings.simplefilter("ignore")
        gp.fit(p, np.asarray(values, dtype=float).reshape(-1))
    return gp


def region_levels(values: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The levels between regions: (levels (K-1,), the region of each band (K,)) from each
    region's mean value, sorted; a level lies midway between neighbouring means. Band b
    (values between levels b-1 and b) is region ``bands[b]``."""
    v = np.asarray(values, dtype=float).reshape(-1)
    lab = np.asarray(labels).reshape(-1)
    regions = np.unique(lab)
    means = np.array([v[lab == r].mean() for r in regions])
    order = np.argsort(means)
    m = means[order]
    return (m[:-1] + m[1:]) / 2.0, regions[order]


def straddle(mean: np.ndarray, std: np.ndarray, levels: np.ndarray, kappa: float = STRADDLE_KAPPA) -> np.ndarray:
    """The level-set acquisition (N,): kappa*sigma - |mu - h| at the nearest level h (Bryan et
    al.'s straddle, Gotovos et al.'s ambiguity; Garg et al.'s ILS-UCB with gamma =
    kappa/(1+kappa) ranks the same). With no level (one region so far): sigma."""
    mu = np.asarray(mean, dtype=float).reshape(-1)
    sd = np.asarray(std, dtype=float).reshape(-1)
    lv = np.asarray(levels, dtype=float).reshape(-1)
    if lv.size == 0:
        return sd
    return kappa * sd - np.min(np.abs(mu[:, None] - lv[None, :]), axis=1)


def next_probe(gp: GaussianProcessRegressor, candidates_mm: np.ndarray, taken_mm: np.ndarray, levels: np.ndarray,
               min_spacing_mm: float, kappa: float = STRADDLE_KAPPA) -> int | None:
    """Index of the candidate (C,3) mm the straddle prefers among those at least
    ``min_spacing_mm`` from every point already taken; None when none is left."""
    c = np.asarray(candidates_mm, dtype=float).reshape(-1, 3)
    free = np.ones(len(c), bool)
    taken = np.asarray(taken_mm, dtype=float).reshape(-1, 3)
    if len(taken):
        free = cKDTree(taken).query(c)[0] >= min_spacing_mm
    if not free.any():
        return None
    idx = np.flatnonzero(free)
    mu, sd = gp.predict(c[idx], return_std=True)
    return int(idx[int(np.argmax(straddle(mu, sd, levels, kappa)))])


def region_map(gp: GaussianProcessRegressor, points_mm: np.ndarray, levels: np.ndarray, bands: np.ndarray,
               chunk: int = 20_000) -> np.ndarray:
    """(P,) the GP's own map of ``points_mm`` (P,3) mm: each point the region of the band its
    posterior mean falls in."""
    p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    b = np.asarray(bands)
    lv = np.asarray(levels, dtype=float)
    out = np.empty(len(p), dtype=b.dtype)
    for a in range(0, len(p), chunk):
        out[a:a + chunk] = b[np.searchsorted(lv, gp.predict(p[a:a + chunk]))]
    return out
