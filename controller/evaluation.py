"""``elastoprobe evaluate DIR``: a simulated session judged against the simulator's ground truth.

Nothing here tunes anything: the session's committed outputs (cloud, region map,
models) are compared with what the simulated object really is (true material of
every scanned point; noise-free profiles for any point, force and angle).
The region map is scored on the object's true top surface (the top-level keys: within
the plan's tilt, inside the arm's reach, one sample per mm^2, the session's labels
carried onto it, and ``coverage``); the same figures over the session's own scanned
cloud stay under ``"cloud"`` (docs/generated_objects.md says how and why).
Held-out sets: interior angles the plan did not train (between 25 and 155
degrees), forces between the trained ones, and surface points never probed.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .cellfactory import ground_truth_for
from .core.config import load_session_inputs
from .core.errors import InputError
from .core.geometry import INTERIOR_ANGLES_DEG, scan_direction
from .core.kinematics import inverse
from .core.validation import arm_model_for
from .journal import Journal, newest_phase
from .learning import evaluate as ev
from .learning.models import OutOfRange, RegionModel, ServedProfile
from .learning.support import SUPPORT_NAMES
from .predict import served_models
from .probe import standoff_pose

REACH_CELL_MM = 10.0


def _inputs_of(j: Journal) -> Any:
    prov = j.provenance()
    return load_session_inputs(prov["plan"]["path"], prov["cell"]["path"])


# Random in-range queries per region for the served-bounds check.
SERVED_BOUND_QUERIES = 10_000


def _held_out_angles(trained: list[float]) -> list[float]:
    """Interior angles between trained ones (within INTERIOR_ANGLES_DEG), e.g. 35, 60, 120, 145."""
    lo, hi = INTERIOR_ANGLES_DEG
    a = sorted(trained)
    mids = [(x + y) / 2.0 for x, y in zip(a, a[1:])]
    return [m for m in mids if lo <= m <= hi and all(abs(m - t) > 1.0 for t in a)]


def _held_out_forces(trained: list[float]) -> list[float]:
    f = sorted(trained)
    return [(x + y) / 2.0 for x, y in zip(f, f[1:])]


class FullSpan:
    """Full-span scores of served profiles: every sample where the true surface is defined."""

    def __init__(self) -> None:
        self.errors: list[np.ndarray] = []
        self.codes: list[np.ndarray] = []
        self.served = 0
        self.refused = 0                 # queries predict refuses (outside the trained ranges)

    def add(self, served: ServedProfile, truth_mm: np.ndarray, face: np.ndarray) -> None:
        scored = face & np.isfinite(truth_mm)
        self.served += int(truth_mm.size)
        # A NaN served sample is scored as the worst error, never skipped.
        err = np.where(np.isfinite(served.depth_mm), served.depth_mm - truth_mm, np.inf)
        self.errors.append(err[scored])
        self.codes.append(np.asarray(served.support)[scored])

    def _all(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.errors:
            return np.zeros(0), np.zeros(0, dtype=np.int8)
        return np.concatenate(self.errors), np.concatenate(self.codes)

    def rmse(self) -> float | None:
        e, _ = self._all()
        return float(np.sqrt(np.mean(e ** 2))) if e.size else None

    def max_abs(self) -> float | None:
        e, _ = self._all()
        return float(np.max(np.abs(e))) if e.size else None

    def scored_fraction(self) -> float | None:
        e, _ = self._all()
        return e.size / self.served if self.served else None

    def support_fractions(self) -> dict[str, Any]:
        _, c = self._all()
        names = list(SUPPORT_NAMES) + ["unknown"]
        idx = np.where((c >= 0) & (c < len(SUPPORT_NAMES)), c, len(SUPPORT_NAMES)).astype(int)
        counts = np.bincount(idx, minlength=len(names)) if c.size else np.zeros(len(names), int)
        return {n: _num(k / c.size) if c.size else None for n, k in zip(names, counts)}

    def rmse_by_support(self) -> dict[str, Any]:
        e, c = self._all()
        return {n: _num(float(np.sqrt(np.mean(e[c == k] ** 2)))) if np.any(c == k) else None
                for k, n in enumerate(SUPPORT_NAMES)}


def served_bounds(model: RegionModel, deepest_true_mm: float | None, force_range_n: tuple[float, float],
                  angle_range_deg: tuple[float, float], queries: int = SERVED_BOUND_QUERIES,
                  seed: int = 0) -> dict[str, Any]:
    """``queries`` random (F, angle) in the trained ranges (the model's own, else the plan's):
    the deepest and highest sample served, against the deepest true dent the region's
    characterized points make; a violation is a profile with a sample deeper than 1.5 x
    that dent or more than 1 mm above the undeformed surface (or not a number)."""
    lim = model.limits
    f_lo, f_hi = lim.force_range_n if lim is not None else force_range_n
    a_lo, a_hi = lim.angle_range_deg if lim is not None else angle_range_deg
    rng = np.random.default_rng(seed)
    depth = model.predict_batch_mm(rng.uniform(f_lo, f_hi, queries), rng.uniform(a_lo, a_hi, queries))
    ok = np.all(np.isfinite(depth) & (depth >= -1.0), axis=1)
    if deepest_true_mm is not None:
        ok &= np.all(depth <= 1.5 * deepest_true_mm, axis=1)
    return {"queries": queries, "deepest_served_mm": _num(np.nanmax(depth)),
            "highest_served_mm": _num(-np.nanmin(depth)), "deepest_true_mm": _num(deepest_true_mm),
            "violations": int(np.count_nonzero(~ok))}


def serve_or_refuse(model: RegionModel, force_n: float, angle_deg: float, tally: FullSpan) -> ServedProfile | None:
    """What predict serves for the query, or None (counted) when it refuses it: a held-out
    (F, angle) outside the region's trained ranges (an angle blocked at its points) is not
    something a user is served, so it is not scored."""
    try:
        return model.serve(force_n, angle_deg)
    except OutOfRange:
        tally.refused += 1
        return None


def evaluate_session(session_dir: Path, n_points_per_region: int = 6, seed: int = 12345) -> dict[str, Any]:
    j = Journal.open_readonly(session_dir)
    try:
        inputs = _inputs_of(j)
        sess = j.session()
        final = j.phase("final", 0)
        cloud = j.phase("cloud", 0)
        if final is None or cloud is None:
            raise InputError("the session has no final region map yet (run or resume it to the end)",
                             path=str(session_dir))
        truth = ground_truth_for(inputs, int(sess["seed"]))
        _, regions_rec = newest_phase(j, "regions")
        done = j.steps(statuses=["done"])
        robot_hours = j.robot_time_s()["total"] / 3600.0
        char = [rec for rec in done if rec.phase == "regions"]
        measured = [(rec, j.step_result(rec.step_id)) for rec in char]
    finally:
        j.close()
    # What predict serves: the newest models, or those `elastoprobe train` refitted since.
    source = served_models(Path(session_dir))
    models = {region: RegionModel.load(path) for region, path in source.files.items()}

    pts = cloud.arrays["points_mm"].astype(float)
    normals = cloud.arrays["normals"].astype(float)
    plan = inputs.plan
    pred = final.arrays["cloud_labels"]
    top = scored_top_surface(inputs, truth)
    region_map = _truth_surface_map(inputs, truth, pts, normals, pred, top)
    ceiling = _truth_surface_map(inputs, truth, pts, normals, truth.region_of(pts), top)
    cloud_map = _cloud_map(truth, pts, normals, pred, plan.sampling.max_tilt_deg)
    target_labels = dict(zip(regions_rec.arrays["labelled_targets"].tolist(),
                             regions_rec.arrays["labels"].tolist())) if regions_rec is not None else {}

    ch = plan.phases.characterize
    x = np.linspace(-plan.model.profile_span_mm / 2, plan.model.profile_span_mm / 2, plan.model.profile_samples)
    radius = inputs.cell.tool.tip_radius_mm
    ref = np.array(plan.sampling.reference_direction)

    def true_profile(point: np.ndarray, normal: np.ndarray, force: float, angle: float) -> np.ndarray:
        return truth.true_profile_mm(point, normal, scan_direction(normal, ref), force, angle, x)

    # The region of interest is where the scanner can see the surface: outside the tip's
    # footprint (the tip hides the surface under it, and a deep dent shows the tip
    # itself) and where this session's scans of the region actually had data on that
    # side of the probe (the probe body shadows the other side; which side depends on
    # whether the angle is under or over 90 degrees).
    coverage: dict[tuple[int, bool], np.ndarray] = {}
    counts: dict[tuple[int, bool], int] = {}
    for rec, res in measured:
        key = (target_labels.get(rec.plan.target_index, -1), rec.plan.angle_deg <= 90.0)
        coverage[key] = coverage.get(key, np.zeros(len(x))) + np.isfinite(res.profile_depth_mm)
        counts[key] = counts.get(key, 0) + 1
    outside_tip = np.abs(x) > radius

    def roi(label: int | None, angle: float, truth_row: np.ndarray) -> np.ndarray:
        key = (label if label is not None else -1, angle <= 90.0)
        seen = coverage[key] >= 0.5 * counts[key] if key in coverage else np.zeros(len(x), bool)
        return ev.roi_mask(truth_row[None, :])[0] & outside_tip & seen

    def on_face(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """(L,) where the true surface of the profile is defined (ev.profile_face_mask)."""
        t = scan_direction(normal, ref)
        return ev.profile_face_mask(truth, point, normal, t, x)

    full = {"held_out_angles": FullSpan(), "held_out_forces": FullSpan(), "held_out_points": FullSpan()}
    # The same per region: an object's figures can hide one region's misses behind another's
    # fits (and each region has its own noise and its own depth to be judged against).
    full_by_region: dict[int, dict[str, FullSpan]] = {
        r: {k: FullSpan() for k in full} for r in models}

    def tally(kind: str, label: int, served: ServedProfile, truth_row: np.ndarray, face: np.ndarray) -> None:
        full[kind].add(served, truth_row, face)
        full_by_region[label][kind].add(served, truth_row, face)
    deepest_true: dict[int, float] = {}

    # Noise floor and held-out angles/forces at the characterized points.
    noise_pred, noise_true, noise_roi = [], [], []
    noise_label: list[int] = []
    ha_pred, ha_true, ha_roi, hf_pred, hf_true, hf_roi = [], [], [], [], [], []
    points_done: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for rec, res in measured:
        f = float(np.linalg.norm(np.nanmean(res.scan_force_n, axis=0)))
        p, n = np.asarray(rec.plan.point_mm), np.asarray(rec.plan.normal)
        noise_pred.append(res.profile_depth_mm)
        noise_true.append(truth.true_profile_mm(p, n, np.asarray(rec.plan.t), f, rec.plan.angle_deg, x))
        label_of_step = target_labels.get(rec.plan.target_index, -1)
        noise_label.append(label_of_step)
        deepest_true[label_of_step] = max(deepest_true.get(label_of_step, 0.0), float(np.nanmax(noise_true[-1])))
        noise_roi.append(roi(target_labels.get(rec.plan.target_index), rec.plan.angle_deg, noise_true[-1]))
        points_done[rec.plan.target_index] = (p, n)
    for ti, (p, n) in points_done.items():
        label = target_labels.get(ti)
        if label not in models:
            continue
        m = models[label]
        face = on_face(p, n)
        for a in _held_out_angles(list(ch.angles_deg)):
            for f in ch.forces_n[1:-1]:
                served = serve_or_refuse(m, f, a, full["held_out_angles"])
                if served is None:
                    continue
                ha_pred.append(served.depth_mm)
                ha_true.append(true_profile(p, n, f, a))
                ha_roi.append(roi(label, a, ha_true[-1]))
                tally("held_out_angles", label, served, ha_true[-1], face)
        for f in _held_out_forces(list(ch.forces_n)):
            for a in ch.angles_deg:
                served = serve_or_refuse(m, f, a, full["held_out_forces"])
                if served is None:
                    continue
                hf_pred.append(served.depth_mm)
                hf_true.append(true_profile(p, n, f, a))
                hf_roi.append(roi(label, a, hf_true[-1]))
                tally("held_out_forces", label, served, hf_true[-1], face)

    # Held-out points: unprobed cloud points, interior of their predicted region, facing up.
    rng = np.random.default_rng(seed)
    hp_pred, hp_true, hp_roi = [], [], []
    up = normals[:, 2] > np.cos(np.radians(plan.sampling.max_tilt_deg))
    from scipy.spatial import cKDTree

    for label, m in models.items():
        cand = np.flatnonzero(up & (pred == label))
        others = np.flatnonzero(pred != label)
        if cand.size == 0:
            continue
        if others.size:
            # Interior of the predicted region (chosen without looking at the truth).
            dist, _ = cKDTree(pts[others]).query(pts[cand])
            interior = cand[dist > 20.0]
            cand = interior if interior.size else cand
        pick = rng.choice(cand, size=min(n_points_per_region, cand.size), replace=False)
        for k in pick:
            face = on_face(pts[k], normals[k])
            for f in ch.forces_n:
                for a in (45.0, 90.0, 135.0):
                    served = serve_or_refuse(m, f, a, full["held_out_points"])
                    if served is None:
                        continue
                    hp_pred.append(served.depth_mm)
                    hp_true.append(true_profile(pts[k], normals[k], f, a))
                    hp_roi.append(roi(label, a, hp_true[-1]))
                    tally("held_out_points", label, served, hp_true[-1], face)

    def rmse(pred_list: list[np.ndarray], true_list: list[np.ndarray], roi_list: list[np.ndarray]) -> float | None:
        if not pred_list:
            return None
        return ev.profile_rmse_mm(np.array(pred_list), np.array(true_list), np.array(roi_list))

    peak = float(np.nanmax(np.array(noise_true))) if noise_true else None

    def region_figures(r: int) -> dict[str, Any]:
        mine = [k for k, lab in enumerate(noise_label) if lab == r]
        floor = rmse([noise_pred[k] for k in mine], [noise_true[k] for k in mine], [noise_roi[k] for k in mine])
        return {"noise_floor_mm": _num(floor), "peak_depth_mm": _num(deepest_true.get(r)),
                "profile_rmse_full_mm": {k: _num(v.rmse()) for k, v in full_by_region[r].items()},
                "profile_max_abs_error_mm": {k: _num(v.max_abs()) for k, v in full_by_region[r].items()}}
    mirror_admitted = {str(r): m.meta.get("support", {}).get("mirror", {}).get("admitted")
                       for r, m in sorted(models.items())}
    mirror = [ev.mirror_residual(m, np.array(ch.forces_n), np.array([a for a in ch.angles_deg if a < 90.0]))
              for m in models.values()]
    return {
        "regions_found": int(len(np.unique(pred))),
        "regions_true": int(len(truth.region_names())),
        **region_map,
        # The best map this cloud can carry: every cloud point labelled with its true region,
        # carried onto the truth surface as the session's map is. What the map loses is the
        # difference; what the ceiling loses, the scan's gaps and spacing.
        "map_ceiling": {"what": "every cloud point labelled with its true region, scored as the map is",
                        **{k: v for k, v in ceiling.items()
                           if k in ("region_map_error", "worst_region_iou", "per_region_iou",
                                    "boundary_mm_mean", "boundary_mm_p90")}},
        "cloud": cloud_map,
        "profile_rmse_mm": {"held_out_angles": _num(rmse(ha_pred, ha_true, ha_roi)),
                            "held_out_forces": _num(rmse(hf_pred, hf_true, hf_roi)),
                            "held_out_points": _num(rmse(hp_pred, hp_true, hp_roi))},
        "profile_rmse_roi": "truth > 5% of its peak, |x| > tip radius, and seen by the scanner on that side "
                            "in >= half of the region's measured profiles",
        "profile_rmse_full_mm": {k: _num(v.rmse()) for k, v in full.items()},
        "profile_max_abs_error_mm": {k: _num(v.max_abs()) for k, v in full.items()},
        "profile_full_span": "every sample predict serves (the full-data member, clipped to the model's "
                             "physical bounds) where the object's true surface continues from the contact, tip "
                             "and shadow included; queries predict refuses (outside a region's trained "
                             "ranges) are counted, not scored; served_support_fraction and the RMSE by "
                             "support: held-out angles; profile_full_by_region: the full-span figures per region beside "
                             "that region's own noise floor and deepest true dent",
        "profile_full_by_region": {str(r): region_figures(r) for r in sorted(models)},
        "profile_full_scored_fraction": {k: _num(v.scored_fraction()) for k, v in full.items()},
        "held_out_queries_refused": {k: v.refused for k, v in full.items()},
        "served_support_fraction": full["held_out_angles"].support_fractions(),
        "profile_rmse_full_by_support_mm": full["held_out_angles"].rmse_by_support(),
        "mirror_admitted": mirror_admitted,
        "served_bounds": {str(r): served_bounds(m, deepest_true.get(r), (min(ch.forces_n), max(ch.forces_n)),
                                                (min(ch.angles_deg), max(ch.angles_deg)), seed=seed + r)
                          for r, m in sorted(models.items())},
        "models": source.source,
        "noise_floor_mm": _num(rmse(noise_pred, noise_true, noise_roi)),
        "peak_depth_mm": _num(peak),
        "mirror_residual": _num(float(np.nanmean(mirror)) if mirror else None),
        "probes": int(len(done)),
        "robot_hours": round(robot_hours, 4),
    }


def _within_reach(inputs: Any, points_mm: np.ndarray, normals: np.ndarray,
                  cell_mm: float = REACH_CELL_MM) -> np.ndarray:
    """(P,) True where the arm can press the surface point along its normal: the standoff and the
    touching pose of the tip (90 degrees) both have an inverse kinematics solution within the
    joint limits. Decided once per ``cell_mm`` cube (at its first point), so the few
    thousand IK solves stay cheap; the reach's edge is placed to within a cell."""
    model = arm_model_for(inputs.cell)
    b2o = inputs.cell.object.base_to_object.pose()
    seed = np.radians(np.asarray(inputs.cell.robot.home_joints_deg, dtype=float))
    radius = inputs.cell.tool.tip_radius_mm
    ref = np.asarray(inputs.plan.sampling.reference_direction, dtype=float)
    cells = np.floor(np.asarray(points_mm) / cell_mm).astype(np.int64)
    _, first, which = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    ok = np.zeros(first.size, bool)
    for k, i in enumerate(first):
        p, n = b2o.apply(points_mm[i]), b2o.apply_vector(normals[i])
        t = b2o.apply_vector(scan_direction(normals[i], ref))
        ok[k] = all(inverse(model, standoff_pose(p, n, t, 90.0, radius, offset), seed) is not None
                    for offset in (inputs.plan.probing.standoff_mm, 0.0))
    return ok[which.reshape(-1)]


