"""The probe tip (tip-sphere centre) in the tool frame, by pivoting or by touching a reference sphere.

Two data sets, one unknown: ``tip_mm``, the tip centre in the frame of the poses the
arm reported (base <- tcp with the cell's nominal flange_to_tcp, or base <- flange).

1. Pivoting about a fixed point (a divot the tip sits in while the wrist turns):
   R_i tip + t_i = pivot for every pose, i.e. the linear system
   ``[R_i  -I] [tip; pivot] = -t_i`` (docs/design.md §10).

2. Touch-offs on a rigid reference sphere of known radius (what the simulated cell
   offers, and what a real cell does with a CMM sphere): each touch stops where the
   tip sphere meets the artefact, so |R_i tip + t_i - c| = rho with rho = artefact
   radius + tip radius. A touch constrains the tip only along the contact normal
   n_i, in the tool frame R_i^T n_i: approaching always along the probe axis leaves
   the lateral offset unobservable, so touches must come in along directions that
   lean away from the probe axis. Started from the pivot-like linear system
   ``[R_i -I][tip; c] = -t_i - rho e_i`` (e_i the approach direction, ~ -n_i) and
   refined by Gauss-Newton on the distances.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from elastoprobe.controller.core.errors import CalibrationError

from .common import (FitReport, data_sha256, residual_stats, rotation_spread_deg,
                     scaled_condition_number)

MIN_PIVOT_POSES = 6
MIN_TOUCHES = 9


@dataclass(frozen=True)
class TipFit:
    """The tip centre in the pose frame (mm), the fixed point (base, mm), and the fit quality."""

    tip_mm: np.ndarray
    fixed_point_base_mm: np.ndarray
    report: FitReport
    data_sha256: str


def _stack_pivot(rotations: np.ndarray) -> np.ndarray:
    n = rotations.shape[0]
    a = np.zeros((3 * n, 6))
    a[:, :3] = rotations.reshape(3 * n, 3)
    a[:, 3:] = -np.tile(np.eye(3), (n, 1))
    return a


def _check_inputs(rotations: np.ndarray, translations_mm: np.ndarray, minimum: int, what: str) -> None:
    n = rotations.shape[0]
    if n < minimum:
        raise CalibrationError(f"{what}: {n} poses, at least {minimum} are needed")
    if rotations.shape != (n, 3, 3) or translations_mm.shape != (n, 3):
        raise CalibrationError(f"{what}: rotations must be (N,3,3) and translations (N,3)")


def solve_pivot(rotations: np.ndarray, translations_mm: np.ndarray, max_condition: float = 50.0,
                min_spread_deg: float = 20.0, max_rms_mm: float = 0.5) -> TipFit:
    """Tip and pivot point from poses (R_i, t_i) pivoting about one fixed point.

    Refuses fewer than 6 poses, a rotation spread under ``min_spread_deg``, rotations
    about a single axis (the tip's component along it is then free: the scaled
    condition number explodes), or an RMS residual above ``max_rms_mm`` (the tip
    slipped out of the divot).
    """
    r = np.asarray(rotations, dtype=float)
    t = np.asarray(translations_mm, dtype=float)
    _check_inputs(r, t, MIN_PIVOT_POSES, "pivot")
    spread = rotation_spread_deg(r)
    if spread < min_spread_deg:
        raise CalibrationError(f"pivot: the orientations span only {spread:.1f} deg (< {min_spread_deg:g}); "
                               f"tilt the tool further about the fixed point")
    a = _stack_pivot(r)
    cond = scaled_condition_number(a)
    if not np.isfinite(cond) or cond > max_condition:
        raise CalibrationError(f"pivot: degenerate orientations (condition number {cond:.3g} > {max_condition:g}): "
                               f"rotate about at least two different axes")
    x, *_ = np.linalg.lstsq(a, -t.ravel(), rcond=None)
    res = (a @ x + t.ravel()).reshape(-1, 3)
    rms, worst = residual_stats(np.linalg.norm(res, axis=1))
    if rms > max_rms_mm:
        raise CalibrationError(f"pivot: residual RMS {rms:.3f} mm > {max_rms_mm} mm (did the tip move in the divot?)")
    return TipFit(x[:3], x[3:], FitReport(r.shape[0], rms, worst, "mm", cond, {"rotation_spread_deg": spread}),
                  data_sha256(r, t))


def solve_sphere_touches(rotations: np.ndarray, translations_mm: np.ndarray, approach_dirs: np.ndarray,
                         rho_mm: float, max_condition: float = 60.0, max_rms_mm: float = 0.1,
                         min_spread_deg: float = 20.0) -> TipFit:
    """Tip and artefact centre from touch-offs on a sphere: |R_i tip + t_i - c| = rho.

    ``approach_dirs`` (N,3): the unit base-frame direction of each touching move;
    ``rho_mm``: artefact radius + tip radius. The fixed point of the result is the
    artefact's centre. Refuses fewer than 9 touches, a small rotation spread, a
    Jacobian whose scaled condition number exceeds ``max_condition`` (e.g. every
    touch along the probe axis, aimed at the centre: the lateral tip offset is unobservable) or an RMS
    distance residual above ``max_rms_mm``.
    """
    r = np.asarray(rotations, dtype=float)
    t = np.asarray(translations_mm, dtype=float)
    e = np.asarray(approach_dirs, dtype=float)
    _check_inputs(r, t, MIN_TOUCHES, "sphere touch-off")
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    spread = rotation_spread_deg(r)
    if spread < min_spread_deg:
        raise CalibrationError(f"sphere touch-off: the orientations span only {spread:.1f} deg (< {min_spread_deg:g})")
    a = _stack_pivot(r)
    x0, *_ = np.linalg.lstsq(a, -(t + rho_mm * e).ravel(), rcond=None)

    def residual(x: np.ndarray) -> np.ndarray:
        p = np.einsum("nij,j->ni", r, x[:3]) + t - x[3:]
        return np.linalg.norm(p, axis=1) - rho_mm

    def jac(x: np.ndarray) -> np.ndarray:
        p = np.einsum("nij,j->ni", r, x[:3]) + t - x[3:]
        nrm = p / np.linalg.norm(p, axis=1, keepdims=True)
        return np.hstack([np.einsum("ni,nij->nj", nrm, r), -nrm])

    sol = least_squares(residual, x0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, max_nfev=200)
    j = jac(sol.x)
    # All unknowns are in mm: the plain condition number is meaningful (column scaling would
    # hide a tip column that is uniformly small, the very degeneracy to catch).
    sv = np.linalg.svd(j, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if not np.isfinite(cond) or cond > max_condition:
        raise CalibrationError(f"sphere touch-off: the tip is not observable from these touches (condition number "
                               f"{cond:.3g} > {max_condition:g}); approach along directions that lean away from "
                               f"the probe axis, from several sides")
    res = residual(sol.x)
    rms, worst = residual_stats(res)
    if rms > max_rms_mm:
        raise CalibrationError(f"sphere touch-off: distance residual RMS {rms:.3f} mm > {max_rms_mm} mm "
                               f"(artefact moved, wrong radius, or a soft contact?)")
    normals_tool = np.einsum("nji,nj->ni", r, -e)
    return TipFit(sol.x[:3], sol.x[3:],
                  FitReport(r.shape[0], rms, worst, "mm", cond,
                            {"rotation_spread_deg": spread, "linear_start_mm": x0[:3],
                             "normal_spread_tool": np.linalg.svd(normals_tool, compute_uv=False)}),
                  data_sha256(r, t, e, np.array([rho_mm])))
