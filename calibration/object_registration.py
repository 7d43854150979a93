"""Object registration: where the object really sits (base <- object) from a scanned cloud.

The cloud (base frame, mapped with the calibrated scanner mount) is taken into the
nominal object frame, the table is removed (RANSAC plane, controller.learning.cloud),
and the cloud is registered onto dense samples of the mesh by trimmed point-to-plane
ICP (:func:`~elastoprobe.controller.learning.cloud.icp`) started at the nominal
placement. Calibration refines a placement known to a few mm and degrees: a global
search (``register_mesh_to_cloud``) would be free to pick a symmetric twin (the
composite turned half a turn) whose regions are not where the object's are.

Local, but not from one start: trimmed ICP drops the worst tenth of its pairs, and on a
partial scan the few wall points that pin a direction down can be exactly that tenth,
so a single start may settle a couple of mm off with a fine-looking trimmed RMS
(measured: 2.2 mm off, trimmed RMS 0.06 mm, on a drawn cell whose sweep saw few
wall points). So ICP runs from the nominal placement and from starts shifted and turned
by about the placement's uncertainty, each refined last with no trimming (every point
within the gate counts), and the candidates are compared by one truncated cost over
every scanned point. A rival placement whose surface lies more than ``DISTINCT_MM`` away
and whose cost is within ``AMBIGUOUS_COST_RATIO`` of the best means the scan does not
decide: refused, not guessed.

The fit is judged by its RMS, by the size of the correction (a large one means the
wrong object or a bad start) and by the conditioning of the point-to-plane problem at
the solution: a shape that slides along itself (a ball turns freely, a flat slab
slides) cannot pin those motions down; translation must be observable, a free
rotation is reported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from elastoprobe.controller.core.errors import CalibrationError
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix
from elastoprobe.controller.learning.cloud import (REGISTRATION_GATE_MM, icp, refine_untrimmed, remove_table,
                                                  sample_mesh, truncated_cost_mm2)

from .common import FitReport, data_sha256, residual_stats


START_SHIFT_MM = 6.0          # starts cover the placement's uncertainty (set down a few mm off)
START_TURN_DEG = 4.0
AMBIGUOUS_COST_RATIO = 2.0    # cost is a mean square: 2x is the scan's noise RMS up by 41 %
DISTINCT_MM = 1.0             # placements whose surfaces lie further apart are different answers


@dataclass(frozen=True)
class _Candidate:
    correction: Pose           # nominal object <- true object
    cost: float                # truncated_cost_mm2 over every scanned point (mm^2)


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


def _starts(points: np.ndarray) -> list[Pose]:
    """ICP starts (mesh <- cloud): the nominal placement, shifted along x and y, turned about
    the vertical through the cloud's centre."""
    c = points.mean(axis=0)
    out = [Pose.identity()]
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            shift = np.zeros(3)
            shift[axis] = sign * START_SHIFT_MM
            out.append(Pose(shift, np.eye(3)))
    for sign in (-1.0, 1.0):
        r = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(sign * START_TURN_DEG)]))
        out.append(Pose(c - r @ c, r))
    return out


def _refine(sub: np.ndarray, points: np.ndarray, mesh_pts: np.ndarray, mesh_nrm: np.ndarray, tree: cKDTree,
            start: Pose) -> _Candidate:
    """Coarse (10 mm gate) and fine trimmed ICP from ``start``, then untrimmed within the gate."""
    pose, _, _ = icp(sub, mesh_pts, start, 40, 1e-4, mesh_nrm, 0.1, 10.0, tree=tree)
    pose, _, _ = icp(sub, mesh_pts, pose, 60, 1e-6, mesh_nrm, 0.1, REGISTRATION_GATE_MM, tree=tree)
    pose = refine_untrimmed(sub, mesh_pts, mesh_nrm, tree, pose)
    return _Candidate(pose.inverse(), truncated_cost_mm2(points, pose, mesh_pts, mesh_nrm, tree))


def _surface_gap_mm(a: Pose, b: Pose, mesh_pts: np.ndarray, tree: cKDTree) -> float:
    """How far apart (mm) the object's surface lies under placements ``a`` and ``b``: the 99th
    percentile distance of the surface placed by ``a`` from the surface placed by ``b``. A motion
    the shape cannot show (a ball turning about its centre) leaves the surface where it was."""
    dist, _ = tree.query(b.inverse().apply(a.apply(mesh_pts)), workers=-1)
    return float(np.quantile(dist, 0.99))


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
    candidates = [_refine(sub, above, mesh_pts, mesh_nrm, tree, start) for start in _starts(above)]
    best = min(candidates, key=lambda c: c.cost)
    rivals = [c for c in candidates if c.cost <= AMBIGUOUS_COST_RATIO * best.cost
              and _surface_gap_mm(c.correction, best.correction, mesh_pts, tree) > DISTINCT_MM]
    if rivals:
        other = min(rivals, key=lambda c: c.cost)
        gap_mm = _surface_gap_mm(other.correction, best.correction, mesh_pts, tree)
        raise CalibrationError(
            f"object: two placements {gap_mm:.1f} mm apart fit the "
            f"scan about equally well (RMS {np.sqrt(best.cost):.3f} and {np.sqrt(other.cost):.3f} mm): the scanned "
            f"surface does not tell them apart; sweep more of the object's walls and edges")
    correction = best.correction
    shift_mm, turn_deg = correction.distance_to(Pose.identity())
    if shift_mm > max_shift_mm or turn_deg > max_turn_deg:
        raise CalibrationError(f"object: the registration moves the object {shift_mm:.1f} mm and {turn_deg:.1f} deg "
                               f"from its nominal placement (limits {max_shift_mm:g} mm, {max_turn_deg:g} deg): "
                               f"wrong object file or placement?")
    # Residuals: every scanned point against the registered mesh (dense samples with normals).
    in_mesh = correction.inverse().apply(above)
    dist, idx = tree.query(in_mesh)
    plane = np.einsum("ij,ij->i", in_mesh - mesh_pts[idx], mesh_nrm[idx])
    keep = dist < REGISTRATION_GATE_MM
    rms, worst = residual_stats(plane[keep])
    c6, c3 = _point_to_plane_conditioning(mesh_pts[idx[keep]], mesh_nrm[idx[keep]], mesh_pts.mean(axis=0),
                                          float(np.linalg.norm(np.ptp(mesh_pts, axis=0))) / 2.0)
    if keep.mean() < 0.8 or rms > max_rms_mm:
        raise CalibrationError(f"object: poor registration (RMS {rms:.3f} mm, {100 * keep.mean():.0f}% of points "
                               f"within {REGISTRATION_GATE_MM:g} mm of the mesh; limits {max_rms_mm} mm and 80%)")
    if not np.isfinite(c3) or c3 > max_translation_condition:
        raise CalibrationError(f"object: the scanned surface does not pin the object's position down (translation "
                               f"condition number {c3:.3g}); scan more of its sides")
    return ObjectFit(base_to_object_nominal.compose(correction), correction,
                     FitReport(int(keep.sum()), rms, worst, "mm", c6,
                               {"translation_condition_number": c3, "rotation_free": bool(c6 > 1e3),
                                "inlier_fraction": float(keep.mean()), "correction_mm": shift_mm,
                                "correction_deg": turn_deg, "starts": len(candidates),
                                "start_rms_mm": sorted(round(float(np.sqrt(c.cost)), 4) for c in candidates)}),
                     data_sha256(cloud))
