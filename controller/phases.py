"""The session's phases (docs/design.md §2): cloud, sampling, survey, regions, characterize, models,
densify rounds, final map.

Each ``phase_*`` either reads its committed outputs back from the journal (a resumed
session continues from exactly the same targets) or computes them and commits them
in one transaction together with the steps it plans. ``run_all`` strings them
together into the session's plan: a generator that yields a message
(:mod:`.messages`) for each thing the engine does for it (sweep the object, run a
round of planned steps, move the lifecycle on to planning or learning).
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.spatial import cKDTree

from .acquire import unseen_of_cloud
from .core.config import SessionInputs
from .core.devices import Cell
from .core.errors import BudgetSpent, SessionAborted
from .core.geometry import INTERIOR_ANGLES_DEG, Pose, follows_scan_rule, scan_direction
from .journal import Journal, StepPlan, newest_phase
from .learning import cloud as cl
from .learning import contact as ct
from .learning import densify as dn
from .learning import neural_gas as ng
from .learning import profiles as prof
from .learning import regions as rg
from .learning import surface_map as sm
from .learning import survey_density as sd
from .learning import targets as tg
from .learning.densify import averaged_noise_mm
from .learning.models import RegionModel, ServingLimits, TrainConfig, fit_region_model
from .learning.support import UNSUPPORTED, CompletedTargets, RegionSteps, complete_targets, support_table
from .messages import Lifecycle, Plan, ProbeRound, Sweep
from .ordering import order_targets
from .probe import ProbeExecutor, ProbeTarget, StepData
from .report import write_report
from .testing import crash_point

# Steps belong to the phase that planned them: the survey of the neural-gas targets is
# planned by "sampling", the survey of densified points by "densify", characterization
# by "regions".
SURVEY_PHASES = ("sampling", "densify")
FEATURE_HALF_WINDOW_MM = 15.0
# The simulator key of the cloud sweep: above every planned step id (ids count up
# from 0), below the simulator's own "outside any step" key (2**32 - 1).
SWEEP_STEP_KEY = 2**32 - 2
CHARACTERIZE = "regions"
# Training weight of a target sample by its support (support.SUPPORT_NAMES order): what was
# measured, mirrored or under the tip counts fully, an inferred sample half, an
# interpolated one a quarter (they shape the curve between supported samples only).
SUPPORT_WEIGHTS = np.array([1.0, 1.0, 1.0, 0.5, 0.25])


def canonical(values: np.ndarray, decimals: int) -> np.ndarray:
    """Phase outputs rounded to a fixed grid before they are committed and used.

    Linear algebra on the same numbers can differ in the last bits between processes
    (SIMD paths depend on memory alignment); a resumed session must plan from exactly
    the numbers an uninterrupted one used, so outputs are rounded far below any
    physical meaning (1 nm, 1e-9 of a unit vector) and everything downstream reads the
    rounded, committed values.
    """
    out = np.round(np.asarray(values, dtype=np.float64), decimals)
    out[out == 0.0] = 0.0      # no negative zeros: their bytes differ from +0
    return out


def _done_steps(j: Any, phases: tuple[str, ...]) -> list[Any]:
    return [r for r in j.steps(statuses=["done"]) if r.phase in phases]


@dataclass
class PhaseContext:
    """What the phases work with: the session's inputs and journal, the cell (its placement of
    the object and scanner mount), the executor's motion checks (reach, collisions) and the
    session's event log; and what the phases found so far."""

    journal: Journal
    inputs: SessionInputs
    cell: Cell
    seed: int
    session_dir: Path
    executor: ProbeExecutor
    log: Callable[..., None]                                       # log(event, **record)
    cloud_mm: np.ndarray | None = None
    cloud_normals: np.ndarray | None = None
    targets: dict[int, ProbeTarget] = field(default_factory=dict)
    edge_flag: dict[int, bool] = field(default_factory=dict)
    labels: dict[int, int] = field(default_factory=dict)         # target index -> region
    n_regions: int = 0
    models: dict[int, RegionModel] = field(default_factory=dict)
    model_round: int = -1
    _surface: Any = None                                           # surface_map.SurfaceGraph, built once

    def surface(self) -> Any:
        """The committed cloud's surface graph (learning.surface_map), built on first use."""

        if self._surface is None:
            assert self.cloud_mm is not None and self.cloud_normals is not None
            self._surface = sm.build_graph(self.cloud_mm, self.cloud_normals)
        return self._surface

    def surface_neighbours(self, points_mm: np.ndarray) -> np.ndarray:
        """(E,2) neighbour pairs of targets: their cells on the cloud touch without a fold between."""

        g = self.surface()
        return np.asarray(sm.seed_neighbours(g, sm.cells(g, points_mm)), dtype=np.int64).reshape(-1, 2)

    @property
    def grid(self) -> prof.ProfileGrid:
        return plan_grid(self.inputs)


# --------------------------------------------------------------------------- helpers
def plan_grid(inputs: Any) -> prof.ProfileGrid:
    """The profile grid a session's plan asks for."""
    m = inputs.plan.model
    return prof.ProfileGrid(span_mm=m.profile_span_mm, samples=m.profile_samples)


def measure_step_data(inputs: SessionInputs, cell: Cell, target: ProbeTarget, data: StepData
                      ) -> prof.StepMeasurement:
    """The step's profile and its facts (tip, rejected samples) from the scans and the arm's poses."""
    return measure_step_arrays(data.scans_xz_mm, data.scan_pose, data.reference_xz_mm, data.reference_pose,
                               target, plan_grid(inputs), cell.tcp_to_scanner, cell.base_to_object,
                               inputs.cell.tool.tip_radius_mm)


def measure_step_arrays(scans_xz_mm: np.ndarray, scan_pose: np.ndarray, reference_xz_mm: np.ndarray,
                        reference_pose: np.ndarray, target: ProbeTarget, grid: prof.ProfileGrid,
                        tcp_to_scanner: Any, base_to_object: Any, tip_radius_mm: float) -> prof.StepMeasurement:
    """:func:`profiles.measure_step` on a step's stored arrays (scans and TCP poses, base frame)."""
    scans = prof.step_scan_points(scans_xz_mm, scan_pose, tcp_to_scanner, base_to_object)
    refs = prof.step_scan_points(reference_xz_mm, reference_pose, tcp_to_scanner, base_to_object)
    tips = base_to_object.inverse().apply(np.asarray(scan_pose, dtype=float).reshape(-1, 6)[:, :3])
    return prof.measure_step(scans, refs, tips, target.point_mm, target.normal, target.t, grid, tip_radius_mm)


