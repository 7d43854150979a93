import numpy as np

from elastoprobe.controller.learning.evaluate import (
    boundary_points, depth_monotone_in_force, mirror_residual, mirror_residuals, noise_floor_mm,
    profile_rmse_mm, region_map_scores, roi_mask, window_mask,
)
from elastoprobe.controller.learning.profiles import ProfileGrid

X_MM = ProfileGrid(80.0, 256).x_mm


def line(n):
    return np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])


def test_identical_maps_score_perfectly_under_permutation():
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 100, (400, 3))
    pos[:, 2] = 0
    true = (pos[:, 0] > 50).astype(int) + 2 * (pos[:, 1] > 60)
    perm = np.array([5, 9, 1, 4])[true]            # same partition, other names
    s = region_map_scores(perm, true, None, pos)
    assert s["mislabelled_fraction"] == 0.0
    assert s["worst_region_iou"] == 1.0 and all(v == 1.0 for v in s["per_region_iou"].values())
    assert s["boundary_mm_mean"] == 0.0 and s["boundary_mm_p90"] == 0.0
    assert s["matching"] == {5: 0, 9: 1, 1: 2, 4: 3}


def test_hand_computed_small_case():
    pos = line(10)
    true = np.array([0] * 5 + [1] * 5)
    pred = np.array([7] * 6 + [3] * 4)
    s = region_map_scores(pred, true, None, pos, radius_mm=1.0)
    assert s["matching"] == {3: 1, 7: 0}
    assert np.isclose(s["mislabelled_fraction"], 0.1)
    assert np.isclose(s["per_region_iou"][0], 5 / 6) and np.isclose(s["per_region_iou"][1], 0.8)
    assert np.isclose(s["worst_region_iou"], 0.8)
    # Boundaries: true {4, 5}, predicted {5, 6}; distances 0, 1 and 1, 0.
    assert np.isclose(s["boundary_mm_mean"], 0.5) and np.isclose(s["boundary_mm_p90"], 1.0)
    # Area weights: the mislabelled point 5 stands for three times the area.
    w = np.ones(10)
    w[5] = 3.0
    s = region_map_scores(pred, true, w, pos, radius_mm=1.0)
    assert np.isclose(s["mislabelled_fraction"], 3 / 12)
    assert np.isclose(s["per_region_iou"][1], 4 / 7)


def test_different_numbers_of_regions():
    pos = line(10)
    true = np.array([0] * 5 + [1] * 5)
    over = np.array([0] * 5 + [1] * 3 + [2] * 2)     # one extra predicted region
    s = region_map_scores(over, true, None, pos, radius_mm=1.0)
    assert np.isclose(s["mislabelled_fraction"], 0.2)
    assert np.isclose(s["per_region_iou"][1], 0.6) and s["n_pred_regions"] == 3
    under = np.zeros(10, dtype=int)                  # one predicted region for two true
    s = region_map_scores(under, true, None, pos, radius_mm=1.0)
    assert np.isclose(s["mislabelled_fraction"], 0.5)
    assert min(s["per_region_iou"].values()) == 0.0 and s["worst_region_iou"] == 0.0
    assert s["boundary_mm_mean"] is None
    s = region_map_scores(under, under, None, pos)
    assert s["boundary_mm_mean"] == 0.0 and s["mislabelled_fraction"] == 0.0


def test_boundary_points_radius():
    pos = line(6)
    labels = np.array([0, 0, 0, 1, 1, 1])
    assert boundary_points(labels, pos, 1.0).tolist() == [2, 3]
    assert boundary_points(labels, pos, 2.0).tolist() == [1, 2, 3, 4]


def test_profile_rmse_roi_and_noise_floor():
    truth = np.stack([np.exp(-(X_MM / 5) ** 2) * 2.0, np.exp(-(X_MM / 8) ** 2)])
    roi = roi_mask(truth)
    assert roi[0, 128] and not roi[0, 0]
    pred = truth + 0.1
    assert np.isclose(profile_rmse_mm(pred, truth), 0.1)
    pred_far = truth.copy()
    pred_far[:, np.abs(X_MM) > 35] += 5.0             # errors outside the ROI are not scored
    assert np.isclose(profile_rmse_mm(pred_far, truth), 0.0)
    assert profile_rmse_mm(pred_far, truth, window_mask(X_MM, 40.0)) > 1.0
    rng = np.random.default_rng(1)
    meas = truth + rng.normal(0, 0.05, truth.shape)
    meas[0, 100:120] = np.nan
    assert abs(noise_floor_mm(meas, truth) - 0.05) < 0.01


def shifted_dent_model(symmetric=True):
    def predict(forces_n, angles_deg):
        f = np.asarray(forces_n, dtype=float)[:, None]
        c = np.cos(np.radians(np.asarray(angles_deg, dtype=float)))[:, None]
        shift = 2.0 * c if symmetric else 2.0 * np.abs(c)
        return 0.1 * f * np.exp(-((X_MM[None, :] - shift) / 6.0) ** 2)
    return predict


def test_mirror_residual():
    forces, angles = [5.0, 15.0], [10.0, 45.0, 75.0]
    assert mirror_residual(shifted_dent_model(True), forces, angles, X_MM) < 1e-9
    res = mirror_residuals(shifted_dent_model(False), forces, angles, X_MM)
    assert res.shape == (2, 3) and np.all(res > 0.05)
    assert res[0, 0] > res[0, 2]                      # 10° shifts further than 75°


def test_depth_monotone_in_force():
    forces, angles = [2.0, 5.0, 9.0], [45.0, 90.0]
    good = depth_monotone_in_force(shifted_dent_model(True), forces, angles, x_mm=X_MM)
    assert good == {"peak_fraction": 1.0, "sample_fraction": 1.0}

    def bad(forces_n, angles_deg):
        d = shifted_dent_model(True)(forces_n, angles_deg)
        d[np.asarray(forces_n) == 5.0] *= 3.0          # deeper at 5 N than at 9 N
        return d
    s = depth_monotone_in_force(bad, forces, angles, x_mm=X_MM)
    assert s["peak_fraction"] == 0.5 and s["sample_fraction"] < 0.6


def test_unseen_force_between():
    from elastoprobe.controller.learning.evaluate import unseen_force_between

    forces, angles = [2.0, 5.0, 9.0], [45.0, 90.0, 135.0]
    good = unseen_force_between(shifted_dent_model(True), forces, angles, x_mm=X_MM)
    assert good["fraction"] == 1.0 and good["worst_mm"] == 0.0 and good["cases"] == 6

    def wobbly(forces_n, angles_deg):
        d = shifted_dent_model(True)(forces_n, angles_deg)
        d[np.isclose(forces_n, 7.0)] *= 1.4             # 7 N (between 5 and 9) deeper than 9 N
        return d

    bad = unseen_force_between(wobbly, forces, angles, x_mm=X_MM)
    assert bad["fraction"] < 0.9 and bad["worst_mm"] > 0.05
    assert {(f, a) for f, a, _ in bad["failed_cases"]} == {(7.0, 45.0), (7.0, 90.0), (7.0, 135.0)}