def scored_top_surface(inputs: Any, truth: Any) -> tuple[Any, float]:
    """The surface a region map is scored on: the object's true top seen from above within the
    plan's tilt (``truth.top_surface``, one sample per mm^2 of projected area), the samples
    inside the arm's reach only. Returns (that TopSurface, the area out of reach in mm^2)."""
    top = truth.top_surface(inputs.plan.sampling.max_tilt_deg)
    reach = _within_reach(inputs, top.points_mm, top.normals)
    return top.subset(reach), float(top.area_mm2[~reach].sum())


def _truth_surface_map(inputs: Any, truth: Any, cloud_mm: np.ndarray, cloud_normals: np.ndarray,
                       cloud_labels: np.ndarray, scored: tuple[Any, float] | None = None) -> dict[str, Any]:
    """The map scored on the object's true top (within the plan's tilt, inside the arm's reach),
    sampled at one point per mm^2 of projected area (sim/truth_surface.py); the cloud's labels
    carried onto it by learning.evaluate.carry_labels (docs/generated_objects.md). ``scored``:
    :func:`scored_top_surface`'s result, when the caller has it already."""
    max_tilt = inputs.plan.sampling.max_tilt_deg
    top, out_of_reach = scored if scored is not None else scored_top_surface(inputs, truth)
    s = ev.truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, cloud_mm, cloud_normals,
                                cloud_labels, top.spacing_mm, seam_distance_mm=truth.boundary_distance_mm)
    wrong = s["wrong"]
    names = truth.region_names()
    return {
        "region_map_error": _num(s["mislabelled_fraction"]),
        "worst_region_iou": _num(s["worst_region_iou"]),
        "per_region_iou": {names[int(k)]: _num(v) for k, v in s["per_region_iou"].items()},
        "boundary_mm_mean": _num(s["boundary_mm_mean"]),
        "boundary_mm_p90": _num(s["boundary_mm_p90"]),
        "coverage": _num(s["coverage"]),
        # How far from the true seam the mislabelled area reaches (0: none mislabelled).
        "mislabelled_max_from_true_boundary_mm": _num(float(np.max(truth.boundary_distance_mm(top.points_mm[wrong])))
                                                      if wrong.any() else 0.0),
        "truth_surface": {
            "points": len(top), "area_mm2": round(s["area_mm2"], 1), "spacing_mm": top.spacing_mm,
            "max_tilt_deg": max_tilt, "out_of_reach_area_mm2": round(out_of_reach, 1),
            "uncovered_area_mm2": round(s["uncovered_area_mm2"], 1), "covered_within_mm": ev.COVERED_MM,
            "error_covered": _num(s["error_covered"]), "error_uncovered": _num(s["error_uncovered"]),
            "labels_from": f"nearest cloud point facing within {ev.CARRY_MAX_ANGLE_DEG:g} deg of the surface's "
                           "normal (the same face), however far",
        },
    }


