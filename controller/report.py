"""DIR/report/index.html: the session report, one self-contained file readable offline.

The report answers "what happened overnight" from the journal alone:
the point cloud with the sampling points coloured by region (paper Fig. 7), averaged
profiles per region under increasing force and across angles (Figs. 8-12), measured
versus modelled profiles (Figs. 13-17), predictions for unseen forces and angles
(Figs. 18-19), the disagreement map of each densification round, training errors, a
timeline of states and faults with each fault's raw F/T trace, and the numbers and
provenance. Figures are matplotlib (Agg, imported lazily) PNGs embedded as data URIs;
there is no script and no external URL, so the page works from a USB stick.

It is regenerated after each phase of a running session, so every section copes with
a partial journal: what is missing is shown as "not yet". A figure that fails to
render is shown as an error in its section rather than breaking the report. The file
is written to a temporary name and renamed (a reader never sees half a page).

Units: positions mm (object frame), depth mm along -n (plotted as surface height
change = -depth, a dent goes down, as in the paper), forces N, angles deg, robot
time s (per run, each run's clock starts at 0; the timeline lays runs end to end).
"""
from __future__ import annotations

import base64
import html
import io
import json
import math
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from .core.atomic import atomic_write_text, ensure_dir, readable_text
from .coverage import cloud_summary, describe_cloud
from .journal import FaultRecord, Journal, StepRecord
from .learning.models import RegionModel
from .learning.support import INFERRED, MEASURED, SUPPORT_NAMES, UNSUPPORTED
from .machine import STATES
from .predict import read_manifest

MAX_CLOUD_POINTS = 6000          # points drawn of the cloud (subsampled, seeded)
MAX_FAULT_TRACES = 24            # fault F/T figures embedded; the rest are listed
MAX_REGIONS_DRAWN = 8            # regions with their own profile figures
STEP_CHUNK = 64                  # done steps loaded from the journal at a time (bounds memory)
DPI = 80
# Why the averaging dropped samples (the step summary's counts, profiles.StepMeasurement).
REJECTION_KEYS = ("rejected_scan_samples", "rejected_line_samples", "implausible_samples", "off_face_samples")
# Support of a model's samples (learning.support codes): colour of its band in the model plots.
SUPPORT_COLOURS = ("none", "#9ecae1", "#fdae6b", "#a1d99b", "#d9d9d9")
SECTION_IDS = ("numbers", "region-map", "profiles", "measured-vs-model", "predictions", "disagreement",
               "training", "timeline", "faults", "provenance")


# ============================================================================ the data
@dataclass
class StepProfile:
    """A done step's averaged profile and what it was pressed with."""

    step_id: int
    target_index: int
    region: int | None
    angle_deg: float           # commanded
    force_n: float             # planned level
    force_measured_n: float    # |mean contact force| over the exposures
    x_mm: np.ndarray           # (L,) grid along t
    depth_mm: np.ndarray       # (L,) depth along -n, NaN = missing
    rejected: dict[str, int] = field(default_factory=dict)   # samples the averaging dropped, by reason


@dataclass
class DensifyView:
    """One densification round and the labelled targets its edge indices refer to."""

    round: int
    outputs: dict[str, Any]
    positions_mm: np.ndarray   # (N, 3) labelled targets of the preceding regions phase, sorted by index
    labels: np.ndarray         # (N,)
    new_points_mm: np.ndarray  # (K, 3) targets the round added


@dataclass
class ReportData:
    """Everything the report draws, read once from the journal (numpy arrays, plain dicts)."""

    session_dir: Path
    session: dict[str, Any]
    provenance: dict[str, Any]
    counts: dict[str, int]
    robot_time_s: dict[str, float]
    phases: list[dict[str, Any]]
    steps: list[StepRecord]
    cloud_mm: np.ndarray | None = None
    cloud_outputs: dict[str, Any] = field(default_factory=dict)
    cloud_labels: np.ndarray | None = None
    targets_mm: dict[int, np.ndarray] = field(default_factory=dict)
    target_labels: dict[int, int] = field(default_factory=dict)
    regions_round: int | None = None
    n_regions: int | None = None
    profiles: list[StepProfile] = field(default_factory=list)
    models: dict[int, Any] = field(default_factory=dict)          # region -> RegionModel
    model_problems: dict[int, str] = field(default_factory=dict)
    model_round: int | None = None
    models_source: str = ""
    model_rows: list[dict[str, Any]] = field(default_factory=list)
    densify: list[DensifyView] = field(default_factory=list)
    transitions: list[dict[str, Any]] = field(default_factory=list)
    faults: list[FaultRecord] = field(default_factory=list)
    runs: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)


def _rounds(phases: list[dict[str, Any]], name: str) -> list[int]:
    return sorted(p["round"] for p in phases if p["name"] == name)


def _collect_targets(j: Journal, phases: list[dict[str, Any]], steps: list[StepRecord]) -> dict[int, np.ndarray]:
    """Target index -> point (mm): from the sampling and densify phases, then the step plans."""
    out: dict[int, np.ndarray] = {}
    for name in ("sampling", "densify"):
        for r in _rounds(phases, name):
            rec = j.phase(name, r)
            if rec is None or "target_points_mm" not in rec.arrays:
                continue
            pts = np.asarray(rec.arrays["target_points_mm"], dtype=float).reshape(-1, 3)
            idx = rec.arrays.get("target_index", np.arange(len(pts)))
            out.update({int(i): pts[k] for k, i in enumerate(idx)})
    for s in steps:
        out.setdefault(s.plan.target_index, np.asarray(s.plan.point_mm, dtype=float))
    return out


def _load_profiles(j: Journal, steps: list[StepRecord], labels: dict[int, int]) -> list[StepProfile]:
    out = []
    done = [s for s in steps if s.status == "done"]
    results: dict[int, Any] = {}
    for k, s in enumerate(done):
        if k % STEP_CHUNK == 0:   # a chunk at a time: raw scans are large, only profiles are kept
            results = j.step_results([r.step_id for r in done[k:k + STEP_CHUNK]])
        res = results[s.step_id]
        depth = np.asarray(res.profile_depth_mm, dtype=float)
        x = np.asarray(res.profile_x_mm, dtype=float) if res.profile_x_mm is not None else np.arange(depth.size, dtype=float)
        f_meas = float(np.linalg.norm(np.nanmean(np.asarray(res.scan_force_n, dtype=float), axis=0)))
        facts = res.summary or {}
        rejected = {k: int(facts[k]) for k in REJECTION_KEYS if isinstance(facts.get(k), (int, float))}
        out.append(StepProfile(s.step_id, s.plan.target_index, labels.get(s.plan.target_index), float(s.plan.angle_deg),
                               float(s.plan.force_n), f_meas, x, depth, rejected))
    return out


