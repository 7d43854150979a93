"""Gaussian-process active search (bench/gp_search.py): the bench's GP peer."""
from __future__ import annotations

import numpy as np

from bench import gp_search as gps
from bench import strategies as st
from elastoprobe.controller.learning import targets as tg

X_MM = np.linspace(-20.0, 20.0, 41)


def _plane(n: int = 6000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A flat 200 x 120 mm top at z = 30 mm, points (n,3) mm and normals +z."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-100.0, -60.0], [100.0, 60.0], size=(n, 2))
    pts = np.column_stack([xy, np.full(n, 30.0)])
    return pts, np.tile([0.0, 0.0, 1.0], (n, 1))


def _dent(peak_mm: float) -> np.ndarray:
    """A dent of ``peak_mm`` at x = 0, Gaussian of 6 mm width, on X_MM."""
    return peak_mm * np.exp(-0.5 * (X_MM / 6.0) ** 2)


def test_dent_level_is_the_mean_log_peak_in_the_window_and_nan_where_unseen():
    d = np.stack([np.stack([_dent(1.0), _dent(4.0)]), np.stack([_dent(0.001), _dent(0.5)])])
    d[0, 0, np.abs(X_MM) > 15] = 50.0                     # outside the window: ignored
    lv = gps.dent_level(d, X_MM, half_window_mm=15.0)
    assert np.allclose(lv[0], np.mean(np.log([1.0, 4.0])))
    assert np.allclose(lv[1], np.mean(np.log([gps.PEAK_FLOOR_MM, 0.5])))     # floored, finite
    d[1, 1, :] = np.nan                                    # one force's dent never seen
    assert np.isnan(gps.dent_level(d, X_MM)[1]) and np.isfinite(gps.dent_level(d, X_MM)[0])


def test_region_levels_lie_midway_between_sorted_region_means():
    values = np.array([2.0, 2.2, -1.0, -1.2, 0.4, 0.6])
    labels = np.array([7, 7, 3, 3, 5, 5])
    levels, bands = gps.region_levels(values, labels)
    assert np.allclose(levels, [(-1.1 + 0.5) / 2, (0.5 + 2.1) / 2])
    assert list(bands) == [3, 5, 7]
    one_levels, one_bands = gps.region_levels(values[:2], labels[:2])
    assert one_levels.size == 0 and list(one_bands) == [7]


def test_straddle_prefers_uncertain_points_near_a_level_and_explores_with_none():
    mean = np.array([0.0, 0.0, 2.0, 2.0])
    std = np.array([0.1, 0.5, 0.1, 0.5])
    s = gps.straddle(mean, std, np.array([0.1]), kappa=2.0)
    assert np.allclose(s, [0.2 - 0.1, 1.0 - 0.1, 0.2 - 1.9, 1.0 - 1.9])
    assert int(np.argmax(s)) == 1
    assert np.allclose(gps.straddle(mean, std, np.array([])), std)


def test_gp_search_finds_and_maps_a_two_material_seam():
    """A plane in two materials (x < 20 mm: dents 0.3 mm; beyond: 3 mm, 10x): from a coarse
    start the straddle puts the next probes near the seam, and the GP's own map of the
    plane is right away from it."""
    pts, nrm = _plane()
    surface = st.make_surface(pts, nrm, 30.0)
    rules = tg.TargetRules(tip_radius_mm=5.0, edge_clearance_radii=2.0, max_tilt_deg=30.0)
    cand = gps.candidates(surface, rules, 8.0)
    assert len(cand) > 100
    d = np.linalg.norm(cand.points_mm[:, None] - cand.points_mm[None], axis=2) + np.eye(len(cand)) * 1e9
    assert d.min() >= 0.95 * 8.0 - 1e-6

    def truth(p: np.ndarray) -> np.ndarray:
        return (p[:, 0] > 20.0).astype(int)

    def level(p: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(len(p))
        return np.log(np.where(truth(p) == 1, 3.0, 0.3)) + rng.normal(0.0, 0.05, len(p))

    taken = st.raster_targets(surface, rules, 12, seed=1).points_mm
    for _ in range(12):
        gp = gps.fit_surface_gp(taken, level(taken), seed=0)
        levels, _ = gps.region_levels(level(taken), truth(taken))
        k = gps.next_probe(gp, cand.points_mm, taken, levels, min_spacing_mm=6.0)
        assert k is not None
        assert np.min(np.linalg.norm(taken - cand.points_mm[k], axis=1)) >= 6.0
        taken = np.vstack([taken, cand.points_mm[k]])
    added = taken[12:]
    assert np.median(np.abs(added[:, 0] - 20.0)) < 15.0          # the search went to the seam
    gp = gps.fit_surface_gp(taken, level(taken), seed=0)
    levels, bands = gps.region_levels(level(taken), truth(taken))
    mapped = gps.region_map(gp, pts, levels, bands, chunk=1000)
    far = np.abs(pts[:, 0] - 20.0) > 15.0
    assert np.mean(mapped[far] == truth(pts[far])) > 0.98
    assert np.mean(mapped == truth(pts)) > 0.9


def test_next_probe_is_none_when_every_candidate_is_taken():
    pts, nrm = _plane()
    surface = st.make_surface(pts, nrm, 30.0)
    rules = tg.TargetRules(tip_radius_mm=5.0, edge_clearance_radii=2.0, max_tilt_deg=30.0)
    cand = gps.candidates(surface, rules, 20.0)
    gp = gps.fit_surface_gp(cand.points_mm[:5], np.arange(5.0))
    assert gps.next_probe(gp, cand.points_mm, cand.points_mm, np.array([1.0]), min_spacing_mm=1.0) is None
