"""Neural gas (Martinetz, Berkovich, Schulten 1993) over a point cloud: where to probe (docs/design.md §7).

Online NG moves every unit j toward a sample x by
``dw_j = eps(t) * exp(-k_j / lam(t)) * (x - w_j)``, k_j the rank of unit j by distance
to x (0 = nearest), with lam and eps annealed exponentially from their initial to
their final values. ``train_neural_gas`` is the fast form for 1e5-1e6 points:
minibatches, the neighbourhood cut to the K = ceil(lam * ln(1/cutoff)) nearest units
(torch.topk; the dropped terms weigh less than ``cutoff``), and per unit the batch's
per-sample online updates accumulated in closed form. Applied one after another, the
updates of samples i = 1..B shrink (w_j - x) by prod_i (1 - eps h_ij), h_ij =
exp(-k_ij / lam); the accumulation keeps exactly that factor and moves toward the
h-weighted batch mean instead of the order-dependent sequence:

    r_j = 1 - prod_i (1 - eps h_ij),   w_j += r_j * (sum_i h_ij x_i / sum_i h_ij - w_j)

With batch size 1 that is exactly online NG (r = eps h); with many samples per unit
the step keeps online NG's per-sample rate instead of shrinking as the batch grows
(averaging would divide it by the batch size). Ranks within a batch are taken against
the units at the start of the batch — the one approximation of the minibatch form.
``reference_online_ng`` is the plain numpy form kept as the test oracle.

Units: features are whatever the caller gives (plain xyz in mm, or xyz plus normals
scaled to mm by ``geometry_features``); the quantization error is the MEAN SQUARED
distance to the nearest unit in feature units squared (mm^2 for xyz).
torch is imported inside functions so the CLI stays fast to start.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:      # annotations only: torch loads inside the functions that use it
    import torch


@dataclass(frozen=True)
class Schedule:
    """Exponential annealing of the neighbourhood range lam (ranks) and step size eps."""

    lambda_initial: float = 10.0
    lambda_final: float = 0.01
    epsilon_initial: float = 0.5
    epsilon_final: float = 0.005

    def at(self, fraction: float) -> tuple[float, float]:
        """(lam, eps) at ``fraction`` in [0, 1] of training."""
        lam = self.lambda_initial * (self.lambda_final / self.lambda_initial) ** fraction
        eps = self.epsilon_initial * (self.epsilon_final / self.epsilon_initial) ** fraction
        return lam, eps


@dataclass
class NeuralGasResult:
    """Trained units (M,D) in feature units, their quantization error (mean squared
    distance, feature units^2) on all training points, and checkpoints along the way
    (dicts: step, lambda, epsilon, k_neighbours, qe on a fixed subsample)."""

    units: np.ndarray
    quantization_error: float
    history: list[dict] = field(default_factory=list)


def neighbour_count(lam: float, n_units: int, cutoff: float | None = 1e-4) -> int:
    """K = ceil(lam * ln(1/cutoff)) clamped to [1, n_units]; all units without a cutoff."""
    if cutoff is None:
        return n_units
    return int(min(max(math.ceil(lam * math.log(1.0 / cutoff)), 1), n_units))


def sample_indices(n_points: int, n_samples: int, seed: int, weights: np.ndarray | None = None) -> np.ndarray:
    """The order samples are drawn in (n_samples,) int64.

    Uniform: whole shuffled epochs back to back (every point used as evenly as possible).
    Weighted: i.i.d. draws with probability proportional to ``weights``.
    """
    rng = np.random.default_rng([seed, 1])
    if weights is None:
        n_epochs = -(-n_samples // n_points)
        return np.concatenate([rng.permutation(n_points) for _ in range(n_epochs)])[:n_samples]
    p = np.asarray(weights, dtype=float)
    return rng.choice(n_points, size=n_samples, p=p / p.sum())


def initial_units(features: np.ndarray, n_units: int, seed: int) -> np.ndarray:
    """Units started on distinct random data points (M,D), same dtype as the features."""
    rng = np.random.default_rng([seed, 0])
    return np.array(features[rng.choice(features.shape[0], size=n_units, replace=False)], copy=True)


def train_neural_gas(features: np.ndarray, n_units: int, n_steps: int, batch_size: int = 4096, seed: int = 0,
                     schedule: Schedule = Schedule(), sample_weights: np.ndarray | None = None,
                     init_units: np.ndarray | None = None, cutoff: float | None = 1e-4, lloyd_iters: int = 0,
                     n_threads: int | None = None, history_points: int = 20_000, history_every: int = 0
                     ) -> NeuralGasResult:
    """Minibatch neural gas -> NeuralGasResult (units in the features' dtype).

    features (N,D) float32 (float64 for exact comparisons); ``n_steps`` minibatches of
    ``batch_size`` samples drawn by ``sample_indices`` (weighted by ``sample_weights``,
    e.g. ``curvature_weights``); lam and eps follow ``schedule`` over the steps,
    step s at fraction s / (n_steps - 1). ``cutoff=None`` keeps every unit in the
    neighbourhood (exact NG). ``lloyd_iters`` full passes at lam -> 0 and eps = 1
    finish (each unit to the mean of its points; the limit of the schedule).
    ``n_threads`` sets torch's intra-op threads for this call only (restored after; None
    leaves torch's setting). On the 2-core machine, quiet, two threads ran the bench in
    3.0 s against 5.6 s for one; with other processes busy on the cores they were 2-5x
    SLOWER than one (the per-step tensors are small and threads wait on each other), so
    pass 1 where the cores are shared. The k-d tree passes use every core regardless.
    """
    import torch

    threads_before = torch.get_num_threads()
    if n_threads is not None:
        torch.set_num_threads(n_threads)
    try:
        return _train(features, n_units, n_steps, batch_size, seed, schedule, sample_weights, init_units, cutoff,
                      lloyd_iters, history_points, history_every)
    finally:
        torch.set_num_threads(threads_before)


def _train(features: np.ndarray, n_units: int, n_steps: int, batch_size: int, seed: int, schedule: Schedule,
           sample_weights: np.ndarray | None, init_units: np.ndarray | None, cutoff: float | None,
           lloyd_iters: int, history_points: int, history_every: int) -> NeuralGasResult:
    import torch

    x_all = torch.from_numpy(np.ascontiguousarray(features))
    n_points, dim = x_all.shape
    if not 1 <= n_units <= n_points:
        raise ValueError(f"n_units must be in [1, {n_points}], got {n_units}")
    init = initial_units(features, n_units, seed) if init_units is None else np.asarray(init_units, features.dtype)
    w = torch.from_numpy(np.array(init, copy=True))
    order = torch.from_numpy(sample_indices(n_points, n_steps * batch_size, seed, sample_weights))
    probe = _history_subset(features, history_points, seed)
    history: list[dict] = []
    every = history_every or max(1, n_steps // 10)
    with torch.no_grad():
        for step in range(n_steps):
            lam, eps = schedule.at(step / max(1, n_steps - 1))
            k = neighbour_count(lam, n_units, cutoff)
            _ng_step(w, x_all[order[step * batch_size:(step + 1) * batch_size]], lam, eps, k)
            if step % every == 0 or step == n_steps - 1:
                history.append({"step": step, "lambda": lam, "epsilon": eps, "k_neighbours": k,
                                "qe": quantization_error(probe, w.numpy())})
        for it in range(lloyd_iters):
            _lloyd_step(w, x_all)
            history.append({"step": n_steps + it, "lambda": 0.0, "epsilon": 1.0, "k_neighbours": 1,
                            "qe": quantization_error(probe, w.numpy())})
    units = w.numpy().copy()
    return NeuralGasResult(units, quantization_error(features, units), history)


def _ng_step(w: "torch.Tensor", x: "torch.Tensor", lam: float, eps: float, k: int) -> None:
    """One minibatch NG update of ``w`` (M,D) in place by the batch ``x`` (B,D)."""
    import torch

    n_units, dim = w.shape
    d2 = torch.addmm((w * w).sum(dim=1)[None, :], x, w.T, alpha=-2.0)  # |x|^2 omitted: same per row
    if k == 1:
        nbr = d2.argmin(dim=1, keepdim=True)
    else:
        nbr = torch.topk(d2, k, dim=1, largest=False, sorted=True).indices
    h = torch.exp(-torch.arange(k, dtype=w.dtype) / lam)  # by rank 0..k-1
    flat = nbr.reshape(-1)
    mass = torch.zeros(n_units, dtype=w.dtype).index_add_(0, flat, h.repeat(x.shape[0]))
    sum_x = torch.zeros_like(w).index_add_(0, flat, (h[None, :, None] * x[:, None, :]).reshape(-1, dim))
    # Online NG would shrink (w_j - target) by prod_i (1 - eps h_ij) over the batch's samples;
    # keep that exact factor and aim at the h-weighted batch mean. With one sample: eps h (x - w).
    log_keep = torch.zeros(n_units, dtype=w.dtype).index_add_(
        0, flat, torch.log1p(-(eps * h).clamp(max=1.0)).repeat(x.shape[0]))
    rate = -torch.expm1(log_keep)
    hit = mass > 0
    w[hit] += rate[hit, None] * (sum_x[hit] / mass[hit, None] - w[hit])


def _lloyd_step(w: "torch.Tensor", x_all: "torch.Tensor") -> None:
    """lam -> 0, eps = 1 over all points: each unit to the mean of the points it wins."""
    import torch

    labels = torch.from_numpy(assign(x_all.numpy(), w.numpy()))
    count = torch.bincount(labels, minlength=w.shape[0]).to(w.dtype)
    sums = torch.zeros_like(w).index_add_(0, labels, x_all)
    won = count > 0  # a unit that wins nothing stays where it is
    w[won] = sums[won] / count[won, None]


def _history_subset(features: np.ndarray, n: int, seed: int) -> np.ndarray:
    if features.shape[0] <= n:
        return features
    return features[np.random.default_rng([seed, 2]).choice(features.shape[0], n, replace=False)]


def reference_online_ng(features: np.ndarray, init_units: np.ndarray, order: np.ndarray,
                        schedule: Schedule = Schedule()) -> np.ndarray:
    """Plain online NG in float64, the test oracle: one sample at a time, every unit ranked
    by a full sort, no neighbourhood cutoff. Sample s = features[order[s]] at fraction
    s / (len(order) - 1). Returns the units (M,D)."""
    w = np.array(init_units, dtype=np.float64, copy=True)
    x_all = np.asarray(features, dtype=np.float64)
    n = len(order)
    ranks = np.empty(w.shape[0], dtype=np.int64)
    for s, i in enumerate(order):
        frac = s / max(1, n - 1)
        lam = schedule.lambda_initial * (schedule.lambda_final / schedule.lambda_initial) ** frac
        eps = schedule.epsilon_initial * (schedule.epsilon_final / schedule.epsilon_initial) ** frac
        x = x_all[i]
        dist2 = ((w - x) ** 2).sum(axis=1)
        ranks[np.argsort(dist2, kind="stable")] = np.arange(w.shape[0])
        w += eps * np.exp(-ranks / lam)[:, None] * (x - w)
    return w


# --------------------------------------------------------------------------- evaluation

def assign(points: np.ndarray, units: np.ndarray) -> np.ndarray:
    """Index of the nearest unit for every point (N,) int64 (Euclidean, feature units)."""
    _, idx = cKDTree(np.asarray(units, dtype=float)).query(np.asarray(points, dtype=float), workers=-1)
    return idx.astype(np.int64)


def quantization_error(points: np.ndarray, units: np.ndarray) -> float:
    """Mean squared distance from each point to its nearest unit (feature units^2; mm^2 for xyz)."""
    dist, _ = cKDTree(np.asarray(units, dtype=float)).query(np.asarray(points, dtype=float), workers=-1)
    return float(np.mean(dist**2))


# --------------------------------------------------------------------------- geometry awareness

def geometry_features(points_mm: np.ndarray, normals: np.ndarray, normal_weight_mm: float = 20.0) -> np.ndarray:
    """(N,6) float32 features: xyz (mm) and unit normals scaled to ``normal_weight_mm``.

    Where the normal turns, the surface is stretched in feature space, so more units
    gather at curved places and edges; on flat faces the extra columns are constant.
    The first three columns of units trained on these are positions in mm.
    """
    return np.hstack([points_mm, normal_weight_mm * np.asarray(normals)]).astype(np.float32)


def curvature_weights(curvature: np.ndarray, gain: float = 100.0) -> np.ndarray:
    """Sampling weights 1 + gain * curvature (N,): points at edges are drawn more often.

    ``curvature`` is the PCA surface variation (0 on a plane, up to 1/3); with the
    default gain an edge (variation ~0.1) is drawn about ten times as often as a face.
    """
    return 1.0 + gain * np.asarray(curvature, dtype=float)


def geometry_aware_inputs(points_mm: np.ndarray, normals: np.ndarray, curvature: np.ndarray,
                          normal_weight_mm: float = 10.0, curvature_gain: float = 100.0
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Features and sampling weights for geometry-aware NG -> (features (N,6) float32, weights (N,)).

    Plain NG follows point density only. Drawing edge points more often is what pulls
    units toward edges and corners; the scaled normals add units where the surface
    bends smoothly (a pillow's rim) and keep units from straddling the two faces of
    an edge. Units trained on these have positions (mm) in their first three columns.
    """
    return geometry_features(points_mm, normals, normal_weight_mm), curvature_weights(curvature, curvature_gain)