def _load_models(data: ReportData, j: Journal) -> None:
    """The region models ``predict`` serves: the latest models phase's, or those
    ``elastoprobe train`` refitted since (or, before any, the model table)."""
    rounds = _rounds(data.phases, "models")
    entries: dict[int, str] = {}
    manifest = read_manifest(data.session_dir)
    if manifest is not None and int(manifest.get("session_models_round", -1)) >= (rounds[-1] if rounds else -1):
        entries = {int(k): v["path"] for k, v in manifest["regions"].items() if isinstance(v, dict) and "path" in v}
        data.models_source = f"retrained by `elastoprobe train` at {manifest.get('trained_utc', '?')}"
    elif rounds:
        rec = j.phase("models", rounds[-1])
        data.model_round = rounds[-1]
        data.models_source = f"models round {rounds[-1]}"
        for region, info in (rec.outputs.get("regions", {}) if rec else {}).items():
            if isinstance(info, dict) and "path" in info:
                entries[int(region)] = info["path"]
            elif isinstance(info, dict):
                data.model_problems[int(region)] = str(info.get("skipped", "no model"))
    else:
        entries = {int(m["region"]): m["path"] for m in data.model_rows if int(m["member"]) == 0}
    for region, rel in sorted(entries.items()):
        path = Path(rel) if Path(rel).is_absolute() else data.session_dir / rel
        try:
            data.models[region] = RegionModel.load(path)
        except Exception as exc:   # any damage (truncated zip, bad JSON, hash mismatch) is shown, not fatal
            data.model_problems[region] = f"cannot load {rel}: {type(exc).__name__}: {exc}"


def _densify_views(j: Journal, phases: list[dict[str, Any]], targets_mm: dict[int, np.ndarray]) -> list[DensifyView]:
    """Each densify round with the labelled targets of the regions phase before it: the
    round scored ``sorted(labelled targets)``, so its edge indices refer to that order."""
    views = []
    region_rounds = _rounds(phases, "regions")
    for r in _rounds(phases, "densify"):
        rec = j.phase("densify", r)
        if rec is None:
            continue
        before = [q for q in region_rounds if q < r]
        reg = j.phase("regions", before[-1]) if before else None
        ids, lab = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if reg is not None:
            ids = np.asarray(reg.arrays["labelled_targets"], dtype=np.int64)
            order = np.argsort(ids, kind="stable")
            ids, lab = ids[order], np.asarray(reg.arrays["labels"], dtype=np.int64)[order]
        pos = np.array([targets_mm.get(int(i), np.full(3, np.nan)) for i in ids]).reshape(-1, 3)
        new = np.asarray(rec.arrays.get("target_points_mm", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
        views.append(DensifyView(r, rec.outputs, pos, lab, new))
    return views


def collect(j: Journal) -> ReportData:
    """Read what the report needs from a (possibly partial) journal."""
    phases = j.phases()
    steps = j.steps()
    summary = j.summary()
    data = ReportData(session_dir=Path(j.session_dir), session=j.session(), provenance=j.provenance(),
                      counts=j.status_counts(), robot_time_s=j.robot_time_s(), phases=phases, steps=steps,
                      runs=summary["runs"], model_rows=j.models())
    cloud = j.phase("cloud", 0)
    if cloud is not None:
        data.cloud_mm = np.asarray(cloud.arrays["points_mm"], dtype=float)
        data.cloud_outputs = cloud.outputs
    final = j.phase("final", 0)
    if final is not None and "cloud_labels" in final.arrays:
        data.cloud_labels = np.asarray(final.arrays["cloud_labels"])
    data.targets_mm = _collect_targets(j, phases, steps)
    region_rounds = _rounds(phases, "regions")
    if region_rounds:
        reg = j.phase("regions", region_rounds[-1])
        assert reg is not None
        data.regions_round = region_rounds[-1]
        data.n_regions = int(reg.outputs.get("n_regions", len(np.unique(reg.arrays["labels"]))))
        data.target_labels = {int(i): int(lab) for i, lab in zip(reg.arrays["labelled_targets"], reg.arrays["labels"])}
    data.profiles = _load_profiles(j, steps, data.target_labels)
    _load_models(data, j)
    data.densify = _densify_views(j, phases, data.targets_mm)
    data.transitions = j.transitions()
    data.faults = j.faults()
    data.events = j.events()
    return data


# ============================================================================ numbers
def _probe_counts(steps: Iterable[StepRecord]) -> dict[str, int]:
    done = [s for s in steps if s.status == "done"]
    return {"force_steps_done": len(done),
            "probes_done": len({(s.plan.target_index, round(s.plan.angle_deg, 6)) for s in done}),
            "targets_probed": len({s.plan.target_index for s in done}),
            "attempts": int(sum(s.attempts for s in steps))}


def _model_table(data: ReportData) -> list[dict[str, Any]]:
    """Per region: training error (mm) from the model metadata and fit error over the measured profiles."""
    rows = []
    for region, model in sorted(data.models.items()):
        mse = model.meta.get("train_mse_norm")
        train_rmse = math.sqrt(mse) * model.depth_scale_mm if isinstance(mse, (int, float)) and mse >= 0 else None
        fit = _fit_rmse_mm(data, region, model)
        support = model.meta.get("support", {}) if isinstance(model.meta.get("support"), dict) else {}
        mirror = support.get("mirror", {}) if isinstance(support.get("mirror"), dict) else {}
        counts = support.get("support", {}) if isinstance(support.get("support"), dict) else {}
        total = sum(v for v in counts.values() if isinstance(v, (int, float)))
        rows.append({"region": region, "members": model.n_members, "hidden_units": model.hidden_units,
                     "n_profiles": model.meta.get("training", {}).get("n_profiles"),
                     "train_rmse_mm": _round(train_rmse, 4), "fit_rmse_mm": _round(fit, 4),
                     "depth_scale_mm": _round(model.depth_scale_mm, 4), "model_hash": model.model_hash()[:12],
                     "mirror": mirror.get("reason", "not recorded"),
                     "support": {k: round(v / total, 3) for k, v in counts.items()} if total else "not recorded",
                     "depth_bounds_mm": support.get("depth_bounds_mm")})
    for region, problem in sorted(data.model_problems.items()):
        rows.append({"region": region, "problem": problem})
    return rows


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), digits)


