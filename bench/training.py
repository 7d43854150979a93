"""Benchmark: train one region model on a 9 angles x 5 forces characterization, then serve it.

Prints ONE JSON object: ``train_s`` (wall time to the stopping rule of the session's
training: a region's full ensemble, ``members`` nets, spline outputs, float32, the
noise-relative stop), ``train_mse`` (normalised), ``epochs``, ``stop_reason`` and
``test_rmse_mm`` (unseen (F, α) against the noise-free truth, every sample) beside the
same for the training as it was before (``baseline_*``: float64, one weight per output
sample, a 400-epoch 0.2 % plateau), trained in the same run on the same data, and
``speedup``; single-query latency of the numpy serving path (``infer_p50_us``,
``infer_p99_us``) beside the plain torch forward of the same net (``torch_infer_p50_us``,
``torch_infer_p99_us``). ``*_cpu_s``: this process's CPU time for the same (the wall
time grows with whatever else runs on the machine; on an idle one the two agree).
Goals: <= 10 s per region (``train_goal_met``: judged on the CPU time, so a busy shared
machine does not decide it, and with test_rmse_mm no worse than the baseline's);
infer_p99_us <= 100.

Data: synthetic rubber-like profiles (Hertz surface displacement under the normal part
F sin α, shifted along t by a Mindlin-like tangential displacement from F cos α, plus
the Cerruti term), Gaussian scan noise of the averaged profile, 2 % missing samples
and a gap where the probe shadows the dent at large forces.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from elastoprobe.controller.core.geometry import NINE_ANGLES_DEG
from elastoprobe.controller.learning.models import TrainConfig, fit_region_model
from elastoprobe.controller.learning.profiles import ProfileGrid

FORCES_N = (2.0, 5.0, 9.0, 14.0, 20.0)
NOISE_MM = 0.01
QUERIES = 20000
MEMBERS = 4                   # the demo plan's ensemble: the full-data net and 3 bootstrap members
TRAIN_GOAL_S = 10.0


def hertz_profile_mm(x_mm: np.ndarray, force_n: float, angle_deg: float, e_mpa: float = 2.0,
                     nu: float = 0.49, tip_radius_mm: float = 5.0, shift_gain: float = 0.25) -> np.ndarray:
    """Noise-free rubber-like dent (mm along -n) on the grid ``x_mm``."""
    e_star = e_mpa / (1.0 - nu ** 2)
    a_rad = np.radians(angle_deg)
    p, q = force_n * np.sin(a_rad), force_n * np.cos(a_rad)
    a = (3.0 * p * tip_radius_mm / (4.0 * e_star)) ** (1.0 / 3.0)
    shift_mm = shift_gain * q / (a * e_star)
    r = np.abs(x_mm - shift_mm)
    w = np.empty_like(r)
    inside = r <= a
    w[inside] = a ** 2 / tip_radius_mm - r[inside] ** 2 / (2.0 * tip_radius_mm)
    ro = r[~inside]
    w[~inside] = a ** 2 / (np.pi * tip_radius_mm) * ((2.0 - ro ** 2 / a ** 2) * np.arcsin(a / ro)
                                                   + np.sqrt(ro ** 2 / a ** 2 - 1.0))
    w += (1 + nu) * (1 - 2 * nu) * q * np.sign(x_mm - shift_mm) / (
        2 * np.pi * e_mpa * np.sqrt((x_mm - shift_mm) ** 2 + a ** 2))
    return w


def characterization(x_mm: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    f, a = np.meshgrid(FORCES_N, NINE_ANGLES_DEG, indexing="ij")
    f, a = f.ravel(), a.ravel()
    truth = np.stack([hertz_profile_mm(x_mm, fi, ai) for fi, ai in zip(f, a)])
    meas = truth + rng.normal(0.0, NOISE_MM, truth.shape)
    meas[rng.random(meas.shape) < 0.02] = np.nan
    for i, fi in enumerate(f):
        if fi >= 14.0:                     # the probe's shadow over the deepest part
            meas[i, np.abs(x_mm) < 1.5] = np.nan
    return f, a, meas


def percentiles_us(samples_s: list[float]) -> tuple[float, float]:
    us = np.asarray(samples_s) * 1e6
    return float(np.percentile(us, 50)), float(np.percentile(us, 99))


def main() -> int:
    import torch
    torch.set_num_threads(2)
    grid = ProfileGrid(80.0, 256)
    rng = np.random.default_rng(0)
    f, a, meas = characterization(grid.x_mm, rng)
    config = TrainConfig(ensemble=MEMBERS - 1, seed=0, basis_spacing_mm=1.0)
    t0, c0 = time.perf_counter(), time.process_time()
    model = fit_region_model(f, a, meas, grid.x_mm, config=config, noise_mm=NOISE_MM)
    train_s, train_cpu_s = time.perf_counter() - t0, time.process_time() - c0

    # Baseline: the training as it was, same data, same run.
    t0, c0 = time.perf_counter(), time.process_time()
    baseline = fit_region_model(f, a, meas, grid.x_mm,
                                config=TrainConfig.baseline(ensemble=MEMBERS - 1, seed=0), noise_mm=NOISE_MM)
    baseline_train_s, baseline_cpu_s = time.perf_counter() - t0, time.process_time() - c0

    fu = rng.uniform(2.0, 20.0, 30)
    au = rng.uniform(10.0, 170.0, 30)
    truth_u = np.stack([hertz_profile_mm(grid.x_mm, fi, ai) for fi, ai in zip(fu, au)])
    test_rmse_mm = float(np.sqrt(np.mean((model.predict_batch_mm(fu, au) - truth_u) ** 2)))
    baseline_rmse_mm = float(np.sqrt(np.mean((baseline.predict_batch_mm(fu, au) - truth_u) ** 2)))

    qf = rng.uniform(2.0, 20.0, QUERIES).tolist()
    qa = rng.uniform(10.0, 170.0, QUERIES).tolist()
    out = np.empty(model.outputs)
    for i in range(200):                  # warm-up
        model.predict_mm(qf[i], qa[i], out=out)
    numpy_s = []
    clock = time.perf_counter
    for fi, ai in zip(qf, qa):
        t = clock()
        model.predict_mm(fi, ai, out=out)
        numpy_s.append(clock() - t)

    net = model.torch_module()
    inputs = [torch.tensor([[fi, ai]], dtype=torch.float64) for fi, ai in zip(qf[:5000], qa[:5000])]
    torch_s = []
    with torch.inference_mode():
        for x in inputs[:200]:
            net(x)
        for x in inputs:
            t = clock()
            net(x)
            torch_s.append(clock() - t)

    p50, p99 = percentiles_us(numpy_s)
    tp50, tp99 = percentiles_us(torch_s)
    report = {
        "train_s": round(train_s, 3),
        "train_cpu_s": round(train_cpu_s, 3),
        "members": MEMBERS,
        "train_mse": model.meta["train_mse_norm"],
        "epochs": model.meta["training"]["epochs"],
        "stop_reason": model.meta["training"]["stop_reason"],
        "profiles": int(f.shape[0]),
        "samples_per_profile": grid.samples,
        "noise_mm": NOISE_MM,
        "test_rmse_mm": round(test_rmse_mm, 5),
        "baseline_train_s": round(baseline_train_s, 3),
        "baseline_train_cpu_s": round(baseline_cpu_s, 3),
        "baseline_epochs": baseline.meta["training"]["epochs"],
        "baseline_train_mse": baseline.meta["train_mse_norm"],
        "baseline_test_rmse_mm": round(baseline_rmse_mm, 5),
        "speedup": round(baseline_train_s / train_s, 2) if train_s > 0 else None,
        "cpu_speedup": round(baseline_cpu_s / train_cpu_s, 2) if train_cpu_s > 0 else None,
        "train_goal_s": TRAIN_GOAL_S,
        "train_goal_met": bool(train_cpu_s <= TRAIN_GOAL_S and test_rmse_mm <= baseline_rmse_mm),
        "peak_depth_mm": round(float(np.nanmax(meas)), 4),
        "infer_p50_us": round(p50, 2),
        "infer_p99_us": round(p99, 2),
        "torch_infer_p50_us": round(tp50, 2),
        "torch_infer_p99_us": round(tp99, 2),
        "infer_goal_p99_us": 100.0,
        "infer_goal_met": bool(p99 <= 100.0),
        "torch_version": torch.__version__,
    }
    json.dump(report, sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
