"""Is the object where the controller believes it is? (Re-register it when it moved.)

A probed object rests on the table, so it can only slide (and turn about the vertical):
what matters is a horizontal shift of its surface. Scanner points (base frame) are
aligned to the registered mesh by a translation-only, point-to-plane ICP with robust
weights; the vertical part of that translation soaks up what is not a move (the box
sinking into its pillow, a scanner's small height error). The horizontal part is seen
only where the scanned surface has relief across the scan line (edges, walls, slopes):
a flat patch seen face-on says nothing about a sideways shift, and the estimate stays
near zero there (damped), never invents a move.

:class:`PlacementMonitor` holds the mesh's dense samples; :meth:`PlacementMonitor.estimate`
returns a :class:`PlacementEstimate` in mm; :func:`reregister` finds the new placement
from a fresh cloud.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .core.geometry import Pose
from .learning.cloud import register_mesh_to_cloud, sample_mesh

UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PlacementEstimate:
    """Where the scanned surface lies relative to the registered mesh (base frame, mm)."""

    shift_mm: np.ndarray          # (3,) translation that best moves the mesh onto the points
    horizontal_mm: float          # |shift| across the base z axis
    relief: float                 # 0..1: how much the seen surface constrains a horizontal shift
    n_points: int
    rms_before_mm: float          # robust RMS point-to-surface distance, mesh where believed
    rms_after_mm: float           # ... and after the shift

    def as_dict(self) -> dict[str, object]:
        return {"shift_mm": np.round(self.shift_mm, 2).tolist(), "horizontal_mm": round(self.horizontal_mm, 2),
                "relief": round(self.relief, 3), "n_points": self.n_points,
                "rms_before_mm": _finite_or_none(self.rms_before_mm), "rms_after_mm": _finite_or_none(self.rms_after_mm)}


class PlacementMonitor:
    """Checks scans against the object mesh at its registered placement.

    ``threshold_mm``: a horizontal shift beyond this, that also explains the mismatch
    (the RMS distance at least halves), means the object moved. ``min_relief``: below
    it the scans cannot see a sideways shift at all and nothing is concluded.
    """

    def __init__(self, mesh: object, threshold_mm: float, n_samples: int = 60_000, seed: int = 0,
                 min_points: int = 40, min_relief: float = 0.02, table_clearance_mm: float = 3.0) -> None:
        self.threshold_mm = float(threshold_mm)
        self.min_points = min_points
        self.min_relief = min_relief
        self.table_clearance_mm = table_clearance_mm
        pts, nrm = sample_mesh(mesh, n_samples, seed)
        self._pts_obj = np.asarray(pts, float)
        self._nrm_obj = np.asarray(nrm, float)
        self._table_z_obj = float(np.asarray(mesh.vertices)[:, 2].min())   # type: ignore[attr-defined]
        self._tree = cKDTree(self._pts_obj)

    def estimate(self, points_base_mm: np.ndarray, base_to_object: Pose,
                 exclude_centre_mm: np.ndarray | None = None, exclude_radius_mm: float = 0.0,
                 max_points: int = 3000, iterations: int = 20) -> PlacementEstimate:
        """Align scanner points (N, 3, base frame, NaN allowed) to the mesh by a translation.

        Points on the table (within ``table_clearance_mm`` of the mesh's lowest z) and
        within ``exclude_radius_mm`` of ``exclude_centre_mm`` (the dent under a loaded
        tip) are left out. The work is done in the object frame (the k-d tree's) and
        the shift is reported in the base frame.
        """
        obj_to_base = base_to_object.inverse()
        p = np.asarray(points_base_mm, float).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1)]
        if exclude_centre_mm is not None and exclude_radius_mm > 0 and len(p):
            p = p[np.linalg.norm(p - np.asarray(exclude_centre_mm, float), axis=1) > exclude_radius_mm]
        q = obj_to_base.apply(p) if len(p) else p
        q = q[q[:, 2] > self._table_z_obj + self.table_clearance_mm] if len(q) else q
        if len(q) > max_points:
            q = q[np.linspace(0, len(q) - 1, max_points).astype(int)]
        up_obj = obj_to_base.apply_vector(UP)
        if len(q) < self.min_points:
            return PlacementEstimate(np.zeros(3), 0.0, 0.0, int(len(q)), float("nan"), float("nan"))
        shift, relief, rms0, rms1 = self._align(q, up_obj, iterations)
        shift_base = base_to_object.apply_vector(shift)
        horizontal = shift_base - UP * float(shift_base @ UP)
        return PlacementEstimate(shift_base, float(np.linalg.norm(horizontal)), relief, int(len(q)), rms0, rms1)

    def moved(self, est: PlacementEstimate) -> bool:
        """The scans say the object is elsewhere: a clear sideways shift that explains them.

        Explains them: the RMS distance at least halves, and there was a mismatch to
        explain. A shift s across a surface of relief r (the mean squared sine of its tilt
        along the shift) puts the points s sqrt(r) off it, so an object moved by the
        threshold shows at least threshold x sqrt(r); half that is asked. Scans that already
        fit to the scanner's noise are not a move, however far the fit then slides: on
        composite box 1010 (seed 1, a target on the pillow's nearly flat top) 0.02 mm halved
        to 0.01 mm by a 7 mm slide and paused the session.
        """
        mismatch_mm = 0.5 * self.threshold_mm * float(np.sqrt(max(est.relief, 0.0)))
        return (est.n_points >= self.min_points and est.relief >= self.min_relief
                and est.horizontal_mm > self.threshold_mm and est.rms_after_mm <= 0.5 * est.rms_before_mm
                and est.rms_before_mm >= mismatch_mm)

    # ------------------------------------------------------------------ internals
    def _residuals(self, q: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Point-to-plane distances of the points moved back by ``shift``, and the normals used."""
        _, idx = self._tree.query(q - shift)
        nrm = self._nrm_obj[idx]
        r = np.einsum("ij,ij->i", q - shift - self._pts_obj[idx], nrm)
        return r, nrm

    def _align(self, q: np.ndarray, up_obj: np.ndarray, iterations: int) -> tuple[np.ndarray, float, float, float]:
        shift = np.zeros(3)
        r0, _ = self._residuals(q, shift)
        rms0 = _robust_rms(r0)
        # Wide acceptance first (a shift of a few cm must still pull), then tighter.
        scale_mm = max(20.0, 3.0 * rms0)
        relief = 0.0
        horiz = np.eye(3) - np.outer(up_obj, up_obj)
        for _ in range(iterations):
            r, nrm = self._residuals(q, shift)
            w = _tukey(r, scale_mm)
            if w.sum() < self.min_points * 0.5:
                break
            a = (nrm * w[:, None]).T @ nrm
            b = (nrm * w[:, None]).T @ r
            # Damping: directions the surface does not constrain stay where they are.
            a += np.eye(3) * 1e-3 * w.sum()
            delta = np.linalg.solve(a, b)
            shift = shift + delta
            relief = float(np.linalg.eigvalsh(horiz @ a @ horiz)[-1] / max(w.sum(), 1e-9))
            scale_mm = max(2.0, 0.7 * scale_mm)
            if np.linalg.norm(delta) < 0.02:
                break
        r1, _ = self._residuals(q, shift)
        return shift, relief, rms0, _robust_rms(r1)


def _finite_or_none(x: float, digits: int = 3) -> float | None:
    """JSON has no NaN: a check with too few points has no RMS."""
    return round(float(x), digits) if np.isfinite(x) else None


def _tukey(r: np.ndarray, c: float) -> np.ndarray:
    u = np.clip(np.abs(r) / c, 0.0, 1.0)
    return (1.0 - u ** 2) ** 2


def _robust_rms(r: np.ndarray, keep: float = 0.8) -> float:
    """RMS of the best ``keep`` fraction of |r| (scanner outliers and dents left out)."""
    a = np.sort(np.abs(r))
    n = max(1, int(len(a) * keep))
    return float(np.sqrt(np.mean(a[:n] ** 2)))


def reregister(mesh: object, cloud_base_mm: np.ndarray, believed: Pose, max_rms_mm: float = 3.0,
               max_change_mm: float = 150.0, seed: int = 0) -> tuple[Pose, float]:
    """The object's new placement (base <- object) from a fresh cloud (base frame, table removed).

    ICP of the mesh to the cloud from the believed placement. Raises ValueError when the
    fit is poor or the change implausible (the caller pauses the session: a person must look).
    """
    # The cloud is in the base frame, so the believed base <- object pose is the start.
    pose, rms = register_mesh_to_cloud(mesh, cloud_base_mm, init=believed, seed=seed)
    change = float(np.linalg.norm(pose.position_mm - believed.position_mm))
    tilt_deg = float(np.degrees(np.arccos(np.clip(pose.rotation[:, 2] @ believed.rotation[:, 2], -1.0, 1.0))))
    if rms > max_rms_mm:
        raise ValueError(f"re-registration fits poorly: RMS {rms:.2f} mm > {max_rms_mm:.1f} mm")
    if change > max_change_mm or tilt_deg > 10.0:
        raise ValueError(f"re-registration moved the object implausibly far ({change:.0f} mm, "
                         f"tilted {tilt_deg:.1f} deg): not trusted")
    return pose, rms