def robust_average(depths_mm: np.ndarray, k_mad: float = 4.0) -> np.ndarray:
    """Per-sample mean of the scans without scattered returns (:func:`profiles.robust_mean`)."""
    return prof.robust_mean(depths_mm, k_mad).mean_mm


def _targets_from_arrays(arrays: dict[str, np.ndarray], first_index: int = 0) -> dict[int, ProbeTarget]:
    pts, nrm, tt = arrays["target_points_mm"], arrays["target_normals"], arrays["target_t"]
    idx = arrays.get("target_index", np.arange(first_index, first_index + len(pts)))
    return {int(i): ProbeTarget(int(i), pts[k], nrm[k], tt[k]) for k, i in enumerate(idx)}


def _plan_steps(ctx: PhaseContext, target_ids: list[int], angles_deg: list[float], forces_n: list[float],
                start_order: int, angles_by_target: dict[int, list[float]] | None = None) -> list[StepPlan]:
    """Steps for targets in the given order: per target, per angle (``angles_by_target``'s
    when it names the target), increasing force."""
    j = ctx.journal
    step_id = j.next_step_id()
    order = start_order
    steps = []
    for ti in target_ids:
        tgt = ctx.targets[ti]
        for a in (angles_by_target or {}).get(ti, angles_deg):
            for f in sorted(forces_n):
                steps.append(StepPlan(step_id=step_id, target_index=ti, point_mm=tgt.point_mm, normal=tgt.normal,
                                      t=tgt.t, angle_deg=float(a), force_n=float(f), order_index=order))
                step_id += 1
                order += 1
    return steps


def _next_order(ctx: PhaseContext) -> int:
    j = ctx.journal
    recs = j.steps()
    return (max(r.plan.order_index for r in recs) + 1) if recs else 0


def _ordered(ctx: PhaseContext, ids: list[int]) -> list[int]:

    if len(ids) < 3:
        return ids
    cell = ctx.cell
    pts = cell.base_to_object.apply(np.array([ctx.targets[i].point_mm for i in ids]))
    order, _, _ = order_targets(pts, travel_z_mm=float(pts[:, 2].max()) + 60.0)
    return [ids[k] for k in order]


# --------------------------------------------------------------------------- phases
def phase_cloud(ctx: PhaseContext) -> Plan:
    """The object's cloud, table removed: from a file or a sweep (the engine's), committed."""
    j = ctx.journal
    rec = j.phase("cloud", 0)
    if rec is not None:
        ctx.cloud_mm, ctx.cloud_normals = rec.arrays["points_mm"].astype(float), rec.arrays["normals"].astype(float)
        return
    plan = ctx.inputs.plan
    if plan.cloud.source == "file":
        pts, normals = cl.load_cloud(ctx.inputs.resolve(ctx.inputs.plan_path, plan.cloud.file or ""),
                                     n_samples=plan.cloud.max_points, seed=ctx.seed)
        robot_s = 0.0
    else:
        # Keyed at the sweep, not before: a resumed session reaches it after other
        # motions (the resume retract) than an uninterrupted one.
        swept = yield Sweep(SWEEP_STEP_KEY)
        pts, robot_s = swept.points_mm, swept.robot_s
        for why in swept.replanned:
            ctx.log("sweep_line_replanned", reason=why)
        for why in swept.refused:
            ctx.log("sweep_line_skipped", reason=why)
        sweep = swept.outputs()
        normals = None
        j.add_robot_time("sweep", robot_s)
    obj_pts, plane = remove_table_below(pts, seed=ctx.seed,
                                         link_mm=FOOT_LINK_SPACINGS * plan.cloud.sweep_spacing_mm)
    if plan.cloud.source != "file":
        # What the session keeps, the table gone, is what counts as seen.
        sweep["coverage_swept"] = sweep["coverage"]
        assert swept.top is not None
        sweep.update(unseen_of_cloud(swept.top, obj_pts, sweep["seen_within_mm"]))
        ctx.log("sweep_unseen", unseen_mm2=sweep["unseen_mm2"], top_surface_mm2=sweep["top_surface_mm2"],
                coverage=sweep["coverage"], patches=sweep["unseen_patches"])
    if normals is None or len(normals) != len(obj_pts):
        normals = orient_outward_from_above(obj_pts, cl.estimate_normals(obj_pts, k=16))
    normals = canonical(normals, 6)
    outputs = {"n_points": int(len(obj_pts)), "cloud_sha256": cl.cloud_hash(obj_pts),
               "table_plane": {"normal": canonical(plane[0], 9).tolist(),
                               "offset_mm": float(canonical(np.array([plane[1]]), 6)[0])},
               "robot_s": round(float(robot_s), 3)}
    if plan.cloud.source != "file":
        outputs["sweep"] = sweep
    j.commit_phase("cloud", 0, outputs,
                   {"points_mm": obj_pts.astype(np.float32), "normals": normals.astype(np.float32)})
    swept_facts = {"unseen_mm2": sweep["unseen_mm2"], "coverage": sweep["coverage"]} if plan.cloud.source != "file" else {}
    ctx.log("phase", name="cloud", n_points=int(len(obj_pts)), **swept_facts)
    # Continue from the committed (float32) cloud, exactly as a resumed session will.
    rec = j.phase("cloud", 0)
    assert rec is not None
    ctx.cloud_mm, ctx.cloud_normals = rec.arrays["points_mm"].astype(float), rec.arrays["normals"].astype(float)


TABLE_BAND_MM = 2.0     # points this close to the table plane are table unless the object reaches them
# The foot of the object is chained profile to profile: a little more than the sweep's spacing.
FOOT_LINK_SPACINGS = 1.5


def remove_table_below(points_mm: np.ndarray, seed: int, link_mm: float, max_tries: int = 4
                       ) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
    """The table is the large horizontal plane with the object on it and nothing under it.

    A wide object has big flat faces of its own (the pillow's top can hold as many
    points as the visible table); a plane with many points below it is a face of the
    object, so its points are set aside and the search goes on. Of the points within
    TABLE_BAND_MM of the table, those the object reaches down to stay
    (learning.cloud.standing_on_table, chained ``link_mm`` apart: a little more than
    the sweep's profiles lie apart).
    """

    up = np.array([0.0, 0.0, 1.0])
    rest = points_mm
    for _ in range(max_tries):
        kept, (normal, offset) = cl.remove_table(rest, seed=seed, up=up)
        height = points_mm @ normal - offset
        below = float(np.mean(height < -5.0))
        if below < 0.02:
            return points_mm[cl.standing_on_table(points_mm, height, TABLE_BAND_MM, link_mm)], (normal, offset)
        # A face of the object: drop its inliers and look for a lower plane.
        h_rest = rest @ normal - offset
        rest = rest[np.abs(h_rest) > TABLE_BAND_MM]
        if len(rest) < 100:
            break
    raise SessionAborted("no table plane found under the scanned points")


