"""DIR/report/index.html: a self-contained, offline-readable session report.

Figures are rendered with matplotlib (Agg) into PNGs embedded as data URIs, so the
page is one file. The report is regenerated after each phase and at the end;
it is written to a temporary name and renamed.
"""
from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_text
from .journal import Journal


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _figure_region_map(j: Journal) -> str | None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cloud = j.phase("cloud", 0)
    final = j.phase("final", 0)
    if cloud is None:
        return None
    pts = cloud.arrays["points_mm"]
    sel = np.random.default_rng(0).choice(len(pts), min(len(pts), 20000), replace=False)
    fig, ax = plt.subplots(figsize=(7, 5))
    if final is not None:
        lab = final.arrays["cloud_labels"][sel]
        sc = ax.scatter(pts[sel, 0], pts[sel, 1], c=lab, s=1, cmap="tab10", vmin=0, vmax=9)
    else:
        sc = ax.scatter(pts[sel, 0], pts[sel, 1], c=pts[sel, 2], s=1, cmap="viridis")
        fig.colorbar(sc, ax=ax, label="height (mm)")
    steps = j.steps()
    tp = {}
    for r in steps:
        tp[r.plan.target_index] = (r.plan.point_mm, r.phase)
    for idx, (p, phase) in tp.items():
        ax.plot(p[0], p[1], "k^" if phase == "characterize" else "ko", ms=4 if phase == "survey" else 7, mfc="none")
    ax.set_xlabel("x (mm, object frame)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    ax.set_title("Point cloud, regions (colour) and probed targets (o survey, ^ characterize)")
    return _png(fig)


def _figure_profiles(j: Journal) -> str | None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in j.steps(statuses=["done"]) if abs(r.plan.angle_deg - 90.0) < 1e-9]
    if not done:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    shown = 0
    first_target = done[0].plan.target_index
    for r in done:
        if r.plan.target_index != first_target:
            continue
        res = j.step_result(r.step_id)
        x = res.profile_x_mm if res.profile_x_mm is not None else np.arange(len(res.profile_depth_mm))
        ax.plot(x, -res.profile_depth_mm, label=f"{r.plan.force_n:g} N")
        shown += 1
    ax.set_xlabel("x along t (mm)")
    ax.set_ylabel("surface height change (mm)")
    ax.set_title(f"Averaged profiles at target {first_target} under increasing normal force")
    ax.legend()
    return _png(fig) if shown else None


def report_numbers(j: Journal) -> dict[str, Any]:
    sess = j.session()
    counts = j.status_counts()
    robot = j.robot_time_s()
    faults = j.faults()
    regions = None
    for r in range(50, -1, -1):
        rec = j.phase("regions", r)
        if rec is not None:
            regions = rec.outputs.get("n_regions")
            break
    return {"plan": sess["plan_name"], "seed": sess["seed"], "status": sess["status"],
            "status_reason": sess["status_reason"], "steps": counts,
            "robot_hours": round(robot["total"] / 3600.0, 3),
            "robot_time_s": {k: round(v, 1) for k, v in robot.items()},
            "faults": len(faults), "regions": regions,
            "models": j.models()}


def write_report(session_dir: Path) -> Path:
    """Write DIR/report/index.html from the journal; returns its path."""
    j = Journal.open_readonly(session_dir)
    try:
        numbers = report_numbers(j)
        figs = [("Region map", _figure_region_map(j)), ("Profiles", _figure_profiles(j))]
        faults = j.faults()
        transitions = j.transitions()
        prov = j.provenance()
    finally:
        j.close()
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>Elastoprobe session report</title>",
             "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}img{max-width:100%}</style></head><body>",
             f"<h1>Session {html.escape(str(numbers['plan']))}</h1>",
             "<h2>Numbers</h2><table>"]
    for k in ("status", "status_reason", "seed", "robot_hours", "faults", "regions"):
        parts.append(f"<tr><th>{k}</th><td>{html.escape(str(numbers[k]))}</td></tr>")
    parts.append(f"<tr><th>steps</th><td>{html.escape(json.dumps(numbers['steps']))}</td></tr>")
    parts.append(f"<tr><th>robot time (s)</th><td>{html.escape(json.dumps(numbers['robot_time_s']))}</td></tr></table>")
    for title, uri in figs:
        if uri:
            parts.append(f"<h2>{title}</h2><img alt='{title}' src='{uri}'>")
    parts.append("<h2>Faults</h2>")
    if faults:
        parts.append("<table><tr><th>#</th><th>kind</th><th>step</th><th>action</th><th>message</th></tr>")
        for f in faults:
            parts.append(f"<tr><td>{f.fault_id}</td><td>{html.escape(f.kind)}</td><td>{f.step_id}</td>"
                         f"<td>{html.escape(str(f.policy_action))}</td><td>{html.escape(f.message)}</td></tr>")
        parts.append("</table>")
    else:
        parts.append("<p>None.</p>")
    parts.append(f"<h2>Timeline</h2><p>{len(transitions)} state transitions journaled.</p>")
    parts.append("<h2>Provenance</h2><table>")
    for key in ("plan", "cell", "calibration", "git", "packages", "devices"):
        v = prov.get(key)
        if isinstance(v, dict) and "text" in v:
            v = {k: val for k, val in v.items() if k != "text"}
        parts.append(f"<tr><th>{key}</th><td><code>{html.escape(json.dumps(v))}</code></td></tr>")
    parts.append("</table></body></html>")
    out = Path(session_dir) / "report" / "index.html"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(parts))
    return out