def _fit_rmse_mm(data: ReportData, region: int, model: Any) -> float | None:
    """RMS (mm) of model minus measured averaged profile over every done step of the region
    (training data: an in-sample fit error, not a held-out one)."""
    profs = [p for p in data.profiles if p.region == region and p.depth_mm.size == model.outputs]
    if not profs:
        return None
    pred = model.predict_batch_mm(np.array([p.force_measured_n for p in profs]), np.array([p.angle_deg for p in profs]))
    meas = np.array([p.depth_mm for p in profs])
    ok = np.isfinite(meas)
    return float(np.sqrt(np.mean((pred[ok] - meas[ok]) ** 2))) if ok.any() else None


def _numbers(data: ReportData) -> dict[str, Any]:
    robot = data.robot_time_s
    kinds: dict[str, int] = defaultdict(int)
    for f in data.faults:
        kinds[f.kind] += 1
    return {"plan": data.session["plan_name"], "seed": data.session["seed"], "status": data.session["status"],
            "status_reason": data.session["status_reason"], "created_utc": data.session["created_utc"],
            "steps": data.counts, **_probe_counts(data.steps),
            "robot_hours": round(robot.get("total", 0.0) / 3600.0, 3),
            "robot_time_s": {k: round(v, 1) for k, v in robot.items()},
            "faults": len(data.faults), "faults_by_kind": dict(sorted(kinds.items())),
            "regions": data.n_regions, "regions_round": data.regions_round, "model_round": data.model_round,
            "runs": len(data.runs), "densify_rounds": len(data.densify),
            "cloud": cloud_summary(data.cloud_outputs) if data.cloud_outputs else None,
            "model_errors": _model_table(data), "models": data.model_rows}


def report_numbers(j: Journal) -> dict[str, Any]:
    """The session's numbers as plain JSON-able values (what the report's table shows)."""
    return _numbers(collect(j))


# ============================================================================ figures
def _figure(width_in: float, height_in: float) -> Any:
    from matplotlib.figure import Figure    # no pyplot: no global state, no GUI backend
    return Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _region_colour(region: int | None) -> Any:
    from matplotlib import colormaps
    if region is None or region < 0:
        return (0.6, 0.6, 0.6, 1.0)
    return colormaps["tab10"](int(region) % 10)


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def _characterized(data: ReportData) -> set[int]:
    """Targets probed (or planned) at more than one angle: the characterization points."""
    angles: dict[int, set[float]] = defaultdict(set)
    for s in data.steps:
        angles[s.plan.target_index].add(round(s.plan.angle_deg, 6))
    return {t for t, a in angles.items() if len(a) > 1}


def fig_region_map(data: ReportData) -> Any:
    """Paper Fig. 7: the cloud, and the sampling points coloured by region (3-D view and top view)."""
    if data.cloud_mm is None:
        return None
    pts = data.cloud_mm
    sel = _subsample(len(pts), MAX_CLOUD_POINTS)
    fig = _figure(11, 4.8)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    if data.cloud_labels is not None and len(data.cloud_labels) == len(pts):
        cc = [_region_colour(int(v)) for v in data.cloud_labels[sel]]
        cloud_kw: dict[str, Any] = {"c": cc, "alpha": 0.25}
    else:
        cloud_kw = {"c": pts[sel, 2], "cmap": "Greys", "alpha": 0.3}
    ax3.scatter(pts[sel, 0], pts[sel, 1], pts[sel, 2], s=1, **cloud_kw)
    ax2.scatter(pts[sel, 0], pts[sel, 1], s=1, **cloud_kw)
    char = _characterized(data)
    for idx, p in sorted(data.targets_mm.items()):
        region = data.target_labels.get(idx)
        marker = "^" if idx in char else "o"
        colour = _region_colour(region)
        face = colour if region is not None else "none"
        ax3.scatter([p[0]], [p[1]], [p[2]], s=40 if idx in char else 18, marker=marker, c=[face],
                    edgecolors="k", linewidths=0.6, depthshade=False)
        ax2.scatter([p[0]], [p[1]], s=60 if idx in char else 25, marker=marker, c=[face] if region is not None else "none",
                    edgecolors="k" if region is not None else "0.4", linewidths=0.7)
    for ax in (ax3, ax2):
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    ax3.set_zlabel("z (mm)")
    ax2.set_aspect("equal", adjustable="datalim")
    regions = sorted({v for v in data.target_labels.values()})
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], marker="o", ls="", mfc=_region_colour(r), mec="k", label=f"region {r}") for r in regions]
    handles += [Line2D([], [], marker="o", ls="", mfc="none", mec="k", label="survey point"),
                Line2D([], [], marker="^", ls="", mfc="none", mec="k", label="characterization point")]
    if not regions:
        handles.insert(0, Line2D([], [], marker="o", ls="", mfc="none", mec="0.4", label="not yet labelled"))
    ax2.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    title = "Object frame; regions from " + (f"regions round {data.regions_round}" if data.regions_round is not None
                                              else "(not yet clustered)")
    fig.suptitle(title, fontsize=10)
    return fig


def _grouped(profiles: list[StepProfile]) -> dict[tuple[float, float], tuple[np.ndarray, np.ndarray, float, int]]:
    """(angle, planned force) -> (x, NaN-mean depth over targets, mean measured |F|, count)."""
    groups: dict[tuple[float, float], list[StepProfile]] = defaultdict(list)
    for p in profiles:
        groups[(round(p.angle_deg, 6), round(p.force_n, 6))].append(p)
    out = {}
    for key, ps in groups.items():
        same = [p for p in ps if p.depth_mm.shape == ps[0].depth_mm.shape]
        stack = np.array([p.depth_mm for p in same])
        with warnings.catch_warnings():   # an all-NaN column (shadow) is NaN, said quietly
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(stack, axis=0)
        out[key] = (same[0].x_mm, mean, float(np.mean([p.force_measured_n for p in same])), len(same))
    return out


