"""A small synthetic session written through the Journal API, for the report, export and
notify tests (not collected by pytest: the name does not start with ``test_``).

The object is a flat 120 x 60 mm patch with two materials split at x = 60 mm: region 0
(x < 60) is soft, region 1 stiff. Profiles follow a closed form (Gaussian dent whose
depth grows as F^(2/3) and whose centre shifts with cos(angle)), so the trained models
have something real to fit. ``build_session(dir, upto=...)`` stops after any stage, to
make partial sessions like those a running controller leaves behind.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from elastoprobe.controller.journal import Journal, SessionMeta, StepPlan, StepResult
from elastoprobe.controller.learning.models import TrainConfig, fit_region_model
from elastoprobe.controller.provenance import collect_provenance

STAGES = ("created", "cloud", "sampling", "survey", "regions", "characterize", "models", "densify", "final")
X_MM = np.linspace(-20.0, 20.0, 64)
SURVEY_FORCES_N = (2.0, 5.0)
CHAR_FORCES_N = (1.0, 3.0, 6.0)
CHAR_ANGLES_DEG = (60.0, 90.0, 120.0)
SOFTNESS_MM = (1.2, 0.4)            # depth scale per region (mm at 1 N)
PLAN_TEXT = "name: synthetic\nseed: 11\n"
CELL_TEXT = "name: synthetic-cell\nkind: simulated\n"


def true_region(point_mm: np.ndarray) -> int:
    return 0 if float(point_mm[0]) < 60.0 else 1


def true_depth_mm(region: int, force_n: float, angle_deg: float, x_mm: np.ndarray = X_MM) -> np.ndarray:
    """Noise-free dent depth (mm, along -n) on the grid ``x_mm``."""
    amp = SOFTNESS_MM[region] * force_n ** (2.0 / 3.0) * np.sin(np.radians(angle_deg)) ** 0.5
    shift = 3.0 * np.cos(np.radians(angle_deg))
    return amp * np.exp(-((x_mm - shift) / 6.0) ** 2)


def _cloud(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    xy = rng.uniform([0.0, 0.0], [120.0, 60.0], size=(3000, 2))
    z = 0.02 * np.sin(xy[:, 0] / 15.0)
    pts = np.column_stack([xy, z])
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


def _targets(first_index: int, xy: np.ndarray) -> dict[str, np.ndarray]:
    n = len(xy)
    return {"target_points_mm": np.column_stack([xy, np.zeros(n)]),
            "target_normals": np.tile([0.0, 0.0, 1.0], (n, 1)),
            "target_t": np.tile([1.0, 0.0, 0.0], (n, 1)),
            "target_index": np.arange(first_index, first_index + n, dtype=np.int64)}


def _plans(j: Journal, arrays: dict[str, np.ndarray], ids: list[int], angles: tuple[float, ...],
           forces: tuple[float, ...]) -> list[StepPlan]:
    step_id = j.next_step_id()
    recs = j.steps()
    order = (max(r.plan.order_index for r in recs) + 1) if recs else 0
    index = {int(i): k for k, i in enumerate(arrays["target_index"])}
    out = []
    for ti in ids:
        k = index[ti]
        for a in angles:
            for f in forces:
                out.append(StepPlan(step_id, ti, arrays["target_points_mm"][k], arrays["target_normals"][k],
                                    arrays["target_t"][k], a, f, order))
                step_id += 1
                order += 1
    return out


def _result(rng: np.random.Generator, plan: StepPlan) -> StepResult:
    region = true_region(plan.point_mm)
    truth = true_depth_mm(region, plan.force_n, plan.angle_deg)
    n_scans = 4
    depth = truth + rng.normal(0.0, 0.01, size=(n_scans, X_MM.size))
    scans = np.stack([np.column_stack([X_MM, -d]) for d in depth]).astype(np.float32)
    scans[0, :3, :] = np.nan                                     # a few missing samples, as in the shadow
    profile = np.nanmean(depth, axis=0)
    profile[:2] = np.nan
    a = np.radians(plan.angle_deg)
    direction = np.array([np.cos(a), 0.0, -np.sin(a)])
    force = rng.normal(plan.force_n, 0.02, size=(n_scans, 1)) * direction
    pose = np.column_stack([np.tile(plan.point_mm, (n_scans, 1)) + [0, 0, 150.0], np.tile([np.pi, 0, 0], (n_scans, 1))])
    ref = np.stack([np.column_stack([X_MM, rng.normal(0, 0.01, X_MM.size)]) for _ in range(2)]).astype(np.float32)
    return StepResult(scans_xz_mm=scans, scan_force_n=force, scan_pose=pose, profile_depth_mm=profile,
                      force_direction=direction, reference_xz_mm=ref, scan_t_s=np.arange(n_scans) * 0.1,
                      reference_pose=pose[:2].copy(), profile_x_mm=X_MM.copy(), robot_time_s=4.0 + plan.force_n,
                      summary={"force_target_n": plan.force_n, "angle_deg": plan.angle_deg,
                               "force_measured_n": float(np.linalg.norm(force.mean(axis=0))), "n_scans": n_scans})


def _raw_ft(rng: np.random.Generator, t0_s: float, spike_n: float) -> np.ndarray:
    t = t0_s + np.arange(500) * 0.001
    f = np.column_stack([rng.normal(0, 0.05, 500), rng.normal(0, 0.05, 500), -3.0 + rng.normal(0, 0.05, 500)])
    f[450:, 2] -= spike_n
    torque = rng.normal(0, 0.002, (500, 3))
    return np.column_stack([t, f, torque])


class _Clock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def advance(self, dt_s: float) -> float:
        self.t_s += dt_s
        return self.t_s


def _run_steps(j: Journal, rng: np.random.Generator, clock: _Clock, phase: str, round_: int,
               fail_first: bool = False) -> None:
    for k, rec in enumerate(j.pending_steps(phase=phase, round=round_)):
        attempt = j.begin_step(rec.step_id)
        j.record_transition("planning", "moving_to_standoff", "go_to_target", clock.advance(2.0), rec.step_id)
        j.record_transition("moving_to_standoff", "ramping", "contact", clock.advance(1.0), rec.step_id)
        if fail_first and k == 1:
            t = clock.advance(0.5)
            fid = j.record_fault("force_spike", f"|F| rose 25 N above target at step {rec.step_id}", t,
                                 rec.step_id, "retry", _raw_ft(rng, t - 0.5, 25.0))
            j.record_transition("ramping", "fault", "fault", t, rec.step_id)
            j.record_transition("fault", "recovering", "recover", clock.advance(1.0), rec.step_id)
            j.fail_step(rec.step_id, attempt, "force spike", fid)
            j.record_transition("recovering", "moving_to_standoff", "go_to_target", clock.advance(3.0), rec.step_id)
            attempt = j.begin_step(rec.step_id)
        j.commit_step(rec.step_id, attempt, _result(rng, rec.plan))
        j.record_transition("ramping", "retracting", "retract", clock.advance(4.0), rec.step_id)
        j.record_transition("retracting", "planning", "plan", clock.advance(1.0), None)


def _labels_for(j: Journal, target_arrays: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    ids, labels = [], []
    for arrays in target_arrays:
        for i, p in zip(arrays["target_index"], arrays["target_points_mm"]):
            ids.append(int(i))
            labels.append(true_region(p))
    return np.array(ids, dtype=np.int64), np.array(labels, dtype=np.int64)


def _fit_models(j: Journal, session_dir: Path, round_: int, labels: dict[int, int]) -> None:
    outputs: dict[str, dict] = {"regions": {}}
    for region in (0, 1):
        force, angle, depth, pids = [], [], [], []
        for rec in j.steps(statuses=["done"]):
            if labels.get(rec.plan.target_index) != region:
                continue
            res = j.step_result(rec.step_id)
            force.append(float(np.linalg.norm(res.scan_force_n.mean(axis=0))))
            angle.append(rec.plan.angle_deg)
            depth.append(res.profile_depth_mm)
            pids.append(rec.plan.target_index)
        cfg = TrainConfig(ensemble=2, stages=1, epochs_per_stage=200, seed=region)
        (session_dir / "models" / f"round{round_}").mkdir(parents=True, exist_ok=True)
        model = fit_region_model(np.array(force), np.array(angle), np.array(depth), X_MM,
                                 point_ids=np.array(pids), config=cfg)
        path = model.save(session_dir / "models" / f"round{round_}" / f"region{region}.npz")
        digest = j.record_model(region, 0, path, {"round": round_, "n_profiles": len(force)})
        outputs["regions"][str(region)] = {"path": str(path.relative_to(session_dir)), "sha256": digest,
                                           "model_hash": model.model_hash(), "n_profiles": len(force)}
    j.commit_phase("models", round_, outputs)


def build_session(session_dir: Path, upto: str = "final", seed: int = 11) -> Path:
    """Write a synthetic session into ``session_dir`` up to and including stage ``upto``."""
    if upto not in STAGES:
        raise ValueError(f"upto must be one of {STAGES}")
    stop = STAGES.index(upto)
    rng = np.random.default_rng(seed)
    clock = _Clock()
    session_dir.mkdir(parents=True, exist_ok=True)
    inputs = session_dir.parent / f"{session_dir.name}-inputs"
    inputs.mkdir(exist_ok=True)
    (inputs / "plan.yaml").write_text(PLAN_TEXT)
    (inputs / "cell.yaml").write_text(CELL_TEXT)
    prov = collect_provenance(inputs / "plan.yaml", inputs / "cell.yaml", None)
    j = Journal.create(session_dir, SessionMeta("synthetic", seed, prov), min_free_bytes=0)
    try:
        j.set_provenance("devices", {"arm": {"serial": "SIM-0001"}, "ft": {"serial": "FT-SIM"}})
        j.set_status("running")
        j.record_transition("idle", "preflight", "start", clock.advance(0.0))
        if stop < STAGES.index("cloud"):
            return session_dir
        pts, normals = _cloud(rng)
        j.record_transition("preflight", "sweeping", "sweep", clock.advance(1.0))
        j.add_robot_time("sweep", 120.0)
        j.commit_phase("cloud", 0, {"n_points": len(pts)}, {"points_mm": pts.astype(np.float32),
                                                           "normals": normals.astype(np.float32)})
        j.record_transition("sweeping", "planning", "plan", clock.advance(120.0))
        if stop < STAGES.index("sampling"):
            return session_dir
        gx, gy = np.meshgrid(np.linspace(15.0, 105.0, 4), np.linspace(15.0, 45.0, 3))
        sampling = _targets(0, np.column_stack([gx.ravel(), gy.ravel()]))
        units = sampling["target_points_mm"] + [0.0, 0.0, 0.5]
        survey = _plans(j, sampling, list(range(12)), (90.0,), SURVEY_FORCES_N)
        j.commit_phase("sampling", 0, {"n_units": 12, "n_targets": 12},
                       {"units": units, **sampling, "edge_flag": np.zeros(12, np.int8)}, survey)
        if stop < STAGES.index("survey"):
            return session_dir
        _run_steps(j, rng, clock, "sampling", 0, fail_first=True)
        j.complete_phase("sampling", 0)
        if stop < STAGES.index("regions"):
            return session_dir
        ids, labels = _labels_for(j, [sampling])
        chosen = [0, 4, 3, 7]                        # two interior targets per region
        char = _plans(j, sampling, chosen, CHAR_ANGLES_DEG, CHAR_FORCES_N)
        j.commit_phase("regions", 0, {"n_regions": 2, "characterize_targets": chosen},
                       {"labelled_targets": ids, "labels": labels, "features": rng.normal(size=(12, 3))},
                       char)
        if stop < STAGES.index("characterize"):
            return session_dir
        _run_steps(j, rng, clock, "regions", 0)
        if stop < STAGES.index("models"):
            return session_dir
        j.record_transition("planning", "learning", "learn", clock.advance(0.5))
        _fit_models(j, session_dir, 0, dict(zip(ids.tolist(), labels.tolist())))
        j.record_transition("learning", "planning", "plan", clock.advance(30.0))
        if stop < STAGES.index("densify"):
            return session_dir
        dens = _targets(12, np.array([[58.0, 22.0], [62.0, 38.0]]))
        record = {"round_index": 1, "n_points": 12, "n_regions": 2, "noise_mm": 0.01, "threshold": 1.0,
                  "pair_scores": {"0-1": 7.5}, "disagreeing_edges": [[1, 2], [5, 6], [9, 10]],
                  "disagreeing_scores": [7.5, 7.5, 7.5], "proposed_mm": dens["target_points_mm"].tolist(),
                  "proposed_scores": [7.5, 7.5], "resolved": False, "reason": "3 edges disagree", "stop": False}
        j.commit_phase("densify", 1, {"resolved": False, "reason": "3 edges disagree", "n_new": 2,
                                      "record": record}, dens,
                       _plans(j, dens, [12, 13], (90.0,), SURVEY_FORCES_N))
        _run_steps(j, rng, clock, "densify", 1)
        ids, labels = _labels_for(j, [sampling, dens])
        j.commit_phase("regions", 1, {"n_regions": 2, "characterize_targets": []},
                       {"labelled_targets": ids, "labels": labels, "features": rng.normal(size=(14, 3))})
        t = clock.advance(2.0)
        j.record_fault("scanner_timeout", "no profile for 2.0 s", t, None, "pause", None)
        j.record_transition("planning", "paused", "pause", t)
        j.record_transition("paused", "preflight", "resume", clock.advance(5.0))
        j.record_transition("preflight", "planning", "plan", clock.advance(1.0))
        if stop < STAGES.index("final"):
            return session_dir
        cloud_labels = (pts[:, 0] >= 60.0).astype(np.int64)
        j.commit_phase("final", 0, {"n_regions": 2, "model_round": 0}, {"cloud_labels": cloud_labels})
        j.record_transition("planning", "done", "finish", clock.advance(1.0))
        j.add_robot_time("travel", 300.0)
        j.log_event("finished", {"steps": len(j.steps())})
        j.set_status("done")
    finally:
        j.close()
    return session_dir
