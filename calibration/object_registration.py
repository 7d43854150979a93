"""Object registration: where the object really sits (base <- object) from a scanned cloud.

The cloud (base frame, mapped with the calibrated scanner mount) is taken into the
nominal object frame, the table is removed (RANSAC plane, controller.learning.cloud),
and the cloud is registered onto dense samples of the mesh by trimmed point-to-plane
ICP (:func:`~elastoprobe.controller.learning.cloud.icp`) started at the nominal
placement. Calibration refines a placement known to a few mm and degrees: a global
search (``register_mesh_to_cloud``) would be free to pick a symmetric twin (the
composite turned half a turn) whose regions are not where the object's are. The fit is
judged by its RMS, by the size of the correction (a large one means the wrong object
or a bad start) and by the conditioning of the point-to-plane problem at the solution:
a shape that slides along itself (a ball turns freely, a flat slab slides) cannot pin
those motions down; translation must be observable, a free rotation is reported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from elastoprobe.controller.geometry import Pose
from elastoprobe.controller.learning.cloud import icp, remove_table, sample_mesh

from .common import CalibrationError, FitReport, data_sha256, residual_stats


@dataclass(frozen=True)
class ObjectFit:
    base_to_object: Pose
    correction: Pose               # nominal object <- true object
    report: FitReport
    data_sha256: str


def _point_to_plane_conditioning(points: np.ndarray, normals: np.ndarray, centre: np.ndarray,
                                 length_scale_mm: float) -> tuple[float, float]:
    """(condition number of the full 6-dof point-to-plane problem, of its translation block)."""
    p = (points - centre) / length_scale_mm
    j = np.hstack([np.cross(p, normals), normals])
    s6 = np.linalg.svd(j, compute_uv=False)
    s3 = np.linalg.svd(normals, compute_uv=False)
    c6 = float(s6[0] / s6[-1]) if s6[-1] > 0 else float("inf")
    c3 = float(s3[0] / s3[-1]) if s3[-1] > 0 else float("inf")
    return c6, c3


def register_object(mesh, cloud_base_mm: np.ndarray, base_to_object_nominal: Pose,  # noqa: ANN001 — trimesh
                    max_rms_mm: float = 0.5, max_shift_mm: float = 40.0, max_turn_deg: float = 15.0,
                    max_translation_condition: float = 30.0, seed: int = 0) -> ObjectFit:
    """Registered placement of ``mesh`` (object frame, z up, resting on z = 0) from a cloud (base, mm)."""
    cloud = np.asarray(cloud_base_mm, dtype=float)
    if cloud.shape[0] < 500:
        raise CalibrationError(f"object: only {cloud.shape[0]} scanned points; sweep the object first")
    obj_pts = base_to_object_nominal.inverse().apply(cloud)
    try:
        above, _ = remove_table(obj_pts, distance_threshold_mm=1.5, up=np.array([0.0, 0.0, 1.0]), seed=seed)
    except ValueError as exc:
        raise CalibrationError(f"object: no table plane found in the cloud ({exc})") from None
    if above.shape[0] < 300:
        raise CalibrationError(f"object: only {above.shape[0]} points above the table")
    mesh_pts, mesh_nrm = sample_mesh(mesh, 80_000, seed)
    tree = cKDTree(mesh_pts)
    rng = np.random.default_rng(seed)
    sub = above[rng.permutation(above.shape[0])[:30_000]]
    # Coarse (points farther than 10 mm ignored), then fine around the coarse answer.
    mesh_from_cloud, _, _ = icp(sub, mesh_pts, Pose.identity(), 40, 1e-4, mesh_nrm, 0.1, 10.0, tree=tree)
    mesh_from_cloud, _, _ = icp(sub, mesh_pts, mesh_from_cloud, 60, 1e-6, mesh_nrm, 0.1, 3.0, tree=tree)
    correction = mesh_from_cloud.inverse()
    shift_mm, turn_deg = correction.distance_to(Pose.identity())
    if shift_mm > max_shift_mm or turn_deg > max_turn_deg:
        raise CalibrationError(f"object: the registration moves the object {shift_mm:.1f} mm and {turn_deg:.1f} deg "
                               f"from its nominal placement (limits {max_shift_mm:g} mm, {max_turn_deg:g} deg): "
                               f"wrong object file or placement?")
    # Residuals: scanned points against the registered mesh (dense samples with normals).
    in_mesh = correction.inverse().apply(above)
    dist, idx = tree.query(in_mesh)
    plane = np.einsum("ij,ij->i", in_mesh - mesh_pts[idx], mesh_nrm[idx])
    keep = dist < 3.0
    rms, worst = residual_stats(plane[keep])
    c6, c3 = _point_to_plane_conditioning(mesh_pts[idx[keep]], mesh_nrm[idx[keep]], mesh_pts.mean(axis=0),
                                          float(np.linalg.norm(np.ptp(mesh_pts, axis=0))) / 2.0)
    if keep.mean() < 0.8 or rms > max_rms_mm:
        raise CalibrationError(f"object: poor registration (RMS {rms:.3f} mm, {100 * keep.mean():.0f}% of points "
                               f"within 3 mm of the mesh; limits {max_rms_mm} mm and 80%)")
    if not np.isfinite(c3) or c3 > max_translation_condition:
        raise CalibrationError(f"object: the scanned surface does not pin the object's position down (translation "
                               f"condition number {c3:.3g}); scan more of its sides")
    return ObjectFit(base_to_object_nominal.compose(correction), correction,
                     FitReport(int(keep.sum()), rms, worst, "mm", c6,
                               {"translation_condition_number": c3, "rotation_free": bool(c6 > 1e3),
                                "inlier_fraction": float(keep.mean()), "correction_mm": shift_mm,
                                "correction_deg": turn_deg}),
                     data_sha256(cloud))