def _cloud_map(truth: Any, cloud_mm: np.ndarray, cloud_normals: np.ndarray, cloud_labels: np.ndarray,
               max_tilt_deg: float) -> dict[str, Any]:
    """The map scored on the session's own cloud (the figures before the truth surface): the
    scanned points whose normal the probe can approach (within the plan's tilt limit), each
    against the true region of its nearest surface point; walls are scanned, never probed."""
    reachable = cloud_normals[:, 2] >= np.cos(np.radians(max_tilt_deg))
    pred, pts = cloud_labels[reachable], cloud_mm[reachable]
    true = truth.region_of(pts)
    scores = ev.region_map_scores(pred, true, None, pts)
    # Where the mislabelled points are: a few points on the seam of two materials (a tie
    # the scanner's noise decides) are not a misplaced boundary.
    wrong = np.array([scores["matching"].get(int(v), -1) for v in pred]) != true
    names = truth.region_names()
    return {
        "scored_points": int(reachable.sum()),
        "region_map_error": _num(scores["mislabelled_fraction"]),
        "worst_region_iou": _num(scores["worst_region_iou"]),
        "per_region_iou": {names[int(k)]: _num(v) for k, v in scores["per_region_iou"].items()},
        "boundary_mm_mean": _num(scores["boundary_mm_mean"]),
        "boundary_mm_p90": _num(scores["boundary_mm_p90"]),
        "mislabelled_points": int(np.count_nonzero(wrong)),
        "mislabelled_max_from_true_boundary_mm": _num(float(np.max(truth.boundary_distance_mm(pts[wrong])))
                                                      if wrong.any() else 0.0),
    }


def _num(v: Any) -> Any:
    """JSON-safe numbers: None for NaN/inf (never NaN or Infinity in the output)."""
    if v is None:
        return None
    v = float(v)
    return round(v, 6) if np.isfinite(v) else None
