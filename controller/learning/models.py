"""Per-region neural models of the deformation profile (paper §IV).

One network per region maps (F, α) -> the L-sample depth profile:
inputs F (N) and α (deg) each mapped linearly to [-1, 1] (the ranges are stored),
``hidden_units`` (45) tanh or logistic units, L linear outputs in normalised depth
(depth_mm / depth_scale_mm, so the region's deepest measured depth is 1).

Training (torch, imported lazily): full-batch resilient propagation
(``torch.optim.Rprop``) on a weighted, masked MSE, so missing (NaN) samples cost nothing
and each sample counts by its support (the session trains on complete targets, see
:mod:`.support`). The output layer may be trained through a cubic B-spline basis along x
(``basis_spacing_mm``): every output profile is then smooth at the knot spacing whatever
the data, and fewer output weights make an epoch cheaper; served, it is the plain L x H
layer. Training runs in float32 (the served weights are float64).
Stopping rule: at most ``stages x epochs_per_stage`` epochs (the paper trained in
five steps of 5000; one continuous Rprop run here, since restarting its step sizes
makes the loss jump); a member stops early when its training loss improved by less
than ``plateau_rel_tol`` (relative) over the last ``plateau_patience`` epochs, or its RMS
fit by less than ``plateau_noise_fraction`` of the data's noise, or the loss fell below
``loss_goal`` (or the noise itself: the discrepancy principle).

Disagreement: member 0 is fitted on all the data; members 1..E are fitted on
bootstrap resamples of probe POINTS (every profile of a drawn point comes along,
weighted by how often it was drawn), so their spread reflects point-to-point
variation within the region, not just scan noise. All members train together as
one stacked tensor; Rprop is element-wise, so this is exactly independent training.

Monotone in force: the true depth at a given x is monotone in F at a fixed α (not
always increasing: behind a tangential load the surface can rise with force), so a
profile at an unseen force must lie between those at the neighbouring forces. The
loss adds ``monotone_weight`` x the mean, over (angle, output sample), of the summed
steps against that sample's own end-to-end trend along a force grid
(``monotone_forces`` forces over the trained range +-5 %, at the trained angles and
midway between them). Only training changes; serving is untouched.

Serving is pure numpy with the normalisation folded into the weights and
preallocated buffers (``predict_mm``), fast enough for a 1 kHz haptic loop. A model
may carry :class:`ServingLimits`: every serving path clips to its physical depth
bounds, and :meth:`RegionModel.serve` refuses queries outside the trained ranges unless
asked to extrapolate and says where each sample's training value came from.
"""
from __future__ import annotations

import hashlib
import io
import json
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.atomic import atomic_write_bytes, atomic_write_json
from .profiles import depth_scale_mm

FORMAT = "elastoprobe.region_model/1"
ANGLE_RANGE_DEG: tuple[float, float] = (0.0, 180.0)


@dataclass(frozen=True)
class TrainConfig:
    """How a region model is trained (see the module docstring for the stopping rule)."""

    hidden_units: int = 45
    activation: str = "tanh"            # "tanh" or "sigmoid" (logistic)
    stages: int = 5
    epochs_per_stage: int = 2000
    check_every: int = 50               # epochs between stopping-rule checks
    plateau_patience: int = 200         # epochs over which improvement is measured
    plateau_rel_tol: float = 2e-3       # relative improvement below which training stops
    # With the data's noise known: training also stops when the RMS fit (mm) improved by
    # less than this fraction of the noise over ``plateau_patience`` epochs (0 = off).
    plateau_noise_fraction: float = 0.1
    loss_goal: float = 1e-7             # normalised MSE at which training stops
    rprop_lr: float = 0.01              # Rprop's initial step size
    rprop_etas: tuple[float, float] = (0.5, 1.2)
    rprop_step_sizes: tuple[float, float] = (1e-7, 1.0)
    ensemble: int = 5                   # bootstrap members besides the full-data member
    seed: int = 0
    # Monotone-in-force penalty (see ``_fit``): weight (0 = off), force-grid size, and the
    # margin (normalised depth per grid step) a step against the trend may not exceed.
    monotone_weight: float = 0.1
    monotone_forces: int = 25
    monotone_margin: float = 1e-5
    # The training precision (see ``_fit``).
    dtype: str = "float32"
    # Smooth outputs: the output layer is trained as a cubic B-spline along x with knots this
    # far apart (mm; None = one free weight per output sample). See ``_spline_basis``.
    basis_spacing_mm: float | None = None

    def __post_init__(self) -> None:
        if self.activation not in ("tanh", "sigmoid"):
            raise ValueError(f"activation must be tanh or sigmoid, not {self.activation!r}")
        if self.hidden_units < 1 or self.stages < 1 or self.epochs_per_stage < 1 or self.ensemble < 0:
            raise ValueError("hidden_units, stages, epochs_per_stage must be >= 1 and ensemble >= 0")
        if self.monotone_weight < 0.0 or self.monotone_forces < 2 or self.monotone_margin < 0.0:
            raise ValueError("monotone_weight and monotone_margin must be >= 0 and monotone_forces >= 2")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be float32 or float64, not {self.dtype!r}")
        if self.plateau_noise_fraction < 0.0:
            raise ValueError("plateau_noise_fraction must be >= 0")
        if self.basis_spacing_mm is not None and not self.basis_spacing_mm > 0.0:
            raise ValueError("basis_spacing_mm must be > 0 (or None)")

    @classmethod
    def baseline(cls, **changes: Any) -> "TrainConfig":
        """The training as it was before it was made faster (float64, a 400-epoch plateau
        window at 0.2 %, no noise-relative stop; with no spline basis, the default): the
        bench's baseline."""
        settings: dict[str, Any] = {"dtype": "float64", "plateau_patience": 400, "plateau_noise_fraction": 0.0}
        settings.update(changes)
        return cls(**settings)


