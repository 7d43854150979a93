"""Benchmark: the demo on the miscalibrated cell, before and after calibration, against the calibrated cell.

Three sessions of the same plan and seed (default config/plans/demo.yaml, seed 1):

  (i)   ``calibrated``:        the default simulated cell (config/cells/sim.yaml: true = believed);
  (ii)  ``uncalibrated``:      a copy of config/cells/sim_miscalibrated.yaml with no calibration file
                               (the controller believes the nominal drawing; the world is off by
                               the cell's miscalibration; the controller may notice — its
                               placement check sees scans and sweeps disagree — and pause,
                               asking for calibration: reported with the reason, no map);
  (iii) ``after_calibration``: another copy of it, after ``elastoprobe calibrate ft``, ``tcp``,
                               ``scanner`` and ``object`` wrote its calibration file.

and with ``--oracle`` also

  (iv)  ``perfect_calibration``: a third copy whose calibration file holds the simulator's
                               truth (believed == true on the same physical cell as (ii)/(iii)):
                               what (iii) would score if calibration were exact.

Each is scored by ``elastoprobe evaluate DIR --json`` against the simulator's ground truth.
The goal (issue #6): (iii)'s ``region_map_error`` (the mislabelled fraction of the reachable
scanned surface) within 10 % of (i)'s, relative: |e_iii - e_i| / e_i <= 0.10.

Prints ONE JSON object: the three evaluations (region_map_error, worst IoU, boundary
distances, profile RMSE, ...), the calibration summaries, the relative difference, the
goal and whether it is met, and wall times. Every run is a CLI subprocess (what a user
types). ``--out DIR`` keeps the sessions (default: a new temporary folder); ``--reuse``
skips a run whose session already finished in DIR. A demo run takes minutes.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "config" / "plans" / "demo.yaml"
CALIBRATED_CELL = ROOT / "config" / "cells" / "sim.yaml"
MISCALIBRATED_CELL = ROOT / "config" / "cells" / "sim_miscalibrated.yaml"
GOAL_REL_DIFF = 0.10
KINDS = ("ft", "tcp", "scanner", "object")
RUN_TIMEOUT_S = 3600.0           # a demo run takes minutes; this only bounds a hung one


def cli(*args: str, timeout_s: float = RUN_TIMEOUT_S) -> subprocess.CompletedProcess:
    """``elastoprobe ARGS`` in a subprocess (the installed entry point's module)."""
    cmd = [sys.executable, "-m", "elastoprobe.controller.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT,
                          stdin=subprocess.DEVNULL)


def copy_cell(src: Path, dest_dir: Path) -> Path:
    """The cell file copied into ``dest_dir``, its object path made absolute (the calibration
    file it names then lives next to the copy, never next to the shipped cell)."""
    from ruamel.yaml import YAML

    yaml = YAML()
    doc = yaml.load(src.read_text(encoding="utf-8"))
    doc["object"]["file"] = str((src.parent / doc["object"]["file"]).resolve())
    dest_dir.mkdir(parents=True, exist_ok=True)
    dest = dest_dir / src.name
    with dest.open("w", encoding="utf-8") as f:
        yaml.dump(doc, f)
    return dest


def session_status(session_dir: Path) -> dict[str, Any] | None:
    """``elastoprobe status DIR --json`` (None when there is no session)."""
    if not (session_dir / "journal.sqlite").exists():
        return None
    proc = cli("status", str(session_dir), "--json", timeout_s=60.0)
    try:
        return json.loads(proc.stdout) if proc.returncode == 0 else None
    except json.JSONDecodeError:
        return None


def session_done(session_dir: Path) -> bool:
    st = session_status(session_dir)
    return st is not None and st.get("status") == "done"


def paused_record(session_dir: Path, cell: Path, t0: float) -> dict[str, Any]:
    """A run that paused instead of finishing (e.g. the controller noticed the cell's calibration
    is off and asked for it): no map to evaluate; the reason, from the session's status."""
    st = session_status(session_dir) or {}
    return {"session": str(session_dir), "cell": str(cell), "status": st.get("status"),
            "reason": st.get("status_reason"), "code": session_code(session_dir),
            "wall_time_s": round(time.perf_counter() - t0, 1), "evaluation": None}


def run_demo(plan: Path, cell: Path, out: Path, seed: int, reuse: bool) -> dict[str, Any]:
    """Run the plan on the cell (unless ``reuse`` and it finished already); its evaluation."""
    t0 = time.perf_counter()
    ran = False
    status = session_status(out) if reuse else None
    if status is not None and status.get("status") == "paused":
        return paused_record(out, cell, t0)
    if not (status is not None and status.get("status") == "done"):
        if out.exists() and any(out.iterdir()):
            raise SystemExit(f"{out} exists and is not a finished session: remove it or pick another --out")
        proc = cli("run", str(plan), "--cell", str(cell), "--out", str(out), "--seed", str(seed), "--quiet")
        if proc.returncode == 3:          # paused (resumable): report why, nothing to evaluate
            return paused_record(out, cell, t0)
        if proc.returncode != 0:
            raise SystemExit(f"run on {cell} exited {proc.returncode}: {proc.stderr.strip()[-2000:]}")
        ran = True
    ev = cli("evaluate", str(out), "--json", timeout_s=1800.0)
    if ev.returncode != 0:
        raise SystemExit(f"evaluate {out} exited {ev.returncode}: {ev.stderr.strip()[-2000:]}")
    return {"session": str(out), "cell": str(cell), "status": "done", "ran_now": ran, "code": session_code(out),
            "wall_time_s": round(time.perf_counter() - t0, 1), "evaluation": json.loads(ev.stdout)}


def session_code(session_dir: Path) -> Any:
    """The git revision (and dirty flag) a session ran with, from its provenance: runs are
    comparable only on the same code (the tree is shared with engineers committing)."""
    import sqlite3

    con = sqlite3.connect(f"file:{session_dir / 'journal.sqlite'}?mode=ro", uri=True)
    try:
        row = con.execute("SELECT value FROM provenance WHERE key='git'").fetchone()
    finally:
        con.close()
    return json.loads(row[0]) if row else None


def calibrate(cell: Path, seed: int) -> dict[str, Any]:
    """Run the four routines on the cell copy (tcp and scanner before object: the object sweep
    is mapped with the calibrated scanner mount); their fit summaries."""
    out: dict[str, Any] = {}
    for kind in KINDS:
        proc = cli("calibrate", kind, "--cell", str(cell), "--seed", str(seed), "--json", timeout_s=1800.0)
        if proc.returncode != 0:
            raise SystemExit(f"calibrate {kind} exited {proc.returncode}: {proc.stderr.strip()[-2000:]}")
        summary = json.loads(proc.stdout)
        out[kind] = {"written": summary.get("written"), "result": summary.get("result")}
    return out


def write_perfect_calibration(cell: Path) -> str:
    """The simulator's truth written as the cell copy's calibration file (an exact calibration;
    simulator internals, for the oracle run only). Returns the file's path."""
    from elastoprobe.calibration.calfile import calibration_path, pose_list, write_section
    from elastoprobe.controller.config import load_cell
    from elastoprobe.controller.geometry import Pose
    from elastoprobe.sim.cell import params_from_cell, true_geometry

    import numpy as np

    spec, _ = load_cell(cell)
    p = params_from_cell(spec, Path(spec.object.file))
    t = true_geometry(p)
    f2t = p.flange_to_tcp
    sections = {
        "ft": {"payload_mass_kg": t.payload_mass_kg,
               "payload_com_sensor_mm": t.tcp_to_sensor.inverse().apply(t.payload_com_mm).tolist(),
               "flange_to_sensor": pose_list(f2t.compose(t.tcp_to_sensor))},
        "tcp": {"tip_offset_mm": t.tip_offset_mm.tolist(),
                "flange_to_tcp": pose_list(f2t.compose(Pose(t.tip_offset_mm, np.eye(3))))},
        "scanner": {"flange_to_scanner": pose_list(f2t.compose(t.tcp_to_scanner))},
        "object": {"base_to_object": pose_list(t.base_to_object)},
    }
    path = calibration_path(spec, cell)
    for kind, result in sections.items():
        write_section(path, spec.name, kind, result, {"oracle": "the simulator's truth"}, "", )
    return str(path)


def headline(run: dict[str, Any]) -> dict[str, Any]:
    ev = run["evaluation"]
    if ev is None:
        return {"status": run.get("status"), "reason": run.get("reason"), "region_map_error": None}
    keys = ("region_map_error", "worst_region_iou", "boundary_mm_mean", "boundary_mm_p90", "profile_rmse_mm",
            "regions_found", "regions_true", "probes", "robot_hours")
    return {k: ev.get(k) for k in keys}


def compare(calibrated: float | None, after: float | None) -> dict[str, Any]:
    """The goal: |after - calibrated| / calibrated <= 10 % (None when a figure is missing)."""
    if calibrated is None or after is None or calibrated <= 0.0:
        return {"rel_diff": None, "met": False}
    rel = abs(after - calibrated) / calibrated
    return {"rel_diff": round(rel, 4), "met": bool(rel <= GOAL_REL_DIFF)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", type=Path, default=PLAN)
    ap.add_argument("--seed", type=int, default=1, help="the runs' seed (noise); the miscalibration is the cell's")
    ap.add_argument("--calibration-seed", type=int, default=0, help="seed of the calibration runs' noise")
    ap.add_argument("--out", type=Path, default=None, help="folder for the cells and sessions (default: temporary)")
    ap.add_argument("--reuse", action="store_true", help="keep sessions that already finished in --out")
    ap.add_argument("--parallel", type=int, default=1, choices=(1, 2, 3, 4), help="demo runs at once")
    ap.add_argument("--oracle", action="store_true",
                    help="also run the miscalibrated cell with its exact calibration (the simulator's truth)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = args.out or Path(tempfile.mkdtemp(prefix="calibrated_demo_"))
    out.mkdir(parents=True, exist_ok=True)
    uncal_cell = copy_cell(MISCALIBRATED_CELL, out / "cells" / "uncalibrated")
    cal_cell = copy_cell(MISCALIBRATED_CELL, out / "cells" / "calibrated")

    # Calibrate before any demo starts, so that the runs start together on the same code.
    if args.reuse and session_done(out / "after_calibration"):
        cal: dict[str, Any] = {k: {"written": str(cal_cell.with_suffix(".calibration.json")), "result": "reused"}
                               for k in KINDS}
    else:
        cal = calibrate(cal_cell, args.calibration_seed)

    def after_calibration() -> dict[str, Any]:
        return {**run_demo(args.plan, cal_cell, out / "after_calibration", args.seed, args.reuse), "calibration": cal}

    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        jobs = {"calibrated": pool.submit(run_demo, args.plan, CALIBRATED_CELL, out / "calibrated", args.seed,
                                          args.reuse),
                "uncalibrated": pool.submit(run_demo, args.plan, uncal_cell, out / "uncalibrated", args.seed,
                                            args.reuse),
                "after_calibration": pool.submit(after_calibration)}
        if args.oracle:
            oracle_cell = copy_cell(MISCALIBRATED_CELL, out / "cells" / "perfect")

            def perfect() -> dict[str, Any]:
                written = write_perfect_calibration(oracle_cell)
                return {**run_demo(args.plan, oracle_cell, out / "perfect_calibration", args.seed, args.reuse),
                        "calibration": written}

            jobs["perfect_calibration"] = pool.submit(perfect)
        runs = {name: job.result() for name, job in jobs.items()}
    e = {name: headline(r) for name, r in runs.items()}
    result = {
        "plan": str(args.plan), "seed": args.seed, "out": str(out),
        "figure": "region_map_error (mislabelled fraction of the reachable scanned surface)",
        "evaluations": e,
        "after_vs_calibrated": compare(e["calibrated"]["region_map_error"], e["after_calibration"]["region_map_error"]),
        "uncalibrated_vs_calibrated": compare(e["calibrated"]["region_map_error"],
                                              e["uncalibrated"]["region_map_error"]),
        "goal": f"|after - calibrated| / calibrated <= {GOAL_REL_DIFF}",
        "after_no_worse_than_calibrated": bool(
            e["after_calibration"]["region_map_error"] is not None and e["calibrated"]["region_map_error"] is not None
            and e["after_calibration"]["region_map_error"]
            <= (1.0 + GOAL_REL_DIFF) * e["calibrated"]["region_map_error"]),
        "calibration": runs["after_calibration"].get("calibration"),
        "wall_time_s": {**{k: r["wall_time_s"] for k, r in runs.items()},
                        "total": round(time.perf_counter() - t0, 1)},
    }
    if "perfect_calibration" in e:
        result["after_vs_perfect_calibration"] = compare(e["perfect_calibration"]["region_map_error"],
                                                         e["after_calibration"]["region_map_error"])
    codes = [r["code"] for r in runs.values()]
    result["code"] = {k: r["code"] for k, r in runs.items()}
    result["same_code"] = bool(all(c == codes[0] and c is not None and not c.get("dirty") for c in codes))
    result["goal_met"] = result["after_vs_calibrated"]["met"]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
