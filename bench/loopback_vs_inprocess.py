"""Loopback vs in-process: the same plan, seed and cell file, step by step. Prints ONE JSON object.

Runs ``elastoprobe run PLAN --cell CELL --seed S`` twice — on the real drivers against the
served world (the loopback cell; ur_rtde 1.6.5, Net F/T over UDP, the scanner over a socket)
and with ``--dry-run`` (the same cell file's limits, tool, placement and simulation, devices
simulated in process) — or takes two finished session directories (``--sessions LB IP``).
The cell is copied onto ``--host`` (a free 127.0.0.x) so the run never collides with a
served shipped cell.

Per step, matched by (phase, round, order) with the same angle and force:

- ``force``: the held force, mean over the step's scans of |scan_force_n| (the mean contact
  force around each exposure, N).
- ``depth``: the dent around the tip, per scan the mean depth over |x| <= two tip radii of
  that scan's depth profile (profiles.scan_depths against the step's own reference scans),
  then the mean over the scans (mm). Two radii, not one: the probe body hides the profile
  next to the tip from the scanner (at 90 deg x < ~2 mm, at 45 and 135 deg |x| < ~5 mm in
  both runs), so within one radius a 45/135 deg step kept at most one grid sample at the
  band's edge, and often none (its depth was NaN in both runs: counted as a disagreement).
- ``sigma``: the per-scan standard deviation within the step (ddof 1), pooled over the two
  runs (sqrt of the mean of the two variances): the scatter of one scan, which is what
  noise and regulation ripple put into each exposure. ``N``: scans per step (the smaller
  of the two). The step agrees when |loopback - in_process| <= 3 sigma / sqrt(N) (the
  bound of issue #5). ``z`` is the difference over its own standard error,
  sqrt(var_lb/N_lb + var_ip/N_ip), for reading how far inside or outside it is.
- ``peak_mm``: the peak of each run's journaled averaged profile (for reference; no bound).
- ``target_offset_mm``: distance between the two runs' probe points (0 with the shipped
  plan, which gives its point; a plan whose neural gas places targets from each run's own
  cloud presses points millimetres apart).
- ``literal_exceedances``: per quantity, on how many steps the bound failed and
  ``p_value``, the chance of at least that many among two runs of the SAME system (the bound
  is 2.12 standard errors of the difference: 3.4 % of steps by chance alone).

Why depth can miss the literal bound between identical systems: the simulated scanner (like a
real one) adds to every profile of a burst the same smooth, correlated error
(``noise_corr_floor_mm``), and the step's reference burst carries its own. Both shift the step's
mean depth and neither shows in the within-step scatter sigma, so sigma/sqrt(N) understates the
step mean's standard error. ``--scanner-corr-floor-mm 0`` runs both sides without it: the
diagnostic of the transports and drivers alone.

Noise: the two runs do not share noise keys (real devices have none), so their differences
are of the size the bound expects, not smaller.

The force loop (``force_loop``): both runs run the same supervisor (controller/core/forceloop.py)
— ``same_supervisor`` says whether the two journals' arm identities name the same code (a
hash of the module) and gains. Per backend, from each force level's ``force_regulated`` log
event (controller/probe.py, ``regulation_record``): ``overshoot_n`` (peak of the loop's own
10 ms reading minus the setpoint, over the ramp and the settle) and ``held_error_n`` (mean
|F| over the settle's last 0.5 s minus the setpoint), each as mean / mean |x| / max |x| over
the levels, and ``settle_s`` (command to DONE); ``scan_force_error_n``: mean |F| over the
scans minus the setpoint, per step, the same way. With references, each step row also gets
them under ``force_loop`` for both runs and the in-process spread (``sd`` over the seeds).

The in-process reference (``in_process_between_runs``, with ``--reference-seeds``): the same
plan in process with other seeds, i.e. the same exact devices with other noise only. Per step:
``sd`` of the step mean over the in-process runs that did the step (seed ``--seed`` included,
``runs`` of them): the step mean's real standard error, correlated noise included;
``max_pair_diff`` the largest difference between two of them, and ``within_3sd`` whether
|loopback - in_process| <= 3 sqrt(2) sd (two independent runs differ by sqrt(2) sd). It
answers "does the loopback differ from in process by more than in process differs from
itself?". ``between_runs_exceedances`` counts the misses with their chance (Student t,
runs - 1 degrees of freedom: about 2.4 % per step with 7 runs).
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binom, norm
from scipy.stats import t as student_t

ROOT = Path(__file__).resolve().parent.parent


def prepare_configs(out_dir: Path, host: str, plan: Path, cell: Path,
                    scanner_corr_floor_mm: float | None = None) -> tuple[Path, Path]:
    """Copy plan and cell into ``out_dir`` with the cell on ``host`` and absolute object paths.

    ``scanner_corr_floor_mm`` (a diagnostic): both runs' object gets this burst-correlated
    scanner noise on every material instead of its own (the diagnostic in the module docstring).
    """
    objects = ROOT / "config" / "objects"
    cell_text = cell.read_text().replace("127.0.0.2", host).replace("file: ../objects/", f"file: {objects}/")
    plan_text = plan.read_text().replace("simulated_object: ../objects/", f"simulated_object: {objects}/")
    plan_text = plan_text.replace("cell: ../cells/loopback.yaml", f"cell: {out_dir / 'cell.yaml'}")
    if scanner_corr_floor_mm is not None:
        import re

        import yaml

        name = re.search(r"^  file: (\S+)", cell_text, re.M)
        assert name is not None, "the cell names no object file"
        obj = yaml.safe_load(Path(name.group(1)).read_text())
        for material in obj.get("materials", {}).values():
            if "optical" in material:
                material["optical"]["noise_corr_floor_mm"] = float(scanner_corr_floor_mm)
        copy = out_dir / "object.yaml"
        copy.write_text(yaml.safe_dump(obj, sort_keys=False))
        cell_text = cell_text.replace(name.group(0), f"  file: {copy}")
        plan_text = re.sub(r"^simulated_object: \S+", f"simulated_object: {copy}", plan_text, flags=re.M)
    (out_dir / "cell.yaml").write_text(cell_text)
    (out_dir / "plan.yaml").write_text(plan_text)
    return out_dir / "plan.yaml", out_dir / "cell.yaml"


def run_session(plan: Path, cell: Path, out: Path, seed: int, dry_run: bool, timeout_s: float) -> dict[str, Any]:
    """One ``elastoprobe run`` in a subprocess; its exit code and wall time."""
    cmd = [sys.executable, "-m", "elastoprobe.controller.cli", "run", str(plan), "--cell", str(cell),
           "--seed", str(seed), "--out", str(out), "--quiet"] + (["--dry-run"] if dry_run else
                                                                 ["--allow-stale-calibration"])
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    return {"exit_code": proc.returncode, "wall_s": round(time.monotonic() - t0, 1),
            "stderr_tail": proc.stderr[-2000:]}


ROI_TIP_RADII = 2.0     # the depth band: |x| <= this many tip radii (see the module docstring)


def _per_scan_roi_depth(result: Any, rec: Any, cell: Any, grid: Any, tip_radius_mm: float) -> np.ndarray:
    """(S,) mean depth over |x| <= ROI_TIP_RADII tip radii of each scan (mm, NaN if the scan saw none of it)."""
    from elastoprobe.controller.learning import profiles as prof

    p = rec.plan
    point, normal, tangent = (np.asarray(v, float) for v in (p.point_mm, p.normal, p.t))
    tcp_to_scanner = cell.tool.tcp_to_scanner.pose()
    base_to_object = cell.object.base_to_object.pose()
    scans = prof.step_scan_points(result.scans_xz_mm, result.scan_pose, tcp_to_scanner, base_to_object)
    refs = prof.step_scan_points(result.reference_xz_mm, result.reference_pose, tcp_to_scanner, base_to_object)
    depths = np.asarray(prof.scan_depths(scans, point, normal, tangent, grid, refs), dtype=float)
    roi = np.abs(grid.x_mm) <= ROI_TIP_RADII * tip_radius_mm
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", category=RuntimeWarning)
            return np.nanmean(depths[:, roi], axis=1)


def session_steps(session_dir: Path) -> tuple[list[dict[str, Any]], Any]:
    """The done steps of a session with their per-scan force and ROI depth."""
    from elastoprobe.controller.core.config import load_session_inputs
    from elastoprobe.controller.journal import Journal
    from elastoprobe.controller.learning import profiles as prof

    j = Journal.open_readonly(session_dir)
    try:
        prov = j.provenance()
        plan_path = Path(prov["plan"]["path"])
        cell_path = Path(prov["cell"]["path"])
        inputs = load_session_inputs(plan_path, cell_path)
        m = inputs.plan.model
        grid = prof.ProfileGrid(span_mm=m.profile_span_mm, samples=m.profile_samples)
        out = []
        for rec in j.steps(statuses=["done"]):
            res = j.step_result(rec.plan.step_id)
            force = np.linalg.norm(np.asarray(res.scan_force_n, float), axis=1)
            depth = _per_scan_roi_depth(res, rec, inputs.cell, grid, inputs.cell.tool.tip_radius_mm)
            p = rec.plan
            out.append({"phase": rec.phase, "round": rec.round, "step_id": p.step_id, "angle_deg": p.angle_deg,
                        "force_n": p.force_n, "point_mm": np.asarray(p.point_mm, float).tolist(), "scan_force_n": force,
                        "scan_depth_mm": depth, "peak_mm": float(np.nanmax(res.profile_depth_mm))
                        if np.isfinite(res.profile_depth_mm).any() else None})
        return out, inputs
    finally:
        j.close()


def regulation_records(session_dir: Path) -> dict[int, dict[str, Any]]:
    """step id -> the last ``force_regulated`` record of that level (a retried level: its last)."""
    out: dict[int, dict[str, Any]] = {}
    log = session_dir / "log.jsonl"
    if not log.exists():
        return out
    for line in log.read_text().splitlines():
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            continue                      # a torn last line of a killed run
        if event.get("event") == "force_regulated":
            out[int(event["step"])] = event
    return out


def _spread(values: list[float]) -> dict[str, Any]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], float)
    if not v.size:
        return {"n": 0, "mean": None, "mean_abs": None, "max_abs": None}
    return {"n": int(v.size), "mean": round(float(v.mean()), 4), "mean_abs": round(float(np.abs(v).mean()), 4),
            "max_abs": round(float(np.abs(v).max()), 4)}


def force_loop_summary(session_dir: Path) -> dict[str, Any]:
    """The supervisor a session ran (its journaled arm identity) and how its force levels went."""
    from elastoprobe.controller.journal import Journal

    j = Journal.open_readonly(session_dir)
    try:
        identity = ((j.provenance().get("devices") or {}).get("arm") or {}).get("force_loop")
        done = {rec.plan.step_id: rec.plan.force_n for rec in j.steps(statuses=["done"])}
        scan_errors = [float(np.linalg.norm(np.asarray(j.step_result(sid).scan_force_n, float), axis=1).mean()) - f
                       for sid, f in done.items()]
    finally:
        j.close()
    records = [r for sid, r in regulation_records(session_dir).items() if sid in done]
    return {"identity": identity, "levels": len(records),
            "overshoot_n": _spread([r["overshoot_n"] for r in records]),
            "held_error_n": _spread([r["held_error_n"] for r in records]),
            "settle_s": _spread([r["settle_s"] for r in records]),
            "scan_force_error_n": _spread(scan_errors)}


def _stats(values: np.ndarray) -> tuple[float, float, int]:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return (float(v.mean()) if v.size else math.nan), math.nan, int(v.size)
    return float(v.mean()), float(v.std(ddof=1)), int(v.size)


def compare_quantity(lb: np.ndarray, ip: np.ndarray) -> dict[str, Any]:
    """Means, pooled per-scan sigma, N, the 3 sigma/sqrt(N) bound and whether it holds."""
    m_lb, s_lb, n_lb = _stats(lb)
    m_ip, s_ip, n_ip = _stats(ip)
    n = min(n_lb, n_ip)
    sigma = math.sqrt((s_lb ** 2 + s_ip ** 2) / 2.0) if n >= 2 else math.nan
    diff = m_lb - m_ip
    bound = 3.0 * sigma / math.sqrt(n) if n >= 2 else math.nan
    se = math.sqrt(s_lb ** 2 / n_lb + s_ip ** 2 / n_ip) if n >= 2 else math.nan
    return {"loopback": round(m_lb, 4), "in_process": round(m_ip, 4), "diff": round(diff, 4),
            "sigma_lb": round(s_lb, 4), "sigma_ip": round(s_ip, 4), "sigma": round(sigma, 4), "n": n,
            "bound": round(bound, 4), "z": round(diff / se, 2) if se and se > 0 else None,
            "within": bool(abs(diff) <= bound) if n >= 2 else False}


def compare_sessions(lb_dir: Path, ip_dir: Path) -> dict[str, Any]:
    lb, _ = session_steps(lb_dir)
    ip, _ = session_steps(ip_dir)
    key = lambda s: (s["phase"], s["round"], s["angle_deg"], s["force_n"])  # noqa: E731
    ip_by: dict[tuple, list[dict[str, Any]]] = {}
    for s in ip:
        ip_by.setdefault(key(s), []).append(s)
    rows = []
    pairs = []
    for s in lb:
        twins = ip_by.get(key(s))
        if not twins:
            continue
        t = twins.pop(0)
        pairs.append((s, t))
        rows.append({"phase": s["phase"], "round": s["round"], "angle_deg": s["angle_deg"],
                     "force_setpoint_n": s["force_n"],
                     "target_offset_mm": round(float(np.linalg.norm(np.subtract(s["point_mm"], t["point_mm"]))), 3),
                     "force": compare_quantity(s["scan_force_n"], t["scan_force_n"]),
                     "depth": compare_quantity(s["scan_depth_mm"], t["scan_depth_mm"]),
                     "peak_mm": {"loopback": s["peak_mm"], "in_process": t["peak_mm"]}})
    within = [r["force"]["within"] and r["depth"]["within"] for r in rows]
    loops = {"loopback": force_loop_summary(lb_dir), "in_process": force_loop_summary(ip_dir)}
    ident = [loops[k]["identity"] for k in loops]
    loops["same_supervisor"] = bool(ident[0] is not None and ident[0] == ident[1])
    lb_reg, ip_reg = regulation_records(lb_dir), regulation_records(ip_dir)
    for row, (s_lb, s_ip) in zip(rows, pairs):
        row["force_loop"] = {name: {q: (rec or {}).get(q) for q in ("overshoot_n", "held_error_n", "settle_s")}
                             for name, rec in (("loopback", lb_reg.get(s_lb["step_id"])),
                                               ("in_process", ip_reg.get(s_ip["step_id"])))}
    return {"force_loop": loops, "steps_loopback": len(lb), "steps_in_process": len(ip), "steps_compared": len(rows),
            "steps_within": int(sum(within)), "all_within": bool(rows) and all(within),
            "literal_exceedances": {q: exceedances([not r[q]["within"] for r in rows], [LITERAL_CHANCE] * len(rows))
                                    for q in ("force", "depth")},
            "steps": rows}


# Two runs of one system with independent per-scan noise: their step means differ by
# sigma sqrt(2/N), so the 3 sigma/sqrt(N) bound is 3/sqrt(2) = 2.12 standard errors and two
# identical systems exceed it on 3.4 % of steps (normal scatter).
LITERAL_CHANCE = 2.0 * float(norm.sf(3.0 / math.sqrt(2.0)))


def exceedances(exceeded: list[bool], chance: list[float]) -> dict[str, Any]:
    """How many of the comparisons exceeded their bound, and how likely so many are by chance.

    ``chance``: per comparison, the probability that two runs of the SAME system exceed
    it. ``p_value``: the probability of at least this many exceedances among identical
    systems (binomial, at the mean chance): a small value says the two differ beyond noise.
    """
    n, k = len(exceeded), int(sum(exceeded))
    p = float(np.mean(chance)) if chance else 0.0
    return {"exceeded": k, "comparisons": n, "chance_per_comparison": round(p, 4),
            "p_value": round(float(binom.sf(k - 1, n, p)), 4) if n else None}


def add_reference(result: dict[str, Any], ip_dir: Path, reference_dirs: list[Path]) -> None:
    """Add ``in_process_between_runs`` to each row of ``result`` (see the module docstring)."""
    key = lambda s: (s["phase"], s["round"], s["angle_deg"], s["force_n"])  # noqa: E731
    runs: list[dict[tuple, dict[str, float]]] = []
    for d in [ip_dir, *reference_dirs]:
        try:
            steps, _ = session_steps(d)
        except Exception:  # noqa: BLE001 — a reference run that aborted before its journal has no steps
            steps = []
        regulated = regulation_records(d)
        means: dict[tuple, dict[str, float]] = {}
        for st in steps:
            rec = regulated.get(st["step_id"], {})
            with np.errstate(all="ignore"):
                means.setdefault(key(st), {"force": float(np.nanmean(st["scan_force_n"])),
                                           "depth": float(np.nanmean(st["scan_depth_mm"])),
                                           "overshoot_n": _number(rec.get("overshoot_n")),
                                           "held_error_n": _number(rec.get("held_error_n"))})
        runs.append(means)
    for row in result["steps"]:
        k = (row["phase"], row["round"], row["angle_deg"], row["force_setpoint_n"])
        out: dict[str, Any] = {}
        for q in ("force", "depth"):
            vals = np.array([r[k][q] for r in runs if k in r and math.isfinite(r[k][q])])
            sd = float(vals.std(ddof=1)) if vals.size >= 2 else math.nan
            diff = row[q]["diff"]
            out[q] = {"runs": int(vals.size), "sd": round(sd, 4),
                      "max_pair_diff": round(float(vals.max() - vals.min()), 4) if vals.size >= 2 else None,
                      "within_3sd": bool(vals.size >= 3 and diff is not None and math.isfinite(diff)
                                         and abs(diff) <= 3.0 * math.sqrt(2.0) * sd)}
        for q in ("overshoot_n", "held_error_n"):
            vals = np.array([r[k][q] for r in runs if k in r and math.isfinite(r[k][q])])
            row["force_loop"][q + "_in_process_sd"] = round(float(vals.std(ddof=1)), 4) if vals.size >= 2 else None
        row["in_process_between_runs"] = out
    # diff / (sqrt(2) sd), sd from `runs` runs, is Student-t with runs - 1 degrees of freedom
    # for two runs of the same system: the chance it passes 3.
    result["between_runs_exceedances"] = {
        q: exceedances([not r["in_process_between_runs"][q]["within_3sd"] for r in result["steps"]],
                       [2.0 * float(student_t.sf(3.0, max(1, r["in_process_between_runs"][q]["runs"] - 1)))
                        for r in result["steps"]])
        for q in ("force", "depth")}
    result["steps_within_in_process_spread"] = int(sum(r["in_process_between_runs"]["force"]["within_3sd"]
                                                       and r["in_process_between_runs"]["depth"]["within_3sd"]
                                                       for r in result["steps"]))


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def _finite(value: Any) -> Any:
    """NaN/inf (a quantity a step could not measure) -> null, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plan", type=Path, default=ROOT / "config" / "plans" / "loopback.yaml")
    ap.add_argument("--cell", type=Path, default=ROOT / "config" / "cells" / "loopback.yaml")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--host", default="127.0.0.186", help="loopback address for the served cell")
    ap.add_argument("--out", type=Path, default=None, help="where the two sessions go (default: a temp dir)")
    ap.add_argument("--sessions", type=Path, nargs=2, metavar=("LOOPBACK", "IN_PROCESS"),
                    help="compare two finished sessions instead of running them")
    ap.add_argument("--timeout-s", type=float, default=900.0)
    ap.add_argument("--scanner-corr-floor-mm", type=float, default=None,
                    help="diagnostic: run both sides with this burst-correlated scanner noise on the object "
                         "(0 = none) instead of the object file's")
    ap.add_argument("--reference-seeds", type=int, nargs="*", default=[2, 3, 4, 5, 6, 7],
                    help="in-process runs with these seeds: how far the in-process steps move between runs")
    ap.add_argument("--reference-sessions", type=Path, nargs="*", default=None,
                    help="finished in-process sessions to use as that reference instead of running them")
    args = ap.parse_args(argv)
    out: dict[str, Any] = {"seed": args.seed}
    if args.sessions:
        lb_dir, ip_dir = args.sessions
    else:
        base = args.out or Path(tempfile.mkdtemp(prefix="elastoprobe-compare-"))
        base.mkdir(parents=True, exist_ok=True)
        plan, cell = prepare_configs(base, args.host, args.plan, args.cell, args.scanner_corr_floor_mm)
        lb_dir, ip_dir = base / "loopback", base / "in_process"
        out["loopback_run"] = run_session(plan, cell, lb_dir, args.seed, False, args.timeout_s)
        out["in_process_run"] = run_session(plan, cell, ip_dir, args.seed, True, args.timeout_s)
    out["sessions"] = {"loopback": str(lb_dir), "in_process": str(ip_dir)}
    out.update(compare_sessions(lb_dir, ip_dir))
    if args.reference_sessions is not None:
        refs = list(args.reference_sessions)
    else:
        refs = []
        base = args.out or Path(tempfile.mkdtemp(prefix="elastoprobe-compare-ref-"))
        base.mkdir(parents=True, exist_ok=True)
        plan_cell = (prepare_configs(base, args.host, args.plan, args.cell, args.scanner_corr_floor_mm)
                     if args.sessions else (plan, cell))
        runs = out.setdefault("reference_runs", {})
        for seed in args.reference_seeds:
            d = base / f"in_process_seed{seed}"
            runs[str(seed)] = run_session(plan_cell[0], plan_cell[1], d, seed, True, args.timeout_s)
            refs.append(d)
    if refs:
        add_reference(out, ip_dir, refs)
        out["reference_sessions"] = [str(d) for d in refs]
    print(json.dumps(_finite(out), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