def _regions_with_profiles(data: ReportData) -> list[int]:
    return sorted({p.region for p in data.profiles if p.region is not None})[:MAX_REGIONS_DRAWN]


def _nearest(values: Iterable[float], target: float) -> float:
    vals = sorted(set(values))
    return min(vals, key=lambda v: (abs(v - target), v))


def fig_region_profiles(data: ReportData, region: int) -> Any:
    """Figs. 8-12: averaged profiles of one region under increasing force (at the angle
    nearest 90 deg) and across angles (at the largest force)."""
    groups = _grouped([p for p in data.profiles if p.region == region])
    if not groups:
        return None
    from matplotlib import colormaps
    angle_n = _nearest((a for a, _ in groups), 90.0)
    force_top = max(f for _, f in groups)
    fig = _figure(10, 3.4)
    ax_f, ax_a = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    by_force = sorted((f, v) for (a, f), v in groups.items() if a == angle_n)
    for k, (f, (x, mean, fm, n)) in enumerate(by_force):
        ax_f.plot(x, -mean, color=colormaps["viridis"](k / max(1, len(by_force) - 1)),
                  label=f"{f:g} N (|F| {fm:.2f}, n={n})")
    by_angle = sorted((a, v) for (a, f), v in groups.items() if f == force_top)
    for k, (a, (x, mean, fm, n)) in enumerate(by_angle):
        ax_a.plot(x, -mean, color=colormaps["plasma"](k / max(1, len(by_angle))), label=f"{a:g}° (n={n})")
    ax_f.set_title(f"region {region}: increasing force at {angle_n:g}°", fontsize=9)
    ax_a.set_title(f"region {region}: angles at {force_top:g} N", fontsize=9)
    for ax in (ax_f, ax_a):
        ax.set_xlabel("x along t (mm)")
        ax.set_ylabel("surface height change (mm)")
        ax.legend(fontsize=6)
        ax.grid(alpha=0.3)
    return fig


def _pick_groups(keys: list[tuple[float, float]], k: int = 4) -> list[tuple[float, float]]:
    """Up to k (angle, force) pairs spread over the angles, with the extreme forces."""
    angles = sorted({a for a, _ in keys})
    picks: list[tuple[float, float]] = []
    for a in [angles[i] for i in sorted(set(np.linspace(0, len(angles) - 1, min(len(angles), 3)).round().astype(int)))]:
        forces = sorted(f for aa, f in keys if aa == a)
        for f in ([forces[-1], forces[0]] if len(forces) > 1 else forces):
            if (a, f) not in picks:
                picks.append((a, f))
    return picks[:k]


def _support_runs(codes: np.ndarray) -> list[tuple[int, int, int]]:
    """(first, last, code) of each run of equal support codes along the grid."""
    c = np.asarray(codes)
    if c.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(c)) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [c.size]]) - 1
    return [(int(a), int(b), int(c[a])) for a, b in zip(starts, ends)]


def _shade_support(ax: Any, x: np.ndarray, codes: np.ndarray) -> None:
    """Background bands: where the model's samples came from (no band where measured)."""
    half = 0.5 * float(x[1] - x[0]) if x.size > 1 else 0.5
    drawn: set[int] = set()
    for a, b, code in _support_runs(codes):
        if code == MEASURED and code not in drawn:
            # The legend names the unshaded background too, so every support is named.
            ax.fill_between([], [], color="white", ec="0.6", lw=0.5, label=f"{SUPPORT_NAMES[code]} (no band)")
            drawn.add(code)
        if not 0 < code < len(SUPPORT_NAMES):
            continue
        ax.axvspan(x[a] - half, x[b] + half, color=SUPPORT_COLOURS[code], alpha=0.6, lw=0,
                   label=None if code in drawn else SUPPORT_NAMES[code])
        drawn.add(code)


def fig_measured_vs_model(data: ReportData, region: int) -> Any:
    """Figs. 13-17: measured averaged profiles against the region model at the same (|F|, angle),
    over the bands that say where the model's samples come from."""
    model = data.models.get(region)
    groups = _grouped([p for p in data.profiles if p.region == region])
    if model is None or not groups:
        return None
    picks = _pick_groups(sorted(groups))
    fig = _figure(10, 2.8 * math.ceil(len(picks) / 2))
    for k, key in enumerate(picks):
        x, mean, fm, n = groups[key]
        ax = fig.add_subplot(math.ceil(len(picks) / 2), 2, k + 1)
        if model.outputs == x.size:
            served = model.serve(fm, key[0], extrapolate=True)
            if (served.support >= 0).any():
                _shade_support(ax, model.x_mm, served.support)
            ax.plot(model.x_mm, -served.depth_mm, "r-", lw=1.2, label="model")
        ax.plot(x, -mean, "k.", ms=2.5, label=f"measured (n={n})")
        ax.set_title(f"region {region}: {key[0]:g}°, {key[1]:g} N (|F| {fm:.2f} N)", fontsize=8)
        ax.set_xlabel("x along t (mm)", fontsize=8)
        ax.set_ylabel("height change (mm)", fontsize=8)
        ax.legend(fontsize=6, loc="lower right")
        ax.grid(alpha=0.3)
    return fig