@dataclass
class TrainReport:
    """What training did, per member (member 0 = full data)."""

    mse_norm: list[float]               # final masked MSE in normalised units
    epochs: list[int]
    stop_reason: list[str]              # "plateau", "goal", "max_epochs"
    train_s: float
    n_profiles: int
    n_points: int
    valid_fraction: float
    extra: dict[str, Any] = field(default_factory=dict)


def _normalize_inputs(force_n: np.ndarray, angle_deg: np.ndarray, force_range_n: tuple[float, float],
                      angle_range_deg: tuple[float, float]) -> np.ndarray:
    """(M,) forces and angles -> (M,2) in [-1, 1] (a degenerate range maps to 0)."""
    def scale(v: np.ndarray, lo: float, hi: float) -> np.ndarray:
        if hi - lo <= 0.0:
            return np.zeros_like(v)
        return 2.0 * (v - lo) / (hi - lo) - 1.0
    f = np.asarray(force_n, dtype=float).reshape(-1)
    a = np.asarray(angle_deg, dtype=float).reshape(-1)
    return np.column_stack([scale(f, *force_range_n), scale(a, *angle_range_deg)])


def _affine(lo: float, hi: float) -> tuple[float, float]:
    """(gain, offset) with normalised = gain * v + offset."""
    if hi - lo <= 0.0:
        return 0.0, 0.0
    g = 2.0 / (hi - lo)
    return g, -1.0 - g * lo


def data_hash(force_n: np.ndarray, angle_deg: np.ndarray, depth_mm: np.ndarray,
              point_ids: np.ndarray | None = None) -> str:
    """sha256 of the training data (NaN canonicalised), for provenance."""
    h = hashlib.sha256()
    for arr in (force_n, angle_deg, depth_mm):
        a = np.ascontiguousarray(np.asarray(arr, dtype=np.float64))
        a = np.where(np.isfinite(a), a, np.nan)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    if point_ids is not None:
        h.update(np.ascontiguousarray(np.asarray(point_ids, dtype=np.int64)).tobytes())
    return h.hexdigest()


class OutOfRange(ValueError):
    """A query outside the forces and angles the model was trained on (see :meth:`RegionModel.serve`)."""


@dataclass(frozen=True)
class ServingLimits:
    """What a model may be asked and what it may answer.

    ``force_range_n``, ``angle_range_deg``: the trained ranges (queries outside are refused
    unless the caller opts in); ``depth_min_mm``, ``depth_max_mm``: every served depth is
    clipped to these physical bounds (no deeper than the tip went in the region's data
    plus its measured spread, no higher above the undeformed surface than the data rose
    plus that spread); ``support_forces_n`` (F,), ``support_angles_deg`` (A,),
    ``support_codes`` (A,F,L) int8: where each output sample's training value came from
    (:mod:`.support` codes) at each trained force level and angle.
    """

    force_range_n: tuple[float, float]
    angle_range_deg: tuple[float, float]
    depth_min_mm: float
    depth_max_mm: float
    support_forces_n: np.ndarray
    support_angles_deg: np.ndarray
    support_codes: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        return {"limits": np.array([*self.force_range_n, *self.angle_range_deg, self.depth_min_mm, self.depth_max_mm]),
                "support_forces_n": np.asarray(self.support_forces_n, dtype=np.float64),
                "support_angles_deg": np.asarray(self.support_angles_deg, dtype=np.float64),
                "support_codes": np.asarray(self.support_codes, dtype=np.int8)}

    @staticmethod
    def from_arrays(arrays: dict[str, np.ndarray]) -> "ServingLimits | None":
        if "limits" not in arrays:
            return None
        lim = np.asarray(arrays["limits"], dtype=float)
        return ServingLimits((float(lim[0]), float(lim[1])), (float(lim[2]), float(lim[3])), float(lim[4]),
                             float(lim[5]), np.asarray(arrays["support_forces_n"], dtype=float),
                             np.asarray(arrays["support_angles_deg"], dtype=float),
                             np.asarray(arrays["support_codes"], dtype=np.int8))

    def inside(self, force_n: float, angle_deg: float) -> bool:
        """Is (F, alpha) within the trained ranges?"""
        (f0, f1), (a0, a1) = self.force_range_n, self.angle_range_deg
        return f0 <= force_n <= f1 and a0 <= angle_deg <= a1

    def support_at(self, force_n: float, angle_deg: float) -> np.ndarray:
        """(L,) support code of each sample for a query: the weakest (largest code) over the
        trained force levels and angles that bracket it."""
        def bracket(grid: np.ndarray, v: float) -> list[int]:
            k = int(np.searchsorted(grid, v))
            if k < grid.size and abs(grid[k] - v) <= 1e-6 * max(1.0, abs(v)):
                return [k]
            return sorted({min(max(k - 1, 0), grid.size - 1), min(k, grid.size - 1)})
        ai = bracket(self.support_angles_deg, angle_deg)
        fi = bracket(self.support_forces_n, force_n)
        return self.support_codes[np.ix_(ai, fi)].reshape(-1, self.support_codes.shape[-1]).max(axis=0)


