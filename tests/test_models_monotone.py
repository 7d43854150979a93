"""The region model's monotone-in-force training penalty (issue 3): a profile predicted at
an unseen force between two trained forces lies between theirs."""
from dataclasses import replace

import numpy as np
import pytest

from elastoprobe.controller.learning.models import TrainConfig, _monotone_penalty, fit_region_model

from test_models import X_MM, dataset, hertz_profile_mm

FORCES_N = [2.0, 5.0, 9.0, 14.0, 20.0]
ANGLES_DEG = [30.0, 90.0, 150.0]
NOISE_MM = 0.03


def test_penalty_is_zero_for_monotone_either_way_and_the_wrong_way_steps_otherwise():
    torch = pytest.importorskip("torch")
    k = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    up, down = k ** 2, 1.0 - k                 # monotone increasing / decreasing in F
    bump = torch.tensor([0.0, 0.6, 0.4, 0.8, 1.0], dtype=torch.float64)   # one 0.2 step back
    g = torch.stack([up, down, bump], dim=1)[None, None]                 # (B=1, A=1, K=5, L=3)
    per_sample = [float(_monotone_penalty(g[..., i:i + 1], 0.0)) for i in range(3)]
    assert per_sample == pytest.approx([0.0, 0.0, 0.2])
    assert float(_monotone_penalty(g, 0.0)) == pytest.approx(0.2 / 3)


def _excursions(model):
    """Worst excursion (mm) of the mid-force prediction outside its neighbours' interval
    and the fraction of ROI samples inside, over adjacent trained forces at trained angles."""
    worst, inside, total = 0.0, 0, 0
    for ang in ANGLES_DEG:
        for lo, hi in zip(FORCES_N, FORCES_N[1:]):
            p = model.predict_batch_mm([lo, 0.5 * (lo + hi), hi], [ang] * 3)
            truth = hertz_profile_mm(X_MM, hi, ang)
            roi = truth > 0.05 * truth.max()
            exc = np.maximum(np.minimum(p[0], p[2]) - p[1], p[1] - np.maximum(p[0], p[2]))[roi]
            worst = max(worst, float(exc.max()))
            inside += int(np.sum(exc <= 0.0))
            total += int(roi.sum())
    return worst, inside / total


def test_penalty_removes_the_overshoot_without_hurting_the_fit():
    # Five forces, three angles, noisy: 15 profiles that 45 hidden units can interpolate,
    # noise and all, so without the penalty the net wiggles in F between trained forces.
    f, a, meas, truth, _ = dataset(FORCES_N, ANGLES_DEG, seed=0, noise_mm=NOISE_MM)
    base = TrainConfig(ensemble=0, stages=2, epochs_per_stage=1500, seed=0)
    plain = fit_region_model(f, a, meas, X_MM, config=replace(base, monotone_weight=0.0))
    mono = fit_region_model(f, a, meas, X_MM, config=base)
    worst_plain, frac_plain = _excursions(plain)
    worst_mono, frac_mono = _excursions(mono)
    assert worst_plain > 0.5 * NOISE_MM and frac_plain < 0.9, (worst_plain, frac_plain)   # it does overshoot
    # With the penalty: what is left is far below the noise (sub-micron wiggles between
    # the penalty's force-grid nodes), nearly every ROI sample strictly between.
    assert worst_mono < 0.05 * NOISE_MM and frac_mono > 0.98, (worst_mono, frac_mono)
    # ... and the fit to the noise-free truth is no worse than without it.
    rmse = [float(np.sqrt(np.mean((m.predict_batch_mm(f, a) - truth) ** 2))) for m in (plain, mono)]
    assert rmse[1] <= rmse[0], rmse
    assert mono.meta["training"]["extra"]["monotone_penalty"][0] < 1e-5
