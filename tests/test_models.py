import json

import numpy as np
import pytest

from elastoprobe.controller.core.geometry import NINE_ANGLES_DEG
from elastoprobe.controller.learning.models import (
    RegionModel, TrainConfig, bootstrap_point_weights, fit_region_model,
)
from elastoprobe.controller.learning.profiles import ProfileGrid

X_MM = ProfileGrid(80.0, 256).x_mm
FORCES_N = [2.0, 5.0, 9.0, 14.0, 20.0]
NOISE_MM = 0.01


def hertz_profile_mm(x_mm, force_n, angle_deg, e_mpa=2.0, nu=0.49, tip_radius_mm=5.0, shift_gain=0.25):
    """Rubber-like dent: Hertz surface displacement under P = F sin α, shifted along +t by a
    Mindlin-like tangential displacement ~ Q = F cos α, plus the (small) Cerruti term."""
    e_star = e_mpa / (1 - nu ** 2)
    a_rad = np.radians(angle_deg)
    p, q = force_n * np.sin(a_rad), force_n * np.cos(a_rad)
    a = (3 * p * tip_radius_mm / (4 * e_star)) ** (1 / 3)
    shift = shift_gain * q / (a * e_star)
    r = np.abs(x_mm - shift)
    w = np.empty_like(r)
    inside = r <= a
    w[inside] = a ** 2 / tip_radius_mm - r[inside] ** 2 / (2 * tip_radius_mm)
    ro = r[~inside]
    w[~inside] = a ** 2 / (np.pi * tip_radius_mm) * ((2 - ro ** 2 / a ** 2) * np.arcsin(a / ro)
                                                   + np.sqrt(ro ** 2 / a ** 2 - 1))
    w += (1 + nu) * (1 - 2 * nu) * q * np.sign(x_mm - shift) / (2 * np.pi * e_mpa * np.sqrt((x_mm - shift) ** 2 + a ** 2))
    return w


def dataset(forces, angles, seed=0, noise_mm=NOISE_MM, dropout=0.02, points=1):
    rng = np.random.default_rng(seed)
    f, a = np.meshgrid(forces, angles, indexing="ij")
    f, a = np.tile(f.ravel(), points), np.tile(a.ravel(), points)
    ids = np.repeat(np.arange(points), len(forces) * len(angles))
    truth = np.stack([hertz_profile_mm(X_MM, fi, ai) for fi, ai in zip(f, a)])
    meas = truth + rng.normal(0, noise_mm, truth.shape)
    meas[rng.random(meas.shape) < dropout] = np.nan
    return f, a, meas, truth, ids


FAST = TrainConfig(ensemble=0, stages=2, epochs_per_stage=1000, seed=3)


@pytest.fixture(scope="module")
def fitted():
    f, a, meas, truth, _ = dataset(FORCES_N, NINE_ANGLES_DEG)
    return fit_region_model(f, a, meas, X_MM, config=FAST, noise_mm=NOISE_MM), (f, a, meas, truth)


def test_fits_nine_by_five_to_low_error(fitted):
    model, (f, a, _, truth) = fitted
    rmse_mm = float(np.sqrt(np.mean((model.predict_batch_mm(f, a) - truth) ** 2)))
    assert rmse_mm < 2.0 * NOISE_MM, rmse_mm
    assert model.meta["train_mse_norm"] < 1e-4
    assert model.meta["training"]["stop_reason"][0] in ("goal", "plateau", "max_epochs")
    # Unseen forces and angles, against the noise-free truth: within 3 % of the deepest dent.
    fu, au = np.array([7.0, 17.0, 11.0]), np.array([30.0, 60.0, 120.0])
    truth_u = np.stack([hertz_profile_mm(X_MM, fi, ai) for fi, ai in zip(fu, au)])
    err = np.sqrt(np.mean((model.predict_batch_mm(fu, au) - truth_u) ** 2))
    assert err < 0.03 * truth.max(), err


@pytest.mark.parametrize("angle_deg", [90.0, 45.0, 135.0])
def test_unseen_force_lies_between_neighbours(fitted, angle_deg):
    model, _ = fitted
    lo, mid, hi = model.predict_batch_mm([9.0, 11.5, 14.0], [angle_deg] * 3)
    truth_lo = hertz_profile_mm(X_MM, 9.0, angle_deg)
    roi = truth_lo > 0.1 * truth_lo.max()
    assert roi.sum() > 10
    below = np.minimum(lo, hi)[roi]
    above = np.maximum(lo, hi)[roi]
    assert np.all(mid[roi] >= below - 1e-6) and np.all(mid[roi] <= above + 1e-6)
    assert mid[roi].max() > lo[roi].max() and mid[roi].max() < hi[roi].max()


def test_numpy_serving_equals_torch_forward(fitted):
    import torch
    model, _ = fitted
    rng = np.random.default_rng(5)
    fq, aq = rng.uniform(1, 22, 50), rng.uniform(5, 175, 50)
    ref = model.torch_forward_mm(fq, aq)
    assert np.max(np.abs(model.predict_batch_mm(fq, aq) - ref)) < 1e-6
    out = np.empty(model.outputs)
    for i in range(5):
        single = model.predict_mm(float(fq[i]), float(aq[i]))
        assert np.max(np.abs(single - ref[i])) < 1e-6
        model.predict_mm(fq[i], aq[i], out=out)
        assert np.array_equal(out, single)
    with torch.no_grad():
        mod = model.torch_module()(torch.from_numpy(np.column_stack([fq, aq])))
    assert np.max(np.abs(mod.numpy() - ref)) < 1e-6