def unseen_queries(measured_forces_n: Iterable[float], measured_angles_deg: Iterable[float],
                   force_range_n: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Forces (N) and angles (deg) the region was NOT probed at: midpoints between the
    measured levels (inside the model's force range), and angles between the measured ones."""
    f = np.array(sorted(set(round(v, 6) for v in measured_forces_n)))
    a = np.array(sorted(set(round(v, 6) for v in measured_angles_deg)))
    lo, hi = force_range_n
    forces = (f[:-1] + f[1:]) / 2.0 if f.size > 1 else np.array([])
    forces = forces[(forces >= lo) & (forces <= hi)]
    if forces.size == 0:
        forces = np.array([(lo + hi) / 2.0]) if hi > lo else np.array([lo])
    if a.size > 1:
        angles = (a[:-1] + a[1:]) / 2.0
    else:   # one angle measured: the unseen ones are around it (a model extrapolates there)
        angles = np.clip(a + np.array([-22.5, 22.5]), 5.0, 175.0) if a.size else np.array([90.0])
    return forces, angles


def _plot_served(ax: Any, served: Any, colour: Any, label: str) -> None:
    """A served profile as height change: solid where measured, mirrored or under the tip,
    dashed where inferred, dotted where unsupported; the ensemble spread as a band."""
    x, d, sd = served.x_mm, served.depth_mm, served.spread_mm
    ax.fill_between(x, -d - sd, -d + sd, color=colour, alpha=0.15, lw=0)
    styles = {INFERRED: "--", UNSUPPORTED: ":"}
    for a, b, code in _support_runs(served.support):
        lo, hi = max(a - 1, 0), b + 1     # overlap one sample so the pieces join
        ax.plot(x[lo:hi + 1], -d[lo:hi + 1], styles.get(code, "-"), color=colour, lw=1.1)
    ax.plot([], [], "-", color=colour, lw=1.1, label=label)       # the legend's entry: the colour


def fig_predictions(data: ReportData, region: int) -> Any:
    """Figs. 18-19: predicted profiles for unseen forces and angles, as ``predict`` serves them
    (band: the bootstrap members' spread; line style: the samples' support)."""
    model = data.models.get(region)
    if model is None:
        return None
    profs = [p for p in data.profiles if p.region == region]
    if not profs:
        return None
    from matplotlib import colormaps
    from matplotlib.lines import Line2D
    forces, angles = unseen_queries([p.force_n for p in profs], [p.angle_deg for p in profs], model.force_range_n)
    angle_n = _nearest((p.angle_deg for p in profs), 90.0)
    force_top = float(max(p.force_measured_n for p in profs))
    fig = _figure(10, 3.6)
    ax_f, ax_a = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for k, served in enumerate(model.serve_batch(forces, np.full(forces.shape, angle_n), extrapolate=True)):
        _plot_served(ax_f, served, colormaps["viridis"](k / max(1, len(forces) - 1)), f"{forces[k]:.2f} N")
    for k, served in enumerate(model.serve_batch(np.full(angles.shape, force_top), angles, extrapolate=True)):
        _plot_served(ax_a, served, colormaps["plasma"](k / max(1, len(angles))), f"{angles[k]:g}°")
    ax_f.set_title(f"region {region}: unseen forces at {angle_n:g}°", fontsize=9)
    ax_a.set_title(f"region {region}: unseen angles at {force_top:.2f} N", fontsize=9)
    styles = [Line2D([], [], color="0.3", ls=ls, label=name) for ls, name in
              (("-", "measured, mirrored or tip"), ("--", "inferred"), (":", "unsupported"))]
    for ax in (ax_f, ax_a):
        ax.set_xlabel("x along t (mm)")
        ax.set_ylabel("predicted height change (mm)")
        first = ax.legend(fontsize=6, loc="lower right")
        ax.add_artist(first)
        ax.legend(handles=styles, fontsize=6, loc="lower left")
        ax.grid(alpha=0.3)
    return fig


def fig_disagreement(data: ReportData, view: DensifyView) -> Any:
    """One densification round: labelled targets by region, the edges whose adjacent region
    models disagree (colour = score in noise units), and the points proposed."""
    rec = view.outputs.get("record") if isinstance(view.outputs.get("record"), dict) else {}
    pos = view.positions_mm
    fig = _figure(7.5, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    if data.cloud_mm is not None:
        sel = _subsample(len(data.cloud_mm), 3000, seed=1)
        ax.scatter(data.cloud_mm[sel, 0], data.cloud_mm[sel, 1], s=1, c="0.85")
    for p, lab in zip(pos, view.labels):
        ax.scatter([p[0]], [p[1]], s=25, c=[_region_colour(int(lab))], edgecolors="k", linewidths=0.5)
    edges = rec.get("disagreeing_edges") or []
    scores = rec.get("disagreeing_scores") or [None] * len(edges)
    finite = [s for s in scores if isinstance(s, (int, float))]
    top = max(finite) if finite else 1.0
    from matplotlib import colormaps
    drawn = 0
    for (a, b), s in zip(edges, scores):
        if 0 <= a < len(pos) and 0 <= b < len(pos):
            level = (s / top) if isinstance(s, (int, float)) and top > 0 else 1.0
            ax.plot([pos[a, 0], pos[b, 0]], [pos[a, 1], pos[b, 1]], "-", lw=1 + 2 * level,
                    color=colormaps["Reds"](0.4 + 0.6 * level))
            drawn += 1
    proposed = np.asarray(rec.get("proposed_mm") or view.new_points_mm, dtype=float).reshape(-1, 3)
    if len(proposed):
        ax.scatter(proposed[:, 0], proposed[:, 1], marker="*", s=120, c="gold", edgecolors="k", linewidths=0.7,
                   label=f"proposed ({len(proposed)})")
    if len(view.new_points_mm):
        ax.scatter(view.new_points_mm[:, 0], view.new_points_mm[:, 1], marker="s", s=40, facecolors="none",
                   edgecolors="b", label=f"reachable, added ({len(view.new_points_mm)})")
    ax.plot([], [], "-", color=colormaps["Reds"](1.0), lw=3, label=f"disagreeing edges ({drawn}, max {top:.3g})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    reason = str(view.outputs.get("reason", rec.get("reason", "")))
    ax.set_title(f"densify round {view.round}: {'resolved' if view.outputs.get('resolved') else 'unresolved'} — "
                 f"{reason[:80]}", fontsize=8)
    return fig


def loss_history(meta: dict[str, Any]) -> np.ndarray | None:
    """The training loss history (checks, members) if the model metadata holds one, else None.
    Looked for in ``meta['loss_history']`` and ``meta['training']['history'|'loss_history']``
    (or under ``training['extra']``), as a list of numbers or of per-member lists."""
    training = meta.get("training") if isinstance(meta.get("training"), dict) else {}
    extra = training.get("extra") if isinstance(training.get("extra"), dict) else {}
    for cand in (meta.get("loss_history"), training.get("loss_history"), training.get("history"),
                 extra.get("loss_history"), extra.get("history")):
        if cand is None:
            continue
        try:
            arr = np.asarray(cand, dtype=float)
        except (TypeError, ValueError):
            continue
        if arr.ndim == 1 and arr.size:
            return arr[:, None]
        if arr.ndim == 2 and arr.size:
            return arr
    return None


def fig_training(data: ReportData) -> tuple[Any, bool]:
    """Training curves if the metadata holds the loss history, else the final training
    RMSE (mm) per region with the noise-based goal. Returns (figure, is_curve)."""
    if not data.models:
        return None, False
    histories = {r: loss_history(m.meta) for r, m in data.models.items()}
    fig = _figure(8, 3.4)
    ax = fig.add_subplot(1, 1, 1)
    if all(h is not None for h in histories.values()):
        for r, h in sorted(histories.items()):
            assert h is not None
            ax.semilogy(np.arange(1, len(h) + 1), h[:, 0], color=_region_colour(r), label=f"region {r} (full data)")
            if h.shape[1] > 1:
                ax.semilogy(np.arange(1, len(h) + 1), h[:, 1:], color=_region_colour(r), alpha=0.3, lw=0.7)
        ax.set_xlabel("check (every few epochs)")
        ax.set_ylabel("weighted MSE (normalised depth)")
        ax.legend(fontsize=7)
        return fig, True
    regions = sorted(data.models)
    rmse, goal = [], []
    for r in regions:
        m = data.models[r]
        mse = m.meta.get("train_mse_norm")
        rmse.append(math.sqrt(mse) * m.depth_scale_mm if isinstance(mse, (int, float)) and mse >= 0 else np.nan)
        g = m.meta.get("training", {}).get("extra", {}).get("loss_goal_norm")
        goal.append(math.sqrt(g) * m.depth_scale_mm if isinstance(g, (int, float)) and g > 0 else np.nan)
    ax.bar([str(r) for r in regions], rmse, color=[_region_colour(r) for r in regions], edgecolor="k")
    if np.isfinite(goal).any():
        ax.plot([str(r) for r in regions], goal, "k_", ms=30, mew=2, label="stop goal (noise)")
        ax.legend(fontsize=7)
    ax.set_xlabel("region")
    ax.set_ylabel("final training RMSE (mm)")
    return fig, False


def _run_offsets(transitions: list[dict[str, Any]]) -> dict[int | None, float]:
    """Each run's robot clock starts at 0: lay runs end to end (s) for one timeline."""
    offsets: dict[int | None, float] = {}
    total = 0.0
    for t in transitions:
        run = t["run_id"]
        if run not in offsets:
            offsets[run] = total
        if t["t_robot_s"] is not None:
            total = max(total, offsets[run] + float(t["t_robot_s"]))
    return offsets


def _fault_run(fault: FaultRecord, runs: list[dict[str, Any]]) -> int | None:
    """The run a fault happened in (faults carry wall time, runs their start times)."""
    best = None
    for r in runs:
        if r["started_utc"] and r["started_utc"] <= fault.t_wall_utc:
            best = r["run_id"]
    return best


def fig_timeline(data: ReportData) -> Any:
    """States over robot time (one row per state) with faults as red lines."""
    tr = [t for t in data.transitions if t["t_robot_s"] is not None]
    if not tr:
        return None
    offsets = _run_offsets(tr)
    end_s = max(offsets[t["run_id"]] + float(t["t_robot_s"]) for t in tr)
    unit, scale = ("h", 3600.0) if end_s > 3 * 3600 else ("min", 60.0) if end_s > 600 else ("s", 1.0)
    t_abs = [(offsets[t["run_id"]] + float(t["t_robot_s"])) / scale for t in tr]
    end = end_s / scale
    states = [s for s in STATES if any(s in (t["from_state"], t["to_state"]) for t in tr)]
    row = {s: k for k, s in enumerate(states)}
    fig = _figure(11, 0.3 * len(states) + 1.6)
    ax = fig.add_subplot(1, 1, 1)
    segs: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for k, t in enumerate(tr):
        t1 = t_abs[k + 1] if k + 1 < len(tr) else end
        segs[t["to_state"]].append((t_abs[k], max(t1 - t_abs[k], end * 1e-4)))
    for s, spans in segs.items():
        colour = "tab:red" if s in ("fault", "aborted") else "tab:orange" if s in ("paused", "recovering") else "tab:blue"
        ax.broken_barh(spans, (row[s] - 0.35, 0.7), facecolors=colour)
    timed = [f for f in data.faults if f.t_robot_s is not None]
    for f in timed:
        x = (offsets.get(_fault_run(f, data.runs), 0.0) + float(f.t_robot_s)) / scale   # type: ignore[arg-type]
        ax.axvline(x, color="red", lw=0.8, alpha=0.7)
        if len(timed) <= 12:    # beyond that the labels overlap; the fault table lists them
            ax.text(x, len(states) - 0.4, f"#{f.fault_id} {f.kind}", rotation=90, fontsize=6, va="top", color="red")
    for off in offsets.values():
        if off > 0:
            ax.axvline(off / scale, color="k", ls="--", lw=0.8)
    ax.set_yticks(range(len(states)))
    ax.set_yticklabels(states, fontsize=7)
    ax.set_xlabel(f"robot time ({unit}); red: faults; dashed: a resumed run starts")
    ax.set_xlim(0, end if end > 0 else 1.0)
    ax.grid(axis="x", alpha=0.3)
    return fig


def fig_fault_trace(fault: FaultRecord) -> Any:
    """The raw F/T data (N, 7) journaled with a fault: forces and |F| against time before the fault."""
    if fault.raw is None or len(fault.raw) == 0:
        return None
    raw = np.asarray(fault.raw, dtype=float)
    t = raw[:, 0] - raw[-1, 0]
    fig = _figure(7, 2.4)
    ax = fig.add_subplot(1, 2, 1)
    for k, name in enumerate(("Fx", "Fy", "Fz")):
        ax.plot(t, raw[:, 1 + k], lw=0.8, label=name)
    ax.plot(t, np.linalg.norm(raw[:, 1:4], axis=1), "k", lw=1.0, label="|F|")
    ax.set_xlabel("t - t_last (s)", fontsize=8)
    ax.set_ylabel("force (N)", fontsize=8)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    ax2 = fig.add_subplot(1, 2, 2)
    for k, name in enumerate(("Tx", "Ty", "Tz")):
        ax2.plot(t, raw[:, 4 + k], lw=0.8, label=name)
    ax2.set_xlabel("t - t_last (s)", fontsize=8)
    ax2.set_ylabel("torque (N·m)", fontsize=8)
    ax2.legend(fontsize=6)
    ax2.grid(alpha=0.3)
    fig.suptitle(f"fault #{fault.fault_id} {fault.kind} (step {fault.step_id})", fontsize=9)
    return fig


# ============================================================================ HTML
_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;color:#222}"
        "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left;"
        "vertical-align:top;font-size:90%}img{max-width:100%;display:block;margin:.5em 0}"
        ".not-yet{color:#888;font-style:italic}.figure-error{color:#b00}nav a{margin-right:1em}"
        ".fault{display:inline-block;width:49%;vertical-align:top}"
        "code{font-size:85%;word-break:break-all}section{border-top:1px solid #ddd;margin-top:1.5em}")


def _esc(v: Any) -> str:
    return html.escape(str(v), quote=True)


def _not_yet(what: str) -> str:
    return f"<p class='not-yet'>Not yet: {_esc(what)}</p>"


class _Figures:
    """Renders figure callables into <img> tags; a failure becomes a visible error."""

    def __init__(self) -> None:
        self.errors: list[str] = []

    def img(self, alt: str, build: Callable[[], Any], missing: str) -> str:
        try:
            fig = build()
            if isinstance(fig, tuple):
                fig = fig[0]
            if fig is None:
                return _not_yet(missing)
            return f"<img alt='{_esc(alt)}' src='{_png(fig)}'>"
        except Exception as exc:   # a broken figure must not take the report (or the session) down
            self.errors.append(f"{alt}: {type(exc).__name__}: {exc}")
            return f"<p class='figure-error'>Figure {_esc(alt)} failed: {_esc(type(exc).__name__)}: {_esc(exc)}</p>"


def _table(rows: list[tuple[str, Any]]) -> str:
    body = "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v if not isinstance(v, (dict, list)) else json.dumps(v))}</td></tr>"
                   for k, v in rows)
    return f"<table>{body}</table>"


def _grid(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_esc('' if v is None else v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _section_numbers(data: ReportData, numbers: dict[str, Any]) -> str:
    rows = [(k, numbers[k]) for k in ("plan", "status", "status_reason", "seed", "created_utc", "runs",
                                      "force_steps_done", "probes_done", "targets_probed", "attempts",
                                      "robot_hours", "faults", "regions", "regions_round", "model_round",
                                      "densify_rounds")]
    rows.insert(7, ("steps by status", numbers["steps"]))
    rows.insert(12, ("robot time by category (s)", numbers["robot_time_s"]))
    rows.insert(14, ("faults by kind", numbers["faults_by_kind"]))
    if numbers["cloud"] is not None:
        rows.insert(7, ("cloud", describe_cloud(numbers["cloud"])))
    out = _table(rows)
    errs = numbers["model_errors"]
    if errs:
        out += f"<h3>Model errors</h3><p>Models: {_esc(data.models_source or 'not recorded')}. train RMSE: the " \
               "fit at the end of training over the completed targets (model metadata); fit RMSE: model minus " \
               "every measured averaged profile of the region (in-sample, mm). Support: where the training " \
               "targets' samples came from (measured; mirrored from the same point at 180 - angle; the tip's " \
               "sphere under a normal push; inferred from the 90-degree profile at the same normal load with the " \
               "odd term of the tangential load reversed, or beside the tip from the contact's shape; " \
               "unsupported, interpolated). Served depths are clipped to the depth bounds.</p>"
        out += _grid(["region", "members", "hidden", "profiles", "train RMSE (mm)", "fit RMSE (mm)",
                      "depth scale (mm)", "model hash", "mirror", "support of the targets", "depth bounds (mm)",
                      "problem"],
                     [[e.get("region"), e.get("members"), e.get("hidden_units"), e.get("n_profiles"),
                       e.get("train_rmse_mm"), e.get("fit_rmse_mm"), e.get("depth_scale_mm"), e.get("model_hash"),
                       e.get("mirror"), json.dumps(e["support"]) if isinstance(e.get("support"), dict)
                       else e.get("support"), e.get("depth_bounds_mm"), e.get("problem")] for e in errs])
    else:
        out += _not_yet("no region model has been trained")
    return out


def _per_region(figs: _Figures, data: ReportData, name: str, build: Callable[[ReportData, int], Any],
                missing: str) -> str:
    regions = _regions_with_profiles(data)
    if not regions:
        return _not_yet(missing)
    return "".join(f"<h3>Region {r}</h3>" + figs.img(f"{name} region {r}", lambda r=r: build(data, r),
                                                     f"{missing} (region {r})") for r in regions)


def _section_profiles(figs: _Figures, data: ReportData) -> str:
    """The averaged profiles per region, with what the averaging dropped and why."""
    regions = _regions_with_profiles(data)
    if not regions:
        return _not_yet("no labelled region has measured profiles")
    out = []
    for r in regions:
        profs = [p for p in data.profiles if p.region == r]
        counted = [p for p in profs if p.rejected]
        note = ("The averaging recorded no rejection counts for these steps (measured before they were kept)."
                if not counted else
                f"The averaging of {len(counted)} steps dropped "
                f"{sum(p.rejected.get('rejected_scan_samples', 0) for p in counted)} single-scan values far from "
                f"the other scans, {sum(p.rejected.get('rejected_line_samples', 0) for p in counted)} averaged "
                f"samples standing out of their neighbours along the line, "
                f"{sum(p.rejected.get('implausible_samples', 0) for p in counted)} deeper than the tip went or "
                f"above the surface, and {sum(p.rejected.get('off_face_samples', 0) for p in counted)} off the "
                f"probed face (past a rim or onto another part).")
        out.append(f"<h3>Region {r}</h3><p>{_esc(note)}</p>"
                   + figs.img(f"profiles region {r}", lambda r=r: fig_region_profiles(data, r),
                              f"no labelled region has measured profiles (region {r})"))
    return "".join(out)


def _section_disagreement(figs: _Figures, data: ReportData) -> str:
    if not data.densify:
        return _not_yet("no densification round has been committed")
    out = []
    for view in data.densify:
        rec = view.outputs.get("record") if isinstance(view.outputs.get("record"), dict) else {}
        scores = rec.get("pair_scores")
        out.append(f"<h3>Round {view.round}</h3><p>{_esc(view.outputs.get('reason', ''))}; "
                   f"{_esc(view.outputs.get('n_new', len(view.new_points_mm)))} new targets; "
                   f"pair scores (model distance / noise): {_esc(json.dumps(scores) if scores else 'not recorded')}</p>")
        out.append(figs.img(f"disagreement round {view.round}", lambda v=view: fig_disagreement(data, v),
                            "this round recorded nothing to draw"))
    return "".join(out)


def _section_training(figs: _Figures, data: ReportData) -> str:
    if not data.models:
        return _not_yet("no region model has been trained")
    curves = all(loss_history(m.meta) is not None for m in data.models.values())
    note = ("Loss history from the model metadata." if curves else
            "The model metadata holds no loss history: final training error per region (with the "
            "noise-based stopping goal where recorded).")
    stops = [[r, m.meta.get("training", {}).get("epochs"), m.meta.get("training", {}).get("stop_reason"),
              _round(m.meta.get("training", {}).get("train_s"), 2)] for r, m in sorted(data.models.items())]
    return (f"<p>{_esc(note)}</p>" + figs.img("training", lambda: fig_training(data), "no model")
            + _grid(["region", "epochs per member", "stop reason per member", "train time (s)"], stops))


def _section_timeline(figs: _Figures, data: ReportData) -> str:
    out = figs.img("timeline", lambda: fig_timeline(data), "no state transition with a robot time")
    tail = data.transitions[-40:]
    if tail:
        out += (f"<details><summary>last {len(tail)} of {len(data.transitions)} transitions</summary>"
                + _grid(["run", "t robot (s)", "wall (UTC)", "from", "to", "trigger", "step"],
                        [[t["run_id"], _round(t["t_robot_s"], 2) if t["t_robot_s"] is not None else None,
                          t["t_wall_utc"], t["from_state"], t["to_state"], t["trigger"], t["step_id"]] for t in tail])
                + "</details>")
    return out


def _section_faults(figs: _Figures, data: ReportData) -> str:
    if not data.faults:
        return "<p>No faults.</p>"
    out = [_grid(["#", "kind", "t robot (s)", "wall (UTC)", "step", "action", "message", "raw samples"],
                 [[f.fault_id, f.kind, _round(f.t_robot_s, 2) if f.t_robot_s is not None else None, f.t_wall_utc,
                   f.step_id, f.policy_action, f.message, 0 if f.raw is None else len(f.raw)] for f in data.faults])]
    for f in data.faults[:MAX_FAULT_TRACES]:
        out.append(f"<div class='fault'><h3 id='fault-{f.fault_id}'>Fault #{f.fault_id}: {_esc(f.kind)}</h3>")
        if f.raw is None:
            out.append("<p>No raw F/T data was journaled with this fault.</p>")
        else:
            out.append(figs.img(f"fault {f.fault_id} raw F/T", lambda f=f: fig_fault_trace(f), "empty raw data"))
        out.append("</div>")
    if len(data.faults) > MAX_FAULT_TRACES:
        out.append(f"<p>{len(data.faults) - MAX_FAULT_TRACES} more fault traces are in the journal "
                   f"(elastoprobe export DIR --format hdf5).</p>")
    return "".join(out)


def _section_provenance(data: ReportData) -> str:
    rows = []
    for key, value in sorted(data.provenance.items()):
        if isinstance(value, dict) and "text" in value:
            value = {k: v for k, v in value.items() if k != "text"}
        rows.append((key, value))
    return _table(rows) if rows else _not_yet("no provenance recorded")


def render_html(data: ReportData) -> tuple[str, list[str]]:
    """The report page for ``data`` and the figure errors met (empty when all rendered)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    figs = _Figures()
    numbers = _numbers(data)
    sections: list[tuple[str, str, str]] = [
        ("numbers", "Numbers", _section_numbers(data, numbers)),
        ("region-map", "Point cloud and sampling points by region (Fig. 7)",
         figs.img("region map", lambda: fig_region_map(data), "no point cloud has been acquired")),
        ("profiles", "Averaged profiles per region: increasing force, across angles (Figs. 8–12)",
         _section_profiles(figs, data)),
        ("measured-vs-model", "Measured versus modelled profiles (Figs. 13–17)",
         _per_region(figs, data, "measured vs model", fig_measured_vs_model, "no region model yet")
         if data.models else _not_yet("no region model has been trained")),
        ("predictions", "Predicted profiles for unseen forces and angles (Figs. 18–19)",
         _per_region(figs, data, "predictions", fig_predictions, "no region model yet")
         if data.models else _not_yet("no region model has been trained")),
        ("disagreement", "Disagreement map per densification round", _section_disagreement(figs, data)),
        ("training", "Training", _section_training(figs, data)),
        ("timeline", "Timeline of states and faults", _section_timeline(figs, data)),
        ("faults", "Faults and their raw F/T data", _section_faults(figs, data)),
        ("provenance", "Provenance", _section_provenance(data)),
    ]
    status = data.session["status"]
    head = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width'>"
            f"<title>Elastoprobe session {_esc(data.session['plan_name'])}</title><style>{_CSS}</style></head><body>"
            f"<h1>Session {_esc(data.session['plan_name'])} — {_esc(status)}</h1>"
            f"<p>{_esc(data.session_dir)} · created {_esc(data.session['created_utc'])} · "
            f"{numbers['force_steps_done']} force steps done of {sum(data.counts.values())} planned · "
            f"{numbers['robot_hours']} robot hours · {numbers['faults']} faults</p><nav>"
            + "".join(f"<a href='#{sid}'>{_esc(title.split(' (')[0])}</a>" for sid, title, _ in sections) + "</nav>")
    body = "".join(f"<section id='{sid}'><h2>{_esc(title)}</h2>{content}</section>" for sid, title, content in sections)
    return head + body + "</body></html>\n", figs.errors


def write_report(session_dir: Path) -> Path:
    """Write DIR/report/index.html from the journal (read-only; safe while a session runs)."""
    j = Journal.open_readonly(session_dir)
    try:
        data = collect(j)
    finally:
        j.close()
    page, _errors = render_html(data)
    page = readable_text(page)          # a session folder whose name is not UTF-8
    out = Path(session_dir) / "report" / "index.html"
    ensure_dir(out.parent)
    atomic_write_text(out, page)
    return out