@dataclass
class ServedProfile:
    """What ``predict`` serves for one query: the full-data member's profile clipped to the
    physical bounds, the bootstrap members' spread, and each sample's support."""

    x_mm: np.ndarray
    depth_mm: np.ndarray
    spread_mm: np.ndarray
    support: np.ndarray           # (L,) int8 support codes (support.SUPPORT_NAMES); -1 unknown
    extrapolated: bool            # outside the trained ranges (served only on request)
    clipped: np.ndarray           # (L,) bool: the net's value lay outside the bounds


class RegionModel:
    """A trained region network (plus its bootstrap members), served in numpy.

    Weights (raw, as trained): ``w1`` (B,H,2), ``b1`` (B,H), ``w2`` (B,L,H), ``b2`` (B,L)
    act on normalised inputs and give normalised depth; member 0 is the full-data fit.
    ``predict_mm`` is not thread-safe (it reuses buffers): one model per serving thread.
    """

    def __init__(self, w1: np.ndarray, b1: np.ndarray, w2: np.ndarray, b2: np.ndarray, *,
                 x_mm: np.ndarray, force_range_n: tuple[float, float],
                 angle_range_deg: tuple[float, float] = ANGLE_RANGE_DEG, depth_scale_mm: float,
                 activation: str = "tanh", meta: dict[str, Any] | None = None,
                 limits: ServingLimits | None = None) -> None:
        self.w1 = np.ascontiguousarray(w1, dtype=np.float64)
        self.b1 = np.ascontiguousarray(b1, dtype=np.float64)
        self.w2 = np.ascontiguousarray(w2, dtype=np.float64)
        self.b2 = np.ascontiguousarray(b2, dtype=np.float64)
        if self.w1.ndim == 2:
            self.w1, self.b1, self.w2, self.b2 = self.w1[None], self.b1[None], self.w2[None], self.b2[None]
        self.x_mm = np.asarray(x_mm, dtype=np.float64).copy()
        self.force_range_n = (float(force_range_n[0]), float(force_range_n[1]))
        self.angle_range_deg = (float(angle_range_deg[0]), float(angle_range_deg[1]))
        self.depth_scale_mm = float(depth_scale_mm)
        self.activation = activation
        self.meta: dict[str, Any] = dict(meta or {})
        if self.w2.shape[1] != self.x_mm.shape[0]:
            raise ValueError(f"model has {self.w2.shape[1]} outputs but the grid has {self.x_mm.shape[0]}")
        self.limits = limits
        if limits is not None and limits.support_codes.shape[-1] != self.x_mm.shape[0]:
            raise ValueError("support codes and the grid differ in length")
        self._fold()

    def with_limits(self, limits: ServingLimits) -> "RegionModel":
        """The same net served within ``limits``."""
        return RegionModel(self.w1, self.b1, self.w2, self.b2, x_mm=self.x_mm, force_range_n=self.force_range_n,
                           angle_range_deg=self.angle_range_deg, depth_scale_mm=self.depth_scale_mm,
                           activation=self.activation, meta=self.meta, limits=limits)

    # -- serving ------------------------------------------------------------------------
    @property
    def n_members(self) -> int:
        return int(self.w1.shape[0])

    @property
    def hidden_units(self) -> int:
        return int(self.w1.shape[1])

    @property
    def outputs(self) -> int:
        return int(self.w2.shape[1])

    def _fold(self) -> None:
        """Fold input normalisation, a logistic hidden layer and the depth scale into the
        weights, so serving is h = tanh(wf F + wa α + b); depth_mm = W h + c."""
        gf, of = _affine(*self.force_range_n)
        ga, oa = _affine(*self.angle_range_deg)
        w1f = self.w1[:, :, 0] * gf
        w1a = self.w1[:, :, 1] * ga
        b1 = self.b1 + self.w1[:, :, 0] * of + self.w1[:, :, 1] * oa
        w2 = self.w2 * self.depth_scale_mm
        b2 = self.b2 * self.depth_scale_mm
        if self.activation == "sigmoid":
            # logistic(z) = (1 + tanh(z / 2)) / 2
            w1f, w1a, b1 = w1f / 2.0, w1a / 2.0, b1 / 2.0
            b2 = b2 + 0.5 * w2.sum(axis=2)
            w2 = 0.5 * w2
        self._w1f, self._w1a, self._b1f = w1f, w1a, b1
        self._w2f, self._b2f = np.ascontiguousarray(w2), b2
        # Member 0's serving arrays and buffers, contiguous for np.dot(out=).
        self._s_w1f = np.ascontiguousarray(w1f[0])
        self._s_w1a = np.ascontiguousarray(w1a[0])
        self._s_b1 = np.ascontiguousarray(b1[0])
        self._s_w2 = np.ascontiguousarray(w2[0])
        self._s_b2 = np.ascontiguousarray(b2[0])
        self._h = np.empty(self.hidden_units)
        self._tmp = np.empty(self.hidden_units)
        self._o = np.empty(self.outputs)
        lim = self.limits
        self._lo, self._hi = (-np.inf, np.inf) if lim is None else (lim.depth_min_mm, lim.depth_max_mm)

    def predict_mm(self, force_n: float, angle_deg: float, out: np.ndarray | None = None) -> np.ndarray:
        """Depth profile (L,) in mm for one query (full-data member); numpy only.

        Pass ``out`` (L,) float64 to avoid the one allocation (the copy of the result).
        """
        h, tmp, o = self._h, self._tmp, self._o
        np.multiply(self._s_w1f, force_n, out=h)
        np.multiply(self._s_w1a, angle_deg, out=tmp)
        h += tmp
        h += self._s_b1
        np.tanh(h, out=h)
        np.dot(self._s_w2, h, out=o)
        o += self._s_b2
        np.clip(o, self._lo, self._hi, out=o)
        if out is None:
            return o.copy()
        out[...] = o
        return out

    def predict_batch_mm(self, force_n: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        """Depth profiles (Q,L) in mm for Q queries (full-data member), within the bounds."""
        return np.clip(self.raw_batch_mm(force_n, angle_deg), self._lo, self._hi)

    def raw_batch_mm(self, force_n: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        """The full-data net's output (Q,L) in mm before the physical bounds are applied."""
        f = np.asarray(force_n, dtype=float).reshape(-1, 1)
        a = np.asarray(angle_deg, dtype=float).reshape(-1, 1)
        h = np.tanh(f * self._s_w1f + a * self._s_w1a + self._s_b1)
        return h @ self._s_w2.T + self._s_b2

    def predict_members_mm(self, force_n: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        """Depth profiles (B,Q,L) in mm from every member (member 0 = full data)."""
        f = np.asarray(force_n, dtype=float).reshape(1, -1, 1)
        a = np.asarray(angle_deg, dtype=float).reshape(1, -1, 1)
        h = np.tanh(f * self._w1f[:, None, :] + a * self._w1a[:, None, :] + self._b1f[:, None, :])
        return np.clip(np.einsum("bqh,blh->bql", h, self._w2f) + self._b2f[:, None, :], self._lo, self._hi)

    def serve(self, force_n: float, angle_deg: float, extrapolate: bool = False) -> ServedProfile:
        """The profile ``predict`` serves for one query (see :class:`ServedProfile`).

        Raises :class:`OutOfRange` for a query outside the trained ranges unless
        ``extrapolate``; such a profile is still clipped to the bounds and is flagged.
        """
        return self.serve_batch(np.array([force_n]), np.array([angle_deg]), extrapolate)[0]

    def serve_batch(self, force_n: np.ndarray, angle_deg: np.ndarray, extrapolate: bool = False
                    ) -> list[ServedProfile]:
        """:meth:`serve` for Q queries at once."""
        f = np.asarray(force_n, dtype=float).reshape(-1)
        a = np.asarray(angle_deg, dtype=float).reshape(-1)
        lim = self.limits
        inside = np.array([lim is None or lim.inside(fi, ai) for fi, ai in zip(f, a)], dtype=bool)
        if not extrapolate and not inside.all():
            k = int(np.flatnonzero(~inside)[0])
            assert lim is not None
            raise OutOfRange(f"F = {f[k]:g} N, angle = {a[k]:g} deg lies outside what the model was trained on "
                             f"({lim.force_range_n[0]:g}-{lim.force_range_n[1]:g} N, "
                             f"{lim.angle_range_deg[0]:g}-{lim.angle_range_deg[1]:g} deg)")
        raw = self.raw_batch_mm(f, a)
        members = self.predict_members_mm(f, a)
        boot = members[1:] if self.n_members > 1 else members[:1]
        spread = boot.std(axis=0, ddof=1) if boot.shape[0] > 1 else np.zeros_like(raw)
        depth = np.clip(raw, self._lo, self._hi)
        out = []
        for q in range(f.size):
            support = (lim.support_at(f[q], a[q]) if lim is not None
                       else np.full(self.outputs, -1, dtype=np.int8))
            out.append(ServedProfile(self.x_mm, depth[q], spread[q], support, not bool(inside[q]),
                                     depth[q] != raw[q]))
        return out

    def predict_ensemble(self, force_n: float | np.ndarray, angle_deg: float | np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """(mean, std) in mm over the bootstrap members: (L,) for a scalar query, else (Q,L).

        With no bootstrap members the mean is the full-data prediction and std is 0.
        """
        scalar = np.ndim(force_n) == 0 and np.ndim(angle_deg) == 0
        f, a = np.broadcast_arrays(np.asarray(force_n, dtype=float), np.asarray(angle_deg, dtype=float))
        p = self.predict_members_mm(f.reshape(-1), a.reshape(-1))
        boot = p[1:] if self.n_members > 1 else p[:1]
        mean = boot.mean(axis=0)
        std = boot.std(axis=0, ddof=1) if boot.shape[0] > 1 else np.zeros_like(mean)
        return (mean[0], std[0]) if scalar else (mean, std)

    # -- torch forward (training-time form; the serving reference) ------------------------
    def torch_forward_mm(self, force_n: np.ndarray, angle_deg: np.ndarray, member: int = 0) -> np.ndarray:
        """The same net evaluated by torch with the training-time normalisation (Q,L) mm."""
        import torch
        x = torch.from_numpy(_normalize_inputs(np.atleast_1d(force_n), np.atleast_1d(angle_deg),
                                               self.force_range_n, self.angle_range_deg))
        with torch.no_grad():
            y = _torch_forward(x, torch.from_numpy(self.w1[member:member + 1]),
                               torch.from_numpy(self.b1[member:member + 1]),
                               torch.from_numpy(self.w2[member:member + 1]),
                               torch.from_numpy(self.b2[member:member + 1]), self.activation)
        return y[0].numpy() * self.depth_scale_mm

    def torch_module(self) -> Any:
        """A plain ``torch.nn.Sequential`` of the full-data member taking raw (F, α) -> mm."""
        import torch
        lin1 = torch.nn.Linear(2, self.hidden_units, dtype=torch.float64)
        lin2 = torch.nn.Linear(self.hidden_units, self.outputs, dtype=torch.float64)
        gf, of = _affine(*self.force_range_n)
        ga, oa = _affine(*self.angle_range_deg)
        with torch.no_grad():
            lin1.weight.copy_(torch.from_numpy(self.w1[0] * np.array([gf, ga])))
            lin1.bias.copy_(torch.from_numpy(self.b1[0] + self.w1[0] @ np.array([of, oa])))
            lin2.weight.copy_(torch.from_numpy(self.w2[0] * self.depth_scale_mm))
            lin2.bias.copy_(torch.from_numpy(self.b2[0] * self.depth_scale_mm))
        act = torch.nn.Tanh() if self.activation == "tanh" else torch.nn.Sigmoid()
        return torch.nn.Sequential(lin1, act, lin2).eval()

    # -- persistence -----------------------------------------------------------------------
    def _defining(self) -> dict[str, Any]:
        out = {"format": FORMAT, "activation": self.activation, "hidden_units": self.hidden_units,
               "outputs": self.outputs, "members": self.n_members,
               "force_range_n": list(self.force_range_n), "angle_range_deg": list(self.angle_range_deg),
               "depth_scale_mm": self.depth_scale_mm}
        if self.limits is not None:
            lim = self.limits
            out["serving"] = {"force_range_n": list(lim.force_range_n), "angle_range_deg": list(lim.angle_range_deg),
                              "depth_min_mm": lim.depth_min_mm, "depth_max_mm": lim.depth_max_mm}
        return out

    def _arrays(self) -> dict[str, np.ndarray]:
        out = {"w1": self.w1, "b1": self.b1, "w2": self.w2, "b2": self.b2, "x_mm": self.x_mm}
        if self.limits is not None:
            out.update(self.limits.arrays())
        return out

    def _weights_bytes(self) -> bytes:
        """The stored arrays' bytes (serving limits included when present; a model without
        them hashes exactly as before they existed)."""
        arrays = self._arrays()
        parts = [np.ascontiguousarray(arrays[k], dtype="<f8").tobytes() for k in ("w1", "b1", "w2", "b2", "x_mm")]
        if self.limits is not None:
            parts += [np.ascontiguousarray(arrays[k], dtype="<f8").tobytes()
                      for k in ("limits", "support_forces_n", "support_angles_deg", "support_codes")]
        return b"".join(parts)

    def model_hash(self) -> str:
        """sha256 of what defines the predictions: weights, grid, ranges, scale, activation."""
        h = hashlib.sha256(json.dumps(self._defining(), sort_keys=True).encode())
        h.update(self._weights_bytes())
        return h.hexdigest()

    def save(self, path: str | Path) -> Path:
        """Write ``<path>.npz`` (weights) and ``<path>.json`` (metadata), each atomically.

        The JSON names the weights' hash, so a crash between the two renames is
        detected by :meth:`load` rather than silently pairing old and new files.
        """
        base = Path(path)
        if base.suffix in (".npz", ".json"):
            base = base.with_suffix("")
        buf = io.BytesIO()
        np.savez(buf, **self._arrays())
        atomic_write_bytes(base.with_suffix(".npz"), buf.getvalue())
        meta = dict(self.meta)
        meta.update(self._defining())
        meta.update({
            "units": {"force": "N", "angle": "deg", "depth": "mm", "x": "mm",
                      "outputs": "depth along -n (mm) = normalised output * depth_scale_mm"},
            "grid": {"x0_mm": float(self.x_mm[0]), "x1_mm": float(self.x_mm[-1]), "samples": self.outputs},
            "weights_sha256": hashlib.sha256(self._weights_bytes()).hexdigest(),
            "model_hash": self.model_hash(),
        })
        atomic_write_json(base.with_suffix(".json"), meta)
        return base.with_suffix(".npz")

    @staticmethod
    def load(path: str | Path) -> "RegionModel":
        """Read a model written by :meth:`save`; refuses a weights/metadata mismatch."""
        base = Path(path)
        if base.suffix in (".npz", ".json"):
            base = base.with_suffix("")
        meta = json.loads(base.with_suffix(".json").read_text(encoding="utf-8"))
        if meta.get("format") != FORMAT:
            raise ValueError(f"{base}.json: not a {FORMAT} file")
        with np.load(base.with_suffix(".npz"), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        model = RegionModel(arrays["w1"], arrays["b1"], arrays["w2"], arrays["b2"], x_mm=arrays["x_mm"],
                            force_range_n=tuple(meta["force_range_n"]),
                            angle_range_deg=tuple(meta["angle_range_deg"]),
                            depth_scale_mm=meta["depth_scale_mm"], activation=meta["activation"], meta=meta,
                            limits=ServingLimits.from_arrays(arrays))
        if hashlib.sha256(model._weights_bytes()).hexdigest() != meta.get("weights_sha256"):
            raise ValueError(f"{base}.npz does not match the weights hash in {base}.json")
        if model.model_hash() != meta.get("model_hash"):
            raise ValueError(f"{base}: model hash mismatch")
        return model


# -- training -------------------------------------------------------------------------------

def _torch_forward(x: Any, w1: Any, b1: Any, w2: Any, b2: Any, activation: str) -> Any:
    """x (M,2) -> (B,M,L) normalised depth for stacked members."""
    import torch
    z = torch.baddbmm(b1[:, None, :], x.expand(w1.shape[0], -1, -1), w1.transpose(1, 2))
    h = torch.tanh(z) if activation == "tanh" else torch.sigmoid(z)
    return torch.baddbmm(b2[:, None, :], h, w2.transpose(1, 2))


def _init_weights(rng: np.random.Generator, members: int, hidden: int, outputs: int,
                  y_mean: np.ndarray) -> tuple[np.ndarray, ...]:
    """Nguyen-Widrow-like init (as Matlab's default for the paper's nets): hidden units'
    active regions spread over the [-1, 1]^2 input square; outputs start at the mean profile."""
    gain = 0.7 * hidden ** 0.5
    direction = rng.normal(size=(members, hidden, 2))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    w1 = direction * gain
    b1 = gain * rng.uniform(-1.0, 1.0, size=(members, hidden))
    w2 = rng.uniform(-1.0, 1.0, size=(members, outputs, hidden)) / hidden ** 0.5 * 0.1
    b2 = np.broadcast_to(y_mean, (members, outputs)).copy()
    return w1, b1, w2, b2


def _spline_basis(x_mm: np.ndarray, spacing_mm: float | None) -> np.ndarray | None:
    """(L,K) cubic B-spline design matrix on the grid, uniform knots ``spacing_mm`` apart
    (None when no basis is asked for or the knots would be no coarser than the grid).

    Trained through this basis, every output profile is a cubic spline: smooth at the
    knot spacing whatever the data, so noise or an uneven fill in a few training samples
    cannot show as spikes between them. Served, the layer is the plain L x H matrix."""
    if spacing_mm is None or x_mm.size < 8:
        return None
    span = float(x_mm[-1] - x_mm[0])
    intervals = int(np.ceil(span / spacing_mm))
    if intervals + 3 >= x_mm.size:
        return None
    from scipy.interpolate import BSpline   # training only: serving stays numpy

    inner = np.linspace(x_mm[0], x_mm[-1], intervals + 1)
    knots = np.concatenate([[x_mm[0]] * 3, inner, [x_mm[-1]] * 3])
    return BSpline.design_matrix(x_mm, knots, 3).toarray()


def _monotone_grid(angle_deg: np.ndarray, f_range: tuple[float, float], config: TrainConfig) -> tuple[np.ndarray, tuple[int, int]] | None:
    """Normalised inputs (A*K, 2) where the penalty looks, and (A, K): at every trained angle
    and every midpoint between adjacent trained angles, ``config.monotone_forces`` forces
    evenly over the force range widened by 5 % each side. None if the range is one force."""
    if f_range[1] - f_range[0] <= 0.0:
        return None
    trained = np.unique(np.asarray(angle_deg, dtype=float))
    angles = np.unique(np.concatenate([trained, 0.5 * (trained[1:] + trained[:-1])]))
    forces = np.linspace(-1.1, 1.1, config.monotone_forces)
    ang_n = _normalize_inputs(np.zeros_like(angles), angles, (0.0, 1.0), ANGLE_RANGE_DEG)[:, 1]
    x = np.column_stack([np.tile(forces, angles.shape[0]), np.repeat(ang_n, forces.shape[0])])
    return x, (int(angles.shape[0]), int(forces.shape[0]))


def _monotone_penalty(g: Any, margin: float) -> Any:
    """(B,A,K,L) predictions along the force grid -> (B,) penalty on non-monotone behaviour in F.

    The true depth at a given x is monotone in force (deeper with force under the tip,
    possibly shallower behind a tangential load), but not necessarily increasing. So the
    trend of each (angle, sample) is the sign of its prediction's end-to-end change along
    the grid, and every step against that trend (by more than -``margin``) costs its size:
    the penalty is the mean over (angle, sample) of the summed wrong-way steps, i.e. half
    the excess of the total variation over the net change. An L1 (exact) penalty: a large
    enough weight makes the minimiser monotone, not just nearly so.
    """
    import torch
    d = g[:, :, 1:, :] - g[:, :, :-1, :]
    trend = torch.sign(g[:, :, -1, :] - g[:, :, 0, :]).detach()
    wrong = torch.relu(margin - trend[:, :, None, :] * d)
    return wrong.sum(dim=2).mean(dim=(1, 2))


def bootstrap_point_weights(point_ids: np.ndarray, members: int, rng: np.random.Generator) -> np.ndarray:
    """(members+1, M) row weights: row 0 all ones; rows 1.. draw the distinct probe points
    with replacement, and every profile of a point gets the point's draw count."""
    ids = np.asarray(point_ids)
    uniq, inverse = np.unique(ids, return_inverse=True)
    weights = np.ones((members + 1, ids.shape[0]))
    for b in range(1, members + 1):
        counts = np.bincount(rng.integers(0, uniq.shape[0], uniq.shape[0]), minlength=uniq.shape[0])
        if counts.max() == 0:
            counts[:] = 1
        weights[b] = counts[inverse]
    return weights


def fit_region_model(force_n: np.ndarray, angle_deg: np.ndarray, depth_mm: np.ndarray, x_mm: np.ndarray,
                     point_ids: np.ndarray | None = None, mask: np.ndarray | None = None,
                     config: TrainConfig = TrainConfig(), force_range_n: tuple[float, float] | None = None,
                     depth_scale: float | None = None,
                     noise_mm: float | np.ndarray | None = None,
                     sample_weight: np.ndarray | None = None) -> RegionModel:
    """Fit one region's network (and bootstrap members) to averaged profiles.

    ``force_n``, ``angle_deg`` (M,): the measured |F| (N) and commanded α (deg) of each
    profile; ``depth_mm`` (M,L): averaged profiles on the grid ``x_mm`` (NaN missing);
    ``point_ids`` (M,): which probe point each profile came from (bootstrap unit; default:
    every profile its own point); ``mask`` (M,L): optional extra validity (False = ignore).
    ``force_range_n`` defaults to the data's [min, max]; ``depth_scale`` to its deepest depth.
    ``noise_mm``: the standard error of the averaged profiles (scalar or (M,L), e.g.
    ``std / sqrt(count)`` from :func:`profiles.average_profiles`). When given, training
    stops once the fit is as close to the data as the noise allows (the discrepancy
    principle: masked MSE <= mean noise variance): with 45 hidden units and a few dozen
    profiles the net can fit the noise itself, which only hurts unseen (F, α).
    Deterministic for a given config.seed (numpy draws the init and the resamples).
    """
    import torch

    # One thread: the net is tiny, extra threads only contend (and the reduction order,
    # hence the result, then does not depend on the machine's thread count).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit(force_n, angle_deg, depth_mm, x_mm, point_ids, mask, config, force_range_n,
                    depth_scale, noise_mm, sample_weight)
    finally:
        torch.set_num_threads(threads)


def _fit(force_n: np.ndarray, angle_deg: np.ndarray, depth_mm: np.ndarray, x_mm: np.ndarray,
         point_ids: np.ndarray | None, mask: np.ndarray | None, config: TrainConfig,
         force_range_n: tuple[float, float] | None, depth_scale: float | None,
         noise_mm: float | np.ndarray | None, sample_weight: np.ndarray | None = None) -> RegionModel:
    import torch

    t0 = time.perf_counter()
    f = np.asarray(force_n, dtype=float).reshape(-1)
    a = np.asarray(angle_deg, dtype=float).reshape(-1)
    y_mm = np.asarray(depth_mm, dtype=float)
    if y_mm.ndim != 2 or y_mm.shape[0] != f.shape[0] or a.shape != f.shape:
        raise ValueError(f"need (M,) forces and angles and (M,L) depths; got {f.shape}, {a.shape}, {y_mm.shape}")
    if y_mm.shape[1] != np.asarray(x_mm).shape[0]:
        raise ValueError("depth profiles and grid differ in length")
    ids = np.arange(f.shape[0]) if point_ids is None else np.asarray(point_ids).reshape(-1)
    valid = np.isfinite(y_mm)
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    if not valid.any():
        raise ValueError("no valid depth samples to train on")
    f_range = force_range_n or (float(f.min()), float(f.max()))
    scale = float(depth_scale) if depth_scale is not None else depth_scale_mm(np.where(valid, y_mm, np.nan))
    y = np.where(valid, y_mm / scale, 0.0)

    goal = config.loss_goal
    # The noise-relative plateau: an RMS improvement of noise_fraction x noise (mm), as a
    # change of the normalised MSE's square root.
    min_rms_gain = 0.0
    if noise_mm is not None:
        noise = np.broadcast_to(np.asarray(noise_mm, dtype=float), y.shape)
        noise_ok = valid & np.isfinite(noise)
        if noise_ok.any():
            noise_ms = float(np.mean((noise[noise_ok] / scale) ** 2))
            goal = max(goal, noise_ms)
            min_rms_gain = config.plateau_noise_fraction * np.sqrt(noise_ms)

    rng = np.random.default_rng(config.seed)
    members = config.ensemble
    row_w = bootstrap_point_weights(ids, members, rng)
    with np.errstate(invalid="ignore"):
        y_mean = np.where(valid.any(axis=0), y.sum(axis=0) / np.maximum(valid.sum(axis=0), 1), 0.0)
    basis = _spline_basis(np.asarray(x_mm, dtype=float), config.basis_spacing_mm)
    coef_mean = y_mean if basis is None else np.linalg.lstsq(basis, y_mean, rcond=None)[0]
    init = _init_weights(rng, members + 1, config.hidden_units, coef_mean.shape[0], coef_mean)
    x_n = _normalize_inputs(f, a, f_range, ANGLE_RANGE_DEG)
    sample_w = valid.astype(np.float64)
    if sample_weight is not None:
        sample_w = sample_w * np.broadcast_to(np.asarray(sample_weight, dtype=float), valid.shape)

    dtype = torch.float32 if config.dtype == "float32" else torch.float64
    x_t = torch.from_numpy(x_n).to(dtype)
    y_t = torch.from_numpy(y).to(dtype)
    w_t = (torch.from_numpy(row_w)[:, :, None] * torch.from_numpy(sample_w)[None]).to(dtype)
    denom = w_t.sum(dim=(1, 2)).clamp_min(1e-12)
    # One flat parameter vector (views per layer): Rprop's per-tensor overhead dominates
    # an epoch of this tiny net, so one tensor instead of four is markedly faster.
    shapes = [p.shape for p in init]
    sizes = [int(np.prod(sh)) for sh in shapes]
    flat = torch.from_numpy(np.concatenate([p.ravel() for p in init])).to(dtype).requires_grad_(True)

    def unflatten(v: Any) -> list[Any]:
        return [piece.view(sh) for piece, sh in zip(torch.split(v, sizes), shapes)]
    active = torch.ones(members + 1, dtype=dtype)
    epochs = [0] * (members + 1)
    reason = ["max_epochs"] * (members + 1)
    history: list[np.ndarray] = []
    lag = max(1, config.plateau_patience // config.check_every)

    grid = _monotone_grid(a, f_range, config) if config.monotone_weight > 0.0 else None
    grid_t = torch.from_numpy(grid[0]).to(dtype) if grid is not None else None
    basis_t = torch.from_numpy(basis.T.copy()).to(dtype) if basis is not None else None

    def member_losses() -> tuple[Any, Any]:
        """(data MSE, monotone penalty) per member."""
        params = unflatten(flat)
        pred = _torch_forward(x_t, *params, config.activation)
        if basis_t is not None:
            pred = pred @ basis_t
        mse = ((pred - y_t[None]) ** 2 * w_t).sum(dim=(1, 2)) / denom
        if grid is None:
            return mse, torch.zeros_like(mse)
        g = _torch_forward(grid_t, *params, config.activation)
        if basis_t is not None:
            g = g @ basis_t
        return mse, config.monotone_weight * _monotone_penalty(g.view(members + 1, *grid[1], -1),
                                                               config.monotone_margin)

    opt = torch.optim.Rprop([flat], lr=config.rprop_lr, etas=config.rprop_etas,
                            step_sizes=config.rprop_step_sizes)
    epoch = 0
    for epoch in range(1, config.stages * config.epochs_per_stage + 1):
        opt.zero_grad(set_to_none=False)
        mse, pen = member_losses()
        losses = mse + pen
        # Stopped members get zero gradient, and Rprop leaves a zero-gradient weight alone.
        (losses * active).sum().backward()
        opt.step()
        if epoch % config.check_every:
            continue
        current = losses.detach().to(torch.float64).numpy().copy()
        history.append(current)
        for b in range(members + 1):
            if active[b] == 0:
                continue
            if current[b] <= goal:
                active[b], epochs[b], reason[b] = 0.0, epoch, "goal"
            elif len(history) > lag:
                old = history[-1 - lag][b]
                if (old - current[b] <= config.plateau_rel_tol * old
                        or np.sqrt(max(old, 0.0)) - np.sqrt(max(current[b], 0.0)) < min_rms_gain):
                    active[b], epochs[b], reason[b] = 0.0, epoch, "plateau"
        if not bool(active.any()):
            break
    for b in range(members + 1):
        if active[b] != 0:
            epochs[b] = epoch
    with torch.no_grad():
        final_mse, final_pen = (v.to(torch.float64).numpy().tolist() for v in member_losses())
    w1, b1, w2, b2 = (p.detach().to(torch.float64).numpy().copy() for p in unflatten(flat.detach()))
    if basis is not None:
        w2, b2 = np.einsum("lk,bkh->blh", basis, w2), b2 @ basis.T
    report = TrainReport(mse_norm=[float(v) for v in final_mse], epochs=epochs, stop_reason=reason,
                         train_s=time.perf_counter() - t0, n_profiles=int(f.shape[0]),
                         n_points=int(np.unique(ids).shape[0]), valid_fraction=float(valid.mean()),
                         extra={"loss_goal_norm": goal, "monotone_penalty": [float(v) for v in final_pen],
                                "monotone_grid": None if grid is None else list(grid[1]),
                                "check_every": config.check_every,
                                "loss_history": [[float(f"{v:.6g}") for v in row] for row in history]})
    meta = {
        "train_mse_norm": report.mse_norm[0],
        "training": asdict(report),
        "config": asdict(config),
        "seed": config.seed,
        "data_sha256": data_hash(f, a, np.where(valid, y_mm, np.nan), ids),
        "versions": {"torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version()},
    }
    return RegionModel(w1, b1, w2, b2, x_mm=np.asarray(x_mm, dtype=float), force_range_n=f_range,
                       angle_range_deg=ANGLE_RANGE_DEG, depth_scale_mm=scale,
                       activation=config.activation, meta=meta)