def test_sigmoid_serving_equals_torch():
    f, a, meas, _, _ = dataset([2.0, 8.0, 20.0], [45.0, 90.0, 135.0])
    cfg = TrainConfig(activation="sigmoid", ensemble=1, stages=1, epochs_per_stage=200, seed=1)
    model = fit_region_model(f, a, meas, X_MM, config=cfg)
    ref = model.torch_forward_mm(np.array([3.0, 15.0]), np.array([60.0, 100.0]))
    assert np.max(np.abs(model.predict_batch_mm([3.0, 15.0], [60.0, 100.0]) - ref)) < 1e-6
    members = model.predict_members_mm(np.array([3.0]), np.array([60.0]))
    assert np.max(np.abs(members[1, 0] - model.torch_forward_mm(3.0, 60.0, member=1)[0])) < 1e-6


def test_save_load_round_trip(tmp_path, fitted):
    model, _ = fitted
    model.save(tmp_path / "region_0")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["region_0.json", "region_0.npz"]
    meta = json.loads((tmp_path / "region_0.json").read_text())
    for key in ("units", "force_range_n", "angle_range_deg", "depth_scale_mm", "grid", "train_mse_norm",
                "training", "versions", "seed", "data_sha256", "model_hash"):
        assert key in meta
    back = RegionModel.load(tmp_path / "region_0.npz")
    assert back.model_hash() == model.model_hash() == meta["model_hash"]
    q = (np.array([3.3, 18.0]), np.array([20.0, 150.0]))
    assert np.array_equal(back.predict_batch_mm(*q), model.predict_batch_mm(*q))
    assert np.array_equal(back.predict_mm(12.0, 80.0), model.predict_mm(12.0, 80.0))
    # A weights file that does not belong to the metadata is refused.
    other = RegionModel(model.w1 * 1.01, model.b1, model.w2, model.b2, x_mm=model.x_mm,
                        force_range_n=model.force_range_n, depth_scale_mm=model.depth_scale_mm)
    assert other.model_hash() != model.model_hash()
    other.save(tmp_path / "other")
    (tmp_path / "other.npz").replace(tmp_path / "region_0.npz")
    with pytest.raises(ValueError):
        RegionModel.load(tmp_path / "region_0")


def test_masked_loss_ignores_missing_samples():
    f, a, meas, _, _ = dataset([3.0, 10.0, 20.0], [25.0, 90.0, 155.0], dropout=0.0)
    cfg = TrainConfig(ensemble=0, stages=1, epochs_per_stage=300, seed=7)
    with_nan = meas.copy()
    half = np.zeros_like(meas, dtype=bool)
    half[4, ::2] = True                      # half the samples of one profile
    with_nan[half] = np.nan
    garbage = meas.copy()
    garbage[half] = 1e3                      # finite nonsense, excluded only by the mask
    kw = dict(depth_scale=float(np.max(meas)), force_range_n=(3.0, 20.0))
    m_nan = fit_region_model(f, a, with_nan, X_MM, config=cfg, **kw)
    m_without = fit_region_model(f, a, garbage, X_MM, mask=~half, config=cfg, **kw)
    m_garbage = fit_region_model(f, a, garbage, X_MM, config=cfg, **kw)
    q = (np.array([5.0, 15.0]), np.array([40.0, 120.0]))
    assert np.allclose(m_nan.predict_batch_mm(*q), m_without.predict_batch_mm(*q), atol=1e-9)
    assert np.all(np.isfinite(m_nan.predict_batch_mm(*q)))
    # The same samples left in do change the fit (the test can fail).
    assert not np.allclose(m_garbage.predict_batch_mm(*q), m_nan.predict_batch_mm(*q), atol=1e-3)


def test_deterministic_with_seed_and_ensemble_over_points():
    f, a, meas, _, ids = dataset([3.0, 12.0], [45.0, 90.0, 135.0], points=4, seed=2)
    cfg = TrainConfig(ensemble=3, stages=1, epochs_per_stage=150, seed=11)
    m1 = fit_region_model(f, a, meas, X_MM, point_ids=ids, config=cfg)
    m2 = fit_region_model(f, a, meas, X_MM, point_ids=ids, config=cfg)
    assert m1.model_hash() == m2.model_hash()
    m3 = fit_region_model(f, a, meas, X_MM, point_ids=ids, config=TrainConfig(ensemble=3, stages=1,
                                                                                epochs_per_stage=150, seed=12))
    assert m3.model_hash() != m1.model_hash()
    mean, std = m1.predict_ensemble(8.0, 90.0)
    assert mean.shape == std.shape == (256,) and np.all(std >= 0) and std.max() > 0
    mean_q, std_q = m1.predict_ensemble(np.array([8.0, 4.0]), np.array([90.0, 45.0]))
    assert mean_q.shape == (2, 256) and np.allclose(mean_q[0], mean)


def test_bootstrap_weights_resample_points_not_rows():
    ids = np.repeat(np.arange(5), 7)
    w = bootstrap_point_weights(ids, 20, np.random.default_rng(0))
    assert np.all(w[0] == 1)
    for row in w[1:]:
        per_point = row.reshape(5, 7)
        assert np.all(per_point == per_point[:, :1])     # all rows of a point share its draw count
        assert per_point[:, 0].sum() == 5
    assert len({tuple(r) for r in w[1:]}) > 1
