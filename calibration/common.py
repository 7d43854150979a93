"""Shared pieces of the calibration solvers: the error type, fit reports, data hashes.

Every solver returns its result with a :class:`FitReport` (residuals, conditioning,
sample count) and raises :class:`CalibrationError` with a plain reason when the data
cannot support a trustworthy answer (too few samples, degenerate poses, residuals far
above the sensor noise).
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from elastoprobe.controller.core.geometry import matrix_to_rotvec


@dataclass(frozen=True)
class FitReport:
    """How well a least-squares calibration fit its data.

    ``rms`` and ``max_abs`` are over the final residuals in ``residual_unit`` (e.g. "N",
    "mm"); ``condition_number`` is that of the column-scaled design matrix (or the
    Jacobian at the solution); ``extra`` carries solver-specific figures.
    """

    n_samples: int
    rms: float
    max_abs: float
    residual_unit: str
    condition_number: float
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["extra"] = {k: _plain(v) for k, v in self.extra.items()}
        return d


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def residual_stats(residuals: np.ndarray) -> tuple[float, float]:
    """(rms, max |r|) of a residual array (any shape)."""
    r = np.asarray(residuals, dtype=float).ravel()
    if r.size == 0:
        return 0.0, 0.0
    return float(np.sqrt(np.mean(r * r))), float(np.max(np.abs(r)))


def scaled_condition_number(design: np.ndarray) -> float:
    """Condition number of ``design`` after scaling each column to unit norm.

    Column scaling removes the arbitrary effect of units (mm against kg), so the
    number measures only how close the columns are to being dependent, i.e. how
    degenerate the poses are. Infinite when a column is all zero.
    """
    a = np.asarray(design, dtype=float)
    norms = np.linalg.norm(a, axis=0)
    if np.any(norms < 1e-12):
        return float("inf")
    s = np.linalg.svd(a / norms, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def rotation_spread_deg(rotations: np.ndarray) -> float:
    """The largest angle (deg) between any rotation and the first one: 0 for a pure translation set."""
    r = np.asarray(rotations, dtype=float)
    if r.shape[0] < 2:
        return 0.0
    angles = [np.degrees(np.linalg.norm(matrix_to_rotvec(r[0].T @ ri))) for ri in r[1:]]
    return float(max(angles))


def axis_spread(directions: np.ndarray) -> np.ndarray:
    """Singular values (descending) of the centred unit directions (N,3): how many axes they span.

    Directions that all lie near one line give a smallest-but-one value near 0.
    """
    d = np.asarray(directions, dtype=float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.linalg.svd(d - d.mean(axis=0), compute_uv=False) / np.sqrt(max(d.shape[0], 1))


def data_sha256(*arrays: np.ndarray) -> str:
    """SHA-256 over the raw data a solver used (float64, C order, with shapes), as hex."""
    h = hashlib.sha256()
    for a in arrays:
        arr = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def skew(v: np.ndarray) -> np.ndarray:
    """K(v) with K(v) @ w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) cross-product matrices."""
    v = np.asarray(v, dtype=float)
    k = np.zeros((v.shape[0], 3, 3))
    k[:, 0, 1], k[:, 0, 2] = -v[:, 2], v[:, 1]
    k[:, 1, 0], k[:, 1, 2] = v[:, 2], -v[:, 0]
    k[:, 2, 0], k[:, 2, 1] = -v[:, 1], v[:, 0]
    return k