def orient_outward_from_above(points_mm: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Flip PCA normals of a cloud scanned from above so they point out of the object.

    Orienting away from the centroid fails on flat, wide objects (a point on the
    pillow's top far from the centre would get a sideways reference and half the
    normals point down). The reference here is the horizontal offset from the
    centroid plus an upward component of the object's size: tops face up, sides face
    out.
    """
    c = points_mm.mean(axis=0)
    ref = points_mm - c
    ref[:, 2] = float(np.ptp(points_mm[:, :2], axis=0).max())
    flip = np.einsum("ij,ij->i", normals, ref) < 0
    out = normals.copy()
    out[flip] *= -1.0
    return out


def phase_sampling(ctx: PhaseContext) -> None:
    """Neural gas units -> probe targets (on the surface, away from edges) -> survey steps."""

    j = ctx.journal
    rec = j.phase("sampling", 0)
    if rec is None:
        plan = ctx.inputs.plan
        pts, nrm = ctx.cloud_mm, ctx.cloud_normals
        assert pts is not None and nrm is not None
        if plan.sampling.units > 0:
            curv = cl.curvature(pts, k=16)
            rules = _target_rules(ctx)
            # The units go where targets may: the probe-able part of the cloud (targets.probeable).
            where = tg.probeable(pts, nrm, curv, rules)
            n_units = sd.survey_units(plan.sampling.units, plan.sampling.min_feature_mm, pts[where])
            if np.count_nonzero(where) < n_units:
                where = np.ones(len(pts), bool)
            feats, weights = ng.geometry_aware_inputs(pts[where], nrm[where], curv[where],
                                                      normal_weight_mm=10.0 * plan.sampling.geometry_weight)
            result = ng.train_neural_gas(feats, n_units=n_units,
                                         n_steps=max(200, n_units * plan.sampling.steps_per_unit // 16),
                                         batch_size=256, seed=ctx.seed, sample_weights=weights)
            units = np.asarray(result.units)[:, :3].astype(np.float64)
            ng_qe: float | None = float(result.quantization_error)
            found = tg.make_targets(units, pts, nrm, curv, rules=rules,
                                    reference_dir=np.array(plan.sampling.reference_direction))
            pts_t, nrm_t = np.asarray(found.points_mm).reshape(-1, 3), np.asarray(found.normals).reshape(-1, 3)
            t_dirs = _scan_frames_on_face(ctx, pts_t, nrm_t)
            found_edge = np.asarray(found.edge_flag, bool).reshape(-1)
        else:
            # Explicit targets only: the same points whatever the cloud (config validation
            # insists the plan lists some).
            units = np.zeros((0, 3))
            ng_qe = None
            t_dirs, pts_t, nrm_t = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
            found_edge = np.zeros(0, bool)
        n_found = len(pts_t)
        for k, extra in enumerate(plan.targets):
            n = np.asarray(extra.normal, float) / np.linalg.norm(extra.normal)
            pts_t = np.vstack([pts_t, extra.point_mm])
            nrm_t = np.vstack([nrm_t, n])
            t_dirs = np.vstack([t_dirs, scan_direction(n, np.array(plan.sampling.reference_direction))])
        pts_t, nrm_t, t_dirs = canonical(pts_t, 6), canonical(nrm_t, 9), canonical(t_dirs, 9)
        keep, t_dirs = _reachable(ctx, pts_t, nrm_t, t_dirs, "sampling")
        pts_t, nrm_t, t_dirs = pts_t[keep], nrm_t[keep], t_dirs[keep]
        edge = np.zeros(len(pts_t), bool)
        edge[: int(np.sum(keep[:n_found]))] = found_edge[keep[:n_found]]
        ctx.targets = {i: ProbeTarget(i, pts_t[i], nrm_t[i], t_dirs[i]) for i in range(len(pts_t))}
        sv = plan.phases.survey
        steps = _plan_steps(ctx, _ordered(ctx, list(ctx.targets)), sv.angles_deg, sv.forces_n, 0)
        j.commit_phase("sampling", 0, {"n_units": int(len(units)), "n_targets": int(len(pts_t)),
                                       "dropped_unreachable": int((~keep).sum()), "ng_qe": ng_qe},
                       {"units": units.astype(np.float64), "target_points_mm": pts_t, "target_normals": nrm_t,
                        "target_t": t_dirs, "target_index": np.arange(len(pts_t)), "edge_flag": edge.astype(np.int8)},
                       steps)
        ctx.log("phase", name="sampling", targets=int(len(pts_t)), survey_steps=len(steps))
        rec = j.phase("sampling", 0)
        assert rec is not None
    ctx.targets.update(_targets_from_arrays(rec.arrays))
    # Targets moved off a sharp edge are not characterized (their normal is less sure).
    flags = rec.arrays.get("edge_flag", np.zeros(len(rec.arrays["target_index"]), np.int8))
    ctx.edge_flag.update({int(i): bool(f) for i, f in zip(rec.arrays["target_index"], flags)})


def _target_rules(ctx: PhaseContext) -> Any:
    """The plan's rules for where a target may sit (learning.targets.TargetRules)."""

    plan = ctx.inputs.plan
    radius = ctx.inputs.cell.tool.tip_radius_mm
    return tg.rules_for_plan(radius, plan.sampling.edge_clearance_mm, plan.sampling.max_tilt_deg,
                             plan.sampling.min_feature_mm)


def _scan_frames_on_face(ctx: PhaseContext, pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """Scan directions (N,3) of new targets: the plan's reference direction on each tangent
    plane, turned a quarter turn where that line would leave the face within the survey's
    dent window and the turned one stays on it longer (targets.scan_frames_on_face)."""
    plan = ctx.inputs.plan
    assert ctx.cloud_mm is not None
    return tg.scan_frames_on_face(ctx.cloud_mm, pts, nrm, np.array(plan.sampling.reference_direction),
                                  float(ctx.inputs.cell.tool.tip_radius_mm), plan.model.profile_span_mm / 2.0,
                                  FEATURE_HALF_WINDOW_MM)


def _reachable(ctx: PhaseContext, pts: np.ndarray, nrm: np.ndarray, t_dirs: np.ndarray, what: str
               ) -> tuple[np.ndarray, np.ndarray]:
    """Targets the probe can work at, and their scan directions: (keep (N,), t (N,3)).

    A target is kept when the standoff pose has IK within the joint limits at every planned
    angle, and the contact search at the survey angles touches the object with nothing but
    the probe's tip. A target by the foot of a wall, where the scanner would meet the wall
    on the way down, is dropped here rather than refused at run time (a refused motion is a
    fault in the night's record and a wasted trip). A target whose t was turned off the
    plan's rule at a border (:func:`_scan_frames_on_face`) is never characterized, so it
    needs IK at the survey angles only; one that cannot be worked turned is tried turned
    the other way along the border, then with the rule's t, before it is dropped."""
    plan = ctx.inputs.plan
    survey = sorted(set(plan.phases.survey.angles_deg))
    angles = sorted(set(survey) | set(plan.phases.characterize.angles_deg))
    validator = ctx.executor.validator
    ref = np.array(plan.sampling.reference_direction, dtype=float)
    keep = np.zeros(len(pts), bool)
    chosen = np.array(t_dirs, dtype=float).reshape(-1, 3)
    unreachable = collides = turned = 0
    turn_refused = {"unreachable": 0, "collides": 0}
    for i in range(len(pts)):
        rule_t = canonical(scan_direction(nrm[i], ref), 9)
        # A turned line may run either way along the border: its steps give the regions'
        # survey features only (a dent's peak and width, the same read along -t), and the
        # pose differs (the wrist turned half a turn), which a cell may reach or not.
        options = [chosen[i]] if np.allclose(chosen[i], rule_t) else [chosen[i], -chosen[i], rule_t]
        for k, t in enumerate(options):
            target = ProbeTarget(-1, pts[i], nrm[i], t)
            needed = survey if k < len(options) - 1 else angles     # the last option is the rule's t
            if not validator.reachable_at_all_angles(   # type: ignore[attr-defined]
                    [ctx.executor.contact_search_path(target, a)[0] for a in needed]):
                failed = "unreachable"
            elif len(_clear_angles(ctx, target, survey)) < len(survey):
                failed = "collides"
            else:
                keep[i], chosen[i] = True, t
                break
            if len(options) > 1 and k == 0:
                turn_refused[failed] += 1
        if not keep[i]:
            unreachable += failed == "unreachable"
            collides += failed == "collides"
        elif not np.allclose(chosen[i], rule_t):
            turned += 1
    if unreachable or collides:
        ctx.log("targets_dropped", what=what, unreachable=unreachable, contact_search_collides=collides)
    if turned or any(turn_refused.values()):
        ctx.log("scan_turned_at_border", what=what, targets=turned,
                turn_refused_unreachable=turn_refused["unreachable"], turn_refused_collides=turn_refused["collides"])
    return keep, canonical(chosen, 9)     # -t of a canonical t can hold negative zeros


def _clear_angles(ctx: PhaseContext, target: ProbeTarget, angles: list[float]) -> list[float]:
    """The ``angles`` at which the contact search is free of collisions (the tip may touch)."""
    ex = ctx.executor
    collision = ex.validator.collision   # type: ignore[attr-defined]
    return [a for a in angles if collision(*ex.contact_search_path(target, a), contact_allowed=True) is None]


def survey_profile(depth_mm: np.ndarray, x_mm: np.ndarray, tip_x_mm: float | None, tip_depth_mm: float | None,
                   tip_radius_mm: float, noise_mm: float) -> np.ndarray:
    """A survey step's profile (L,) as the regions phase reads it: all NaN when, by the
    tip's facts, it did not see its dent (:func:`contact.saw_its_dent` over the feature
    window; what it saw is another surface, the table past a low rim); as measured when
    it did or when the facts are unknown (an older journal)."""
    depth = np.asarray(depth_mm, dtype=float)
    if tip_x_mm is None or tip_depth_mm is None:
        return depth
    window = np.abs(np.asarray(x_mm, dtype=float)) <= FEATURE_HALF_WINDOW_MM
    if ct.saw_its_dent(np.asarray(x_mm, dtype=float)[window], depth[window], tip_x_mm, tip_depth_mm,
                       tip_radius_mm, noise_mm):
        return depth
    return np.full_like(depth, np.nan)


def _survey_profiles(ctx: PhaseContext, target_ids: list[int], noise_mm: float
                     ) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Survey profiles (N, F, L) at the first survey angle for targets whose survey is complete;
    all NaN where a profile did not see its dent (``noise_mm``: an averaged profile's standard
    error, see :func:`contact.saw_its_dent`)."""
    j = ctx.journal
    sv = ctx.inputs.plan.phases.survey
    angle = sv.angles_deg[0]
    forces = sorted(sv.forces_n)
    tip_radius_mm = ctx.inputs.cell.tool.tip_radius_mm
    by_target: dict[int, dict[float, np.ndarray]] = {}
    for rec in _done_steps(j, SURVEY_PHASES):
        if abs(rec.plan.angle_deg - angle) > 1e-9 or rec.plan.target_index not in target_ids:
            continue
        res = j.step_result(rec.step_id)
        facts = res.summary or {}
        tip_x, tip_depth = facts.get("tip_x_mm"), facts.get("tip_depth_mm")
        depth = survey_profile(np.asarray(res.profile_depth_mm, dtype=float), ctx.grid.x_mm,
                               None if tip_x is None else float(tip_x),
                               None if tip_depth is None else float(tip_depth), tip_radius_mm, noise_mm)
        by_target.setdefault(rec.plan.target_index, {})[rec.plan.force_n] = depth
    ids = [i for i in target_ids if i in by_target and all(f in by_target[i] for f in forces)]
    depth = np.array([[by_target[i][f] for f in forces] for i in ids]) if ids else np.zeros((0, len(forces), 0))
    return ids, depth, np.array(forces)


def phase_regions(ctx: PhaseContext, round_: int) -> None:
    """Cluster the surveyed targets into regions; plan characterization where a region lacks it."""

    j = ctx.journal
    rec = j.phase("regions", round_)
    if rec is None:
        noise_mm = measured_noise_mm(ctx)
        ids, depth, forces = _survey_profiles(ctx, sorted(ctx.targets), noise_mm)
        if len(ids) == 0:
            raise SessionAborted("no surveyed target has a complete survey: cannot find regions")
        # Features from the dent itself: the grid's ends see the object's edges and
        # the table, which say nothing about the material under the tip.
        window = np.abs(ctx.grid.x_mm) <= FEATURE_HALF_WINDOW_MM
        feats, names = rg.survey_features(depth[:, :, window], ctx.grid.x_mm[window], forces)
        # Regions of similar ELASTICITY: peak depths and compliance. The dent's width
        # also follows the local geometry (a pillow's rounded rim), which is not material.
        elastic = [k for k, name in enumerate(names) if not name.startswith("width")]
        feats, names = feats[:, elastic], [names[k] for k in elastic]
        # A target the scanner never saw (e.g. in the box's shadow) has no features:
        # leave it out of the clustering instead of filling it with the mean, which
        # makes a spurious region of its own.
        seen = np.all(np.isfinite(feats), axis=1)
        if not seen.all():
            ctx.log("targets_unseen", round=round_, targets=[int(i) for i, ok in zip(ids, seen) if not ok])
        ids = [i for i, ok in zip(ids, seen) if ok]
        depth, feats = depth[seen], feats[seen]
        if len(ids) == 0:
            raise SessionAborted("the scanner saw none of the surveyed targets: cannot find regions")
        pts = np.array([ctx.targets[i].point_mm for i in ids])
        # Neighbours along the scanned surface (cells on the cloud), never across a fold.
        edges = ctx.surface_neighbours(pts)
        # The previous round's regions, so a material separated then is not lost now that
        # more points have arrived (regions.cluster_regions, previous_labels).
        before = j.phase("regions", round_ - 1) if round_ > 0 else None
        known = (dict(zip(before.arrays["labelled_targets"].tolist(), before.arrays["labels"].tolist()))
                 if before is not None else {})
        previous = np.array([known.get(i, -1) for i in ids], dtype=np.int64)
        # The error of each point's peak, read where its dent has faded (the far field of
        # its profile at the smallest survey force), so the contrast rule knows which dents
        # are measured (regions.peak_noise_mm).
        far = prof.far_field_error_mm(depth[:, 0, :], ctx.grid.x_mm, FEATURE_HALF_WINDOW_MM)
        rmap = rg.cluster_regions(feats, edges, names, seed=ctx.seed,
                                  min_contrast=ctx.inputs.plan.phases.survey.min_contrast,
                                  noise_mm=noise_mm, previous_labels=previous,
                                  far_field_mm=far)
        labels = {i: int(l) for i, l in zip(ids, rmap.labels)}
        chosen, angles_by_target = _characterize_choice(ctx, labels, rmap.n_regions, pts, ids)
        ch = ctx.inputs.plan.phases.characterize
        steps = _plan_steps(ctx, _ordered(ctx, chosen), ch.angles_deg, ch.forces_n, _next_order(ctx),
                            angles_by_target) if chosen else []
        j.commit_phase("regions", round_, {"n_regions": int(rmap.n_regions), "feature_names": names,
                                           "stats": rg._jsonable(rmap.stats), "characterize_targets": chosen},
                       {"labelled_targets": np.array(ids, dtype=np.int64), "labels": rmap.labels.astype(np.int64),
                        "features": feats, "far_field_mm": far}, steps)
        ctx.log("phase", name="regions", round=round_, n_regions=int(rmap.n_regions), characterize=chosen)
        rec = j.phase("regions", round_)
        assert rec is not None
    ids = rec.arrays["labelled_targets"]
    ctx.labels = {int(i): int(l) for i, l in zip(ids, rec.arrays["labels"])}
    ctx.n_regions = int(rec.outputs["n_regions"])


def _characterize_choice(ctx: PhaseContext, labels: dict[int, int], n_regions: int, pts: np.ndarray,
                         ids: list[int]) -> tuple[list[int], dict[int, list[float]]]:
    """Up to points_per_region interior targets per region that has fewer characterized
    points, and the angles each is characterized at.

    A target qualifies when the contact search is clear at every interior angle of the
    plan (geometry.INTERIOR_ANGLES_DEG); at a grazing angle a flat surface wider than the
    tool meets the F/T sensor or flange, and that angle is left out for that target
    (logged) instead of being refused at run time.
    """
    j = ctx.journal
    per = ctx.inputs.plan.phases.characterize.points_per_region
    angles = list(ctx.inputs.plan.phases.characterize.angles_deg)
    lo, hi = INTERIOR_ANGLES_DEG
    interior_angles = [a for a in angles if lo <= a <= hi]
    reference = np.array(ctx.inputs.plan.sampling.reference_direction, dtype=float)
    clear_at: dict[int, list[float]] = {}
    already = {r.plan.target_index for r in j.steps(phase=CHARACTERIZE)}
    lab = np.array([labels[i] for i in ids])
    chosen: list[int] = []
    for region in range(n_regions):
        have = sum(1 for t in already if labels.get(t) == region)
        need = per - have
        if need <= 0:
            continue
        members = np.flatnonzero(lab == region)
        others = np.flatnonzero(lab != region)
        # A target whose line was turned at a border is not characterized: its angles would
        # be measured from another tangent than the region model's (docs/design.md §3).
        cand = [k for k in members if ids[k] not in already and not ctx.edge_flag.get(ids[k], False)
                and follows_scan_rule(ctx.targets[ids[k]].normal, ctx.targets[ids[k]].t, reference)]
        if not cand:
            continue
        # Interior first: far from every target of another region, then spread apart.
        if len(others):
            interior = np.array([np.min(np.linalg.norm(pts[others] - pts[k], axis=1)) for k in cand])
        else:
            centre = pts[members].mean(axis=0)
            interior = -np.array([np.linalg.norm(pts[k] - centre) for k in cand])
        picked: list[int] = []
        for k in [cand[i] for i in np.argsort(-interior)]:
            if not all(np.linalg.norm(pts[k] - pts[p]) > 20.0 for p in picked):
                continue
            clear = _clear_angles(ctx, ctx.targets[ids[k]], angles)
            if clear and all(a in clear for a in interior_angles):
                picked.append(k)
                clear_at[ids[k]] = clear
            if len(picked) == need:
                break
        chosen += [ids[k] for k in picked]
    blocked = {str(t): [a for a in angles if a not in clear] for t, clear in clear_at.items()}
    if any(blocked.values()):
        ctx.log("angles_blocked", targets={t: b for t, b in blocked.items() if b})
    return chosen, clear_at


@dataclass(frozen=True)
class ScanGeometry:
    """How the controller maps a step's stored scans to its profile (to re-measure old steps)."""

    grid: prof.ProfileGrid
    tcp_to_scanner: Any
    base_to_object: Any
    tip_radius_mm: float
    reference_dir: tuple[float, float, float]


def scan_geometry(inputs: Any, tcp_to_scanner: Any, base_to_object: Any) -> ScanGeometry:
    """The scan geometry of a session's inputs with the scanner mount and the object's
    placement given (a live cell's, or the journal's word: :func:`registered_placement`)."""
    return ScanGeometry(plan_grid(inputs), tcp_to_scanner, base_to_object, inputs.cell.tool.tip_radius_mm,
                        tuple(inputs.plan.sampling.reference_direction))


def registered_placement(j: Any) -> Pose | None:
    """Where the object was last registered (after it moved), as the journal records it;
    None when it never was."""
    events = j.events(kind="object_registered")
    return Pose.from_list(events[-1]["record"]["base_to_object"]) if events else None


def placement_at(registrations: list[dict[str, Any]], started_utc: str | None, current: Pose) -> Pose:
    """Where the object was believed to be when a step started: the last registration
    (``object_registered`` events, oldest first) at or before ``started_utc``; before the
    first one, the placement that one replaced. ``current`` when it never moved (or the
    step has no start time). A step's stored scans are base-frame poses: measured again
    with a later placement, they fall beside the target (the object moved since)."""
    if not registrations or started_utc is None:
        return current
    started = _dt.datetime.fromisoformat(started_utc)
    placed = Pose.from_list(registrations[0]["record"]["previous"])
    for event in registrations:
        if _dt.datetime.fromisoformat(event["t_wall_utc"]) > started:
            break
        placed = Pose.from_list(event["record"]["base_to_object"])
    return placed


def session_geometry(ctx: PhaseContext) -> ScanGeometry:
    """The scan geometry of the running session (the cell's placement of the object now)."""
    return scan_geometry(ctx.inputs, ctx.cell.tcp_to_scanner, ctx.cell.base_to_object)


def region_dataset(ctx: PhaseContext, region: int) -> RegionSteps:
    """Every done step at targets of ``region`` (see :func:`collect_region_steps`)."""
    return collect_region_steps(ctx.journal, ctx.labels, region, session_geometry(ctx))


def collect_region_steps(j: Any, labels: dict[int, int], region: int, geometry: ScanGeometry) -> RegionSteps:
    """The done steps at targets labelled ``region``: measured |F|, planned level, angle,
    averaged profile, point, the tip's position and depth, and the reference surface.

    The tip facts are the ones recorded when the step was measured; a step recorded
    before they were (an older journal) is measured again from its stored scans and
    poses, profile included. The reference surface is always taken from the stored
    reference scans (with ``geometry``'s placement of the object). A journal without
    reference poses keeps its stored profiles and has no tip facts. Steps whose line was
    turned at a border (docs/design.md §3) are left out: their angles are measured from
    another tangent, and by a rim the dent is not the same along it as across it (a
    plate's bowl, a layer's edge), so they feed the regions' features only.
    """
    rows: list[tuple[float, float, float, np.ndarray, int, float, float, np.ndarray]] = []
    for r in j.steps(statuses=["done"]):
        if labels.get(r.plan.target_index) != region:
            continue
        if not follows_scan_rule(np.asarray(r.plan.normal), np.asarray(r.plan.t), np.asarray(geometry.reference_dir)):
            continue
        res = j.step_result(r.step_id)
        target = ProbeTarget(r.plan.target_index, np.asarray(r.plan.point_mm), np.asarray(r.plan.normal),
                             np.asarray(r.plan.t))
        facts = res.summary or {}
        depth = np.asarray(res.profile_depth_mm, dtype=float)
        tip_x, tip_depth = facts.get("tip_x_mm"), facts.get("tip_depth_mm")
        ref_h = np.full(geometry.grid.samples, np.nan)
        if res.reference_pose is not None and "tip_depth_mm" in facts:
            refs = prof.step_scan_points(res.reference_xz_mm, res.reference_pose, geometry.tcp_to_scanner,
                                         geometry.base_to_object)
            ref_h = prof.reference_height(refs, target.point_mm, target.normal, target.t, geometry.grid)
        elif res.reference_pose is not None:
            m = measure_step_arrays(res.scans_xz_mm, res.scan_pose, res.reference_xz_mm, res.reference_pose, target,
                                    geometry.grid, geometry.tcp_to_scanner, geometry.base_to_object,
                                    geometry.tip_radius_mm)
            depth, tip_x, tip_depth, ref_h = m.depth_mm, m.tip_x_mm, m.tip_depth_mm, m.reference_h_mm
        rows.append((float(np.linalg.norm(np.nanmean(res.scan_force_n, axis=0))), float(r.plan.force_n),
                     float(r.plan.angle_deg), depth, int(r.plan.target_index),
                     np.nan if tip_x is None else float(tip_x), np.nan if tip_depth is None else float(tip_depth),
                     ref_h))
    length = geometry.grid.samples
    if not rows:
        empty = np.zeros(0)
        return RegionSteps(geometry.grid.x_mm, empty, empty, empty, np.zeros((0, length)), np.zeros(0, np.int64),
                           empty, empty, np.zeros((0, length)))
    f, lvl, a, d, pid, tx, td, rh = zip(*rows)
    return RegionSteps(geometry.grid.x_mm, np.array(f), np.array(lvl), np.array(a), np.array(d),
                       np.array(pid, dtype=np.int64), np.array(tx), np.array(td), np.array(rh))


def region_noise_mm(completed: CompletedTargets, measured_mm: float) -> float:
    """The error of one of the region's averaged profiles (mm): the larger of the scans'
    own standard error and what two measurements that must agree differ by (the mirror
    test's yardstick, per measurement)."""
    yard = completed.mirror.yardstick_mm
    return float(max(measured_mm, (yard / np.sqrt(2.0)) if yard is not None else 0.0))


def fit_region(steps: RegionSteps, config: TrainConfig, tip_radius_mm: float, measured_noise: float
               ) -> tuple[RegionModel, dict[str, Any]]:
    """Complete the region's targets, fit its model and set what it may serve.

    The served depth is bounded by the deepest supported training value (the tip's own
    indentation under a normal push, or the deepest measured sample) and by the highest
    one (or the undeformed surface), each widened by three times the region's noise;
    queries are accepted over the trained force levels and angles.
    """
    completed = complete_targets(steps, tip_radius_mm)
    noise = region_noise_mm(completed, measured_noise)
    weights = SUPPORT_WEIGHTS[completed.support]
    model = fit_region_model(steps.force_n, steps.angle_deg, completed.depth_mm, steps.x_mm,
                             point_ids=steps.point_ids, config=config, noise_mm=noise, sample_weight=weights)
    supported = completed.support != UNSUPPORTED
    values = completed.depth_mm[supported] if supported.any() else completed.depth_mm.ravel()
    forces, angles, codes = support_table(steps.force_level_n, steps.angle_deg, completed.support)
    all_forces = np.concatenate([steps.force_n, steps.force_level_n])
    limits = ServingLimits((float(all_forces.min()), float(all_forces.max())),
                           (float(steps.angle_deg.min()), float(steps.angle_deg.max())),
                           float(min(0.0, values.min()) - 3.0 * noise), float(values.max() + 3.0 * noise),
                           forces, angles, codes)
    info = {"support": completed.counts, "mirror": completed.mirror.to_dict(), "noise_mm": round(noise, 6),
            "tail_exponent": round(completed.tail_exponent, 4),
            "depth_bounds_mm": [round(limits.depth_min_mm, 6), round(limits.depth_max_mm, 6)],
            "force_range_n": list(limits.force_range_n), "angle_range_deg": list(limits.angle_range_deg)}
    model.meta.update({"support": info})
    return model.with_limits(limits), info


def region_train_config(model_spec: Any, seed: int, region: int, tip_radius_mm: float) -> TrainConfig:
    """How the session trains a region's model: the plan's network and ensemble, its epoch
    cap, a seed per session and region, and spline outputs with knots a fifth of the tip
    radius apart (a spherical tip's dent has no feature finer than its contact, and a cubic
    spline at that spacing follows the simulator's dents of the shipped objects to 0.002 mm
    RMS)."""
    return TrainConfig(hidden_units=model_spec.hidden_units, ensemble=model_spec.ensemble - 1,
                       epochs_per_stage=max(10, model_spec.max_epochs // 5), seed=seed * 1000 + region,
                       basis_spacing_mm=tip_radius_mm / 5.0)


def phase_models(ctx: PhaseContext, round_: int) -> Plan:
    """Fit (or load) one model ensemble per region; files written atomically, hashes committed."""
    j = ctx.journal
    rec = j.phase("models", round_)
    model_dir = ctx.session_dir / "models" / f"round{round_}"
    if rec is None:
        yield Lifecycle("learn")
        m = ctx.inputs.plan.model
        model_dir.mkdir(parents=True, exist_ok=True)
        outputs: dict[str, Any] = {"regions": {}}
        noise = measured_noise_mm(ctx)
        outputs["noise_mm"] = noise
        for region in range(ctx.n_regions):
            data = region_dataset(ctx, region)
            if len(data) < 3:
                outputs["regions"][str(region)] = {"skipped": f"only {len(data)} profiles"}
                continue
            radius = ctx.inputs.cell.tool.tip_radius_mm
            model, info = fit_region(data, region_train_config(m, ctx.seed, region, radius), radius, noise)
            crash_point("models:before_save")
            path = model.save(model_dir / f"region{region}.npz")
            crash_point("models:after_save")
            digest = j.record_model(region, 0, path, {"round": round_, "n_profiles": int(len(data))})
            outputs["regions"][str(region)] = {"path": str(Path(path).relative_to(ctx.session_dir)), "sha256": digest,
                                               "model_hash": model.model_hash(),
                                               "n_profiles": int(len(data)), **info}
        crash_point("models:before_commit")
        j.commit_phase("models", round_, outputs)
        ctx.log("phase", name="models", round=round_, regions=list(outputs["regions"]))
        yield Lifecycle("plan")
        rec = j.phase("models", round_)
        assert rec is not None
    ctx.models = {}
    for region, info in rec.outputs["regions"].items():
        if "path" in info:
            ctx.models[int(region)] = RegionModel.load(ctx.session_dir / info["path"])
    ctx.model_round = round_


def phase_densify(ctx: PhaseContext, round_: int) -> bool:
    """Add survey targets where adjacent regions differ (their models or their survey dents)
    and around survey points their region explains badly; False when resolved or out of budget."""

    j = ctx.journal
    rec = j.phase("densify", round_)
    if rec is None:
        plan = ctx.inputs.plan
        dp = plan.phases.densify
        ids = sorted(ctx.labels)
        pts = np.array([ctx.targets[i].point_mm for i in ids])
        labels = np.array([ctx.labels[i] for i in ids])
        edges = ctx.surface_neighbours(pts).reshape(-1, 2)
        sv = plan.phases.survey
        grid_forces = np.array(sv.forces_n, dtype=float)
        noise = measured_noise_mm(ctx)
        border = sm.shared_border(ctx.surface(), sm.cells(ctx.surface(), pts), edges)
        # The survey's own evidence beside the models': every labelled point's dent, how far
        # apart the regions' dents lie, and which points their region explains badly.
        found = _region_features(ctx, ids)
        assert found is not None
        curv = cl.curvature(ctx.cloud_mm, k=16)
        radius = ctx.inputs.cell.tool.tip_radius_mm
        survey_ok, band_ok = tg.probeable_and_rim_band(
            ctx.cloud_mm, ctx.cloud_normals, curv, _target_rules(ctx),
            radius if dp.rim_clearance_mm is None else dp.rim_clearance_mm)
        # New points snap to where a target may go: the survey's surface, or the rim band
        # beyond it that a seam running out toward the rim is followed into.
        surface = ctx.cloud_mm[survey_ok | band_ok]
        rnd = dn.plan_round(round_, pts, np.asarray(edges).reshape(-1, 2), labels, ctx.models,
                            forces_n=grid_forces, angles_deg=np.array(sv.angles_deg, dtype=float),
                            noise_mm=noise, budget=dp.points_per_round,
                            min_spacing_mm=dp.min_spacing_mm, resolution_mm=dp.resolution_mm,
                            surface_points_mm=surface if len(surface) else ctx.cloud_mm,
                            border=border, band_points_mm=ctx.cloud_mm[band_ok],
                            survey_area_mm=ctx.cloud_mm[survey_ok],
                            **dn.survey_evidence(found[0], found[1], labels, noise, sv.min_contrast,
                                                 far_field_mm=found[2]))
        new_pts = canonical(np.asarray(rnd.proposed_mm, dtype=float).reshape(-1, 3), 6)
        new_nrm = canonical(_cloud_normals_at(ctx, new_pts), 9)
        first = max(ctx.targets) + 1 if ctx.targets else 0
        t_dirs = canonical(_scan_frames_on_face(ctx, new_pts, new_nrm), 9) if len(new_pts) else np.zeros((0, 3))
        keep, t_dirs = _reachable(ctx, new_pts, new_nrm, t_dirs, f"densify[{round_}]") if len(new_pts) \
            else (np.zeros(0, bool), t_dirs)
        new_pts, new_nrm, t_dirs = new_pts[keep], new_nrm[keep], t_dirs[keep]
        idx = np.arange(first, first + len(new_pts))
        for k, i in enumerate(idx):
            ctx.targets[int(i)] = ProbeTarget(int(i), new_pts[k], new_nrm[k], t_dirs[k])
        sv = plan.phases.survey
        steps = _plan_steps(ctx, _ordered(ctx, [int(i) for i in idx]), sv.angles_deg, sv.forces_n,
                            _next_order(ctx)) if len(idx) else []
        j.commit_phase("densify", round_, {"resolved": bool(rnd.resolved), "reason": rnd.reason,
                                           "n_new": int(len(idx)), "record": rnd.to_dict()},
                       {"target_points_mm": new_pts.reshape(-1, 3), "target_normals": new_nrm.reshape(-1, 3),
                        "target_t": t_dirs.reshape(-1, 3), "target_index": idx.astype(np.int64)}, steps)
        ctx.log("phase", name="densify", round=round_, new_targets=int(len(idx)), reason=rnd.reason)
        rec = j.phase("densify", round_)
        assert rec is not None
    if len(rec.arrays["target_index"]):
        ctx.targets.update(_targets_from_arrays(rec.arrays))
    return int(rec.outputs["n_new"]) > 0


def _region_features(ctx: PhaseContext, ids: list[int]
                     ) -> tuple[np.ndarray, list[str], np.ndarray | None] | None:
    """Survey features (len(ids), D), their names, and what each target's survey profile read
    far from its contact (len(ids), 2; profiles.far_field_error_mm; None in a journal written
    before the regions round recorded them), from the latest regions round (None when there
    is none, or it did not label every one of ``ids``)."""
    _, rec = newest_phase(ctx.journal, "regions")
    if rec is None:
        return None
    row = {int(t): k for k, t in enumerate(rec.arrays["labelled_targets"])}
    if any(i not in row for i in ids):
        return None
    rows = [row[i] for i in ids]
    far = rec.arrays["far_field_mm"][rows] if "far_field_mm" in rec.arrays else None
    return rec.arrays["features"][rows], list(rec.outputs["feature_names"]), far


def _seam_evidence(ctx: PhaseContext, ids: list[int]) -> dict[str, np.ndarray | None]:
    """The final map's keyword arguments from the labelled targets' survey features (None
    each without a regions round): ``seed_levels``, each target's mean peak depth in mm
    over the survey forces (regions.mean_peak_mm), ``seed_peaks_mm``, its peak depth at each
    survey force (regions.peaks_mm: a target may stand across the seam from its label only
    when every force says so, and goes with its neighbours' region when the forces
    disagree), and ``dent_not_read``, True where its
    peak fell as the survey force rose (regions.dent_falls_with_force). That rule's noise is
    the scans' standard error: one set of reference scans serves every force level of a
    probe (probe.py), so its error, most of one peak's scatter among probes, is the same at
    every force and leaves the slope alone."""

    found = _region_features(ctx, ids)
    if found is None:
        return {"seed_levels": None, "dent_not_read": None, "seed_peaks_mm": None}
    return {"seed_levels": rg.mean_peak_mm(found[0], found[1]),
            "dent_not_read": rg.dent_falls_with_force(found[0], found[1], measured_noise_mm(ctx)),
            "seed_peaks_mm": rg.peaks_mm(found[0], found[1])}


def _cloud_normals_at(ctx: PhaseContext, points_mm: np.ndarray) -> np.ndarray:
    """Outward normals of the cloud at (the nearest cloud point to) each point."""
    if len(points_mm) == 0:
        return np.zeros((0, 3))
    assert ctx.cloud_mm is not None and ctx.cloud_normals is not None
    _, idx = cKDTree(ctx.cloud_mm).query(points_mm)
    return ctx.cloud_normals[idx]


def measured_noise_mm(ctx: PhaseContext, max_steps: int = 20) -> float:
    """Standard error (mm) of averaged survey profiles, from the scans themselves."""

    j, cell = ctx.journal, ctx.cell
    stds, counts = [], []
    registrations = j.events(kind="object_registered")
    for rec in _done_steps(j, SURVEY_PHASES)[:max_steps]:
        res = j.step_result(rec.step_id)
        tgt = ctx.targets[rec.plan.target_index]
        # With the placement of its time: the first steps were measured before any move.
        placed = placement_at(registrations, rec.started_utc, cell.base_to_object)
        scans = prof.step_scan_points(res.scans_xz_mm, res.scan_pose, cell.tcp_to_scanner, placed)
        refs = prof.step_scan_points(res.reference_xz_mm, res.reference_pose, cell.tcp_to_scanner, placed)
        _, count, std = prof.average_profiles(prof.scan_depths(scans, tgt.point_mm, tgt.normal, tgt.t,
                                                                ctx.grid, refs))
        stds.append(std)
        counts.append(count)
    return averaged_noise_mm(np.array(stds), np.array(counts))


def phase_final(ctx: PhaseContext) -> None:
    """The region map over the whole cloud, and the report."""

    j = ctx.journal
    rec = j.phase("final", 0)
    if rec is None:
        ids = sorted(ctx.labels)
        pts = np.array([ctx.targets[i].point_mm for i in ids])
        # Each cloud point: the region of the nearest labelled target along the surface,
        # parts split at concave folds, the seam drawn through targets whose dent lies
        # between two regions (learning/surface_map.py).
        cloud_labels = sm.labels_from_seeds(ctx.surface(), pts, np.array([ctx.labels[i] for i in ids]),
                                            **_seam_evidence(ctx, ids))
        j.commit_phase("final", 0, {"n_regions": ctx.n_regions, "model_round": ctx.model_round,
                                    "robot_hours": j.robot_time_s()["total"] / 3600.0},
                       {"cloud_labels": cloud_labels.astype(np.int64)})
    crash_point("final:before_report")
    crash_point("report:begin")
    write_report(ctx.session_dir)
    crash_point("final:after_report")


def run_all(ctx: PhaseContext) -> Plan:
    """The session's plan: cloud, sampling and its survey, regions and characterization,
    models, densify rounds, the final map. With the budget spent (thrown in by the engine at
    a round of steps), it models what was measured and ends with the map."""
    plan = ctx.inputs.plan
    yield from phase_cloud(ctx)
    yield Lifecycle("plan")
    phase_sampling(ctx)
    try:
        yield ProbeRound("sampling", 0, ctx.targets)
        phase_regions(ctx, 0)
        yield ProbeRound(CHARACTERIZE, 0, ctx.targets)
        yield from phase_models(ctx, 0)
        for r in range(1, plan.phases.densify.rounds + 1):
            if not phase_densify(ctx, r):
                break
            yield ProbeRound("densify", r, ctx.targets)
            phase_regions(ctx, r)
            yield ProbeRound(CHARACTERIZE, r, ctx.targets)
            yield from phase_models(ctx, r)
    except BudgetSpent as exc:
        ctx.log("budget_spent", reason=str(exc))
        yield from _wrap_up_after_budget(ctx)
    yield Lifecycle("learn")
    phase_final(ctx)


def _wrap_up_after_budget(ctx: PhaseContext) -> Plan:
    """With the budget spent, model what was measured: regions and models from the data at hand."""
    j = ctx.journal
    r = max(newest_phase(j, "regions")[0], 0)   # none yet: cluster the survey as round 0
    phase_regions(ctx, r)
    m = r
    while j.phase("models", m) is not None:
        m += 1
    yield from phase_models(ctx, m)
