"""Benchmark: the demo on the miscalibrated cell, before and after calibration, against the calibrated cell.

For every seed in ``--seeds`` (default 1; the run's --seed drives noise only) the same plan
(default config/plans/demo.yaml) runs as CLI subprocesses on:

  (i)   ``calibrated``:        the default simulated cell (config/cells/sim.yaml: true = believed);
  (ii)  ``uncalibrated``:      a copy of config/cells/sim_miscalibrated.yaml with no calibration file
                               (the controller believes the nominal drawing; the world is off by
                               the cell's miscalibration; its placement check usually sees
                               scans and sweeps disagree and pauses, asking for calibration
                               (8 of 10 runs over 5 seeds and 2 draws; the other two mapped,
                               at 0.40 and 0.0069): reported with the reason, no map);
  (iii) ``after_calibration``: another copy of it, after ``elastoprobe calibrate ft``, ``tcp``,
                               ``scanner`` and ``object`` wrote its calibration file;

and (unless ``--no-oracle``) also

  (iv)  ``perfect_calibration``: a third copy whose calibration file holds the simulator's
                               truth (believed == true on the same physical cell as (ii)/(iii)):
                               what (iii) would score if calibration were exact.

The miscalibration is a property of the cell (simulation.miscalibration.seed in the cell
file), not of the run: one cell is ONE draw of "a miscalibrated cell". ``--cell-seeds 0,1``
makes copies of the miscalibrated cell with those cell-level seeds (each a different
direction of the payload, tip, scanner-mount and placement errors), calibrates each once
(``--calibration-seed``) and runs (ii) and (iii) on each for every seed; (iv) runs on the
first draw only (it separates calibration error from run-to-run variation; the calibration
itself is scored per draw by bench/calibration.py).

Each session is scored by ``elastoprobe evaluate DIR --json`` against the simulator's ground
truth, on the object's true top surface (the same sampled surface for every cell, so the
cells are compared on one reference; docs/generated_objects.md); the figures on each run's
own scanned cloud are kept beside them as ``cloud_*``. Printed: ONE JSON object with every
case's per-seed headline (region_map_error, worst IoU, boundary distances mean/p90,
coverage, regions found, profile RMSE, probes, robot hours, cloud_*), the
aggregate per case (per-seed values, mean, sd, standard error of the mean), and comparisons
of the means. The goal (issue #6): |mean(iii) - mean(i)| <= 10 % of mean(i), over the seeds
(and draws, pooled, when there are several). Both verdicts are printed:
``goal_met_strict`` (the issue's words) and ``goal_met_floored``, which also accepts a
difference within the NOISE FLOOR = 2 standard errors of the difference of the means: both
errors are a few square millimetres of ~110 000 (a few points of the cloud's ~40 000) and
swing by more than 10 % between equivalent runs, so a smaller difference cannot be
resolved by these seeds. The strict
figure is never hidden. Issue 16 restates the goal (``goal_restated_met``): after calibration
within max(10 %, the noise floor) of an exact calibration of the same cell (iii against
(iv)), and on the truth surface within the same margin of the calibrated cell (iii against
(i)); both are the ``floored`` verdicts of those comparisons.

Caveat on the boundary distances: the scored top of the composite is the box's top and the
pillow; the box's walls are too steep to probe and are not scored, so the two materials do
not meet on it. A map that draws no boundary across a face scores 0 there, one that does
scores None (no true boundary to measure against): read them with region_map_error and
IoU, not alone.

Every run is a CLI subprocess (what a user types). ``--out DIR`` keeps the cells and sessions
(default: a new temporary folder; sessions in DIR/seedN/CASE[_drawD]); ``--reuse`` skips a
run whose session already finished there and a calibration already complete. A demo run
takes about a minute of wall time here, a calibration a few minutes per cell.
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

import numpy as np

# Run as a script (python bench/NAME.py) the repository's root is not on the path; the
# benches' shared helpers are imported as the package they are.
if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench import cli_runs  # noqa: E402
from elastoprobe.controller.core.yamlio import dump_yaml_text  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "config" / "plans" / "demo.yaml"
CALIBRATED_CELL = ROOT / "config" / "cells" / "sim.yaml"
MISCALIBRATED_CELL = ROOT / "config" / "cells" / "sim_miscalibrated.yaml"
GOAL_REL_DIFF = 0.10
KINDS = ("ft", "tcp", "scanner", "object")
RUN_TIMEOUT_S = 3600.0           # a demo run takes minutes; this only bounds a hung one


def cli(*args: str, timeout_s: float = RUN_TIMEOUT_S) -> subprocess.CompletedProcess:
    """``elastoprobe ARGS`` in a subprocess (bench/cli_runs.py)."""
    return cli_runs.cli(*args, timeout_s=timeout_s)


def copy_cell(src: Path, dest_dir: Path) -> Path:
    """The cell file copied into ``dest_dir``, its object path made absolute (the calibration
    file it names then lives next to the copy, never next to the shipped cell)."""
    from ruamel.yaml import YAML

    doc = YAML().load(src.read_text(encoding="utf-8"))
    doc["object"]["file"] = str((src.parent / doc["object"]["file"]).resolve())
    dest_dir.mkdir(parents=True, exist_ok=True)
    dest = dest_dir / src.name
    dest.write_text(dump_yaml_text(doc), encoding="utf-8")
    return dest


def session_status(session_dir: Path) -> dict[str, Any] | None:
    """``elastoprobe status DIR --json`` (None when there is no session)."""
    return cli_runs.session_status(session_dir, timeout_s=60.0)


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
    from elastoprobe.controller.core.calfile import calibration_path, pose_list, write_section
    from elastoprobe.controller.core.config import load_cell
    from elastoprobe.controller.core.geometry import Pose
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
    """The figures of one run: the map on the object's true top (``elastoprobe evaluate``'s top
    level), the same map on the run's scanned cloud as ``cloud_*``, profiles, probes, time."""
    ev = run["evaluation"]
    if ev is None:
        return {"status": run.get("status"), "reason": run.get("reason"), "region_map_error": None}
    keys = ("region_map_error", "mislabelled_max_from_true_boundary_mm", "worst_region_iou", "boundary_mm_mean",
            "boundary_mm_p90", "coverage", "profile_rmse_mm", "regions_found", "regions_true", "probes",
            "robot_hours")
    cloud = ev.get("cloud", {})
    cloud_keys = ("region_map_error", "mislabelled_points", "mislabelled_max_from_true_boundary_mm",
                  "worst_region_iou")
    return {**{k: ev.get(k) for k in keys}, **{f"cloud_{k}": cloud.get(k) for k in cloud_keys}}


AGG_KEYS = ("region_map_error", "mislabelled_max_from_true_boundary_mm", "worst_region_iou", "boundary_mm_mean",
            "boundary_mm_p90", "coverage", "regions_found", "cloud_region_map_error", "cloud_mislabelled_points")


def aggregate(per_seed: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """Per-seed values, mean, sample standard deviation and standard error of the mean of each
    headline figure over the seeds that produced a map (paused runs are counted, not averaged)."""
    out: dict[str, Any] = {"seeds": sorted(per_seed), "maps": 0, "paused": 0}
    done = {s: h for s, h in per_seed.items() if h.get("region_map_error") is not None}
    out["maps"], out["paused"] = len(done), len(per_seed) - len(done)
    for key in AGG_KEYS:
        vals = {s: h.get(key) for s, h in done.items()}
        xs = np.array([v for v in vals.values() if v is not None], dtype=float)
        row: dict[str, Any] = {"per_seed": vals}
        if xs.size:
            sd = float(np.std(xs, ddof=1)) if xs.size > 1 else None
            row.update(mean=round(float(xs.mean()), 7), sd=None if sd is None else round(sd, 7),
                       sem=None if sd is None else round(sd / np.sqrt(xs.size), 7),
                       min=round(float(xs.min()), 7), max=round(float(xs.max()), 7))
        out[key] = row
    return out


def compare(reference: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """Issue #6's goal on the seeds' mean region_map_error: |mean_other - mean_ref| <= 10 % of mean_ref.

    ``strict``: the issue's words. ``floored``: also met when the difference is within
    ``noise_floor`` = 2 standard errors of the difference of the two means (sqrt(sem_ref^2 +
    sem_other^2)): with errors near zero a run's map error is a handful of points and swings
    between equivalent runs by more than 10 % relative, so a difference under two standard
    errors cannot be told from none with these seeds. Both verdicts are reported; the strict
    one is the goal.
    """
    a, b = reference["region_map_error"], other["region_map_error"]
    if "mean" not in a or "mean" not in b:
        return {"strict_met": False, "floored_met": False, "why": "a case has no map to score"}
    ma, mb = a["mean"], b["mean"]
    diff = mb - ma
    rel = abs(diff) / ma if ma > 0 else None
    sem_a, sem_b = a.get("sem"), b.get("sem")
    floor = 2.0 * float(np.hypot(sem_a, sem_b)) if sem_a is not None and sem_b is not None else None
    strict = rel is not None and rel <= GOAL_REL_DIFF
    return {"mean_reference": ma, "mean_other": mb, "difference": round(diff, 7),
            "rel_diff": None if rel is None else round(rel, 4),
            "strict_goal": f"|difference| <= {GOAL_REL_DIFF} x mean_reference", "strict_met": bool(strict),
            "noise_floor": None if floor is None else round(floor, 7),
            "noise_floor_is": "2 x sqrt(sem_reference^2 + sem_other^2) over the seeds",
            "floored_met": bool(strict or (floor is not None and abs(diff) <= floor)),
            "other_no_worse_by_10pct": bool(mb <= (1.0 + GOAL_REL_DIFF) * ma)}


def restated_goal(comparisons: dict[str, Any], vs_calibrated_key: str, oracle_draw: int | None) -> dict[str, Any]:
    """Issue 16's restated goal on the truth surface's region_map_error: after calibration, within
    max(10 %, the seed-to-seed noise floor) of an exact calibration of the same cell, and within
    the same margin of the calibrated cell. "Within max(10 % of the reference, noise floor)" is
    :func:`compare`'s ``floored_met``. None without the exact-calibration case (``--no-oracle``)."""
    what = ("|mean(after) - mean(exact)| <= max(10 % of mean(exact), noise floor) on the first draw, and "
            "|mean(after) - mean(calibrated)| <= max(10 % of mean(calibrated), noise floor) (issue 16)")
    if oracle_draw is None:
        return {"goal_restated": what, "goal_restated_met": None,
                "goal_restated_why": "needs the exact-calibration case (run without --no-oracle)"}
    vs_exact = comparisons[f"after_calibration_draw{oracle_draw}_vs_perfect_calibration"]
    vs_calibrated = comparisons[vs_calibrated_key]
    return {"goal_restated": what,
            "goal_restated_met": bool(vs_exact["floored_met"] and vs_calibrated["floored_met"]),
            "goal_restated_parts": {"vs_exact_calibration": bool(vs_exact["floored_met"]),
                                    "vs_calibrated_cell": bool(vs_calibrated["floored_met"])}}


def draw_cell(src: Path, dest_dir: Path, cell_seed: int) -> Path:
    """A copy of the miscalibrated cell whose miscalibration is drawn from ``cell_seed``."""
    from ruamel.yaml import YAML

    dest = copy_cell(src, dest_dir)
    doc = YAML().load(dest.read_text(encoding="utf-8"))
    doc["simulation"]["miscalibration"]["seed"] = int(cell_seed)
    dest.write_text(dump_yaml_text(doc), encoding="utf-8")
    return dest


def calibration_complete(cell: Path) -> bool:
    """Whether the cell copy's calibration file holds all four sections (``--reuse``)."""
    path = cell.with_suffix(".calibration.json")
    if not path.exists():
        return False
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    sections = doc.get("sections", doc)
    return all(k in sections for k in KINDS)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", type=Path, default=PLAN)
    ap.add_argument("--seeds", type=cli_runs.parse_ints, default=[1],
                    help="the demo runs' seeds, e.g. 1,2,3,4,5 (noise only; the miscalibration is the cell's)")
    ap.add_argument("--seed", type=int, default=None, help="one seed (same as --seeds N)")
    ap.add_argument("--cell-seeds", type=cli_runs.parse_ints, default=None,
                    help="miscalibration draws: copies of the miscalibrated cell with these "
                         "simulation.miscalibration.seed values (default: the shipped cell's own)")
    ap.add_argument("--calibration-seed", type=int, default=0, help="seed of the calibration runs' noise")
    ap.add_argument("--out", type=Path, default=None, help="folder for the cells and sessions (default: temporary)")
    ap.add_argument("--reuse", action="store_true", help="keep sessions and calibrations that already finished in --out")
    ap.add_argument("--parallel", type=int, default=1, choices=(1, 2, 3, 4), help="demo runs at once")
    ap.add_argument("--oracle", action=argparse.BooleanOptionalAction, default=True,
                    help="also run the first miscalibration draw with its exact calibration (the simulator's truth; "
                         "the restated goal needs it; default on)")
    args = ap.parse_args(argv)
    seeds = [args.seed] if args.seed is not None else args.seeds
    t0 = time.perf_counter()
    out = args.out or Path(tempfile.mkdtemp(prefix="calibrated_demo_"))
    out.mkdir(parents=True, exist_ok=True)
    from ruamel.yaml import YAML

    shipped_draw = int(YAML().load(MISCALIBRATED_CELL.read_text(encoding="utf-8"))
                       ["simulation"]["miscalibration"]["seed"])
    draws = args.cell_seeds if args.cell_seeds is not None else [shipped_draw]

    # Cells first, then every calibration, before any demo starts, so that the runs start
    # together on the same code.
    cells: dict[int, dict[str, Path]] = {}
    calibrations: dict[int, Any] = {}
    for draw in draws:
        base = out / "cells" / f"draw{draw}"
        cells[draw] = {"uncalibrated": draw_cell(MISCALIBRATED_CELL, base / "uncalibrated", draw),
                       "calibrated": draw_cell(MISCALIBRATED_CELL, base / "calibrated", draw)}
        if args.reuse and calibration_complete(cells[draw]["calibrated"]):
            calibrations[draw] = {k: {"written": str(cells[draw]["calibrated"].with_suffix(".calibration.json")),
                                      "result": "reused"} for k in KINDS}
        else:
            calibrations[draw] = calibrate(cells[draw]["calibrated"], args.calibration_seed)
        if args.oracle and draw == draws[0]:
            cells[draw]["perfect"] = draw_cell(MISCALIBRATED_CELL, base / "perfect", draw)
            if not (args.reuse and calibration_complete(cells[draw]["perfect"])):
                write_perfect_calibration(cells[draw]["perfect"])

    jobs_spec: list[tuple[str, int | None, int, Path]] = []     # (case, draw, seed, cell)
    for seed in seeds:
        jobs_spec.append(("calibrated", None, seed, CALIBRATED_CELL))
        for draw in draws:
            jobs_spec.append(("uncalibrated", draw, seed, cells[draw]["uncalibrated"]))
            jobs_spec.append(("after_calibration", draw, seed, cells[draw]["calibrated"]))
            if "perfect" in cells[draw]:
                jobs_spec.append(("perfect_calibration", draw, seed, cells[draw]["perfect"]))

    def session_dir(case: str, draw: int | None, seed: int) -> Path:
        return out / f"seed{seed}" / (case if draw is None else f"{case}_draw{draw}")

    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        futures = {(case, draw, seed): pool.submit(run_demo, args.plan, cell, session_dir(case, draw, seed), seed,
                                                   args.reuse)
                   for case, draw, seed, cell in jobs_spec}
        runs = {key: f.result() for key, f in futures.items()}

    def case_name(case: str, draw: int | None) -> str:
        return case if draw is None else f"{case}_draw{draw}"

    per_case: dict[str, dict[int, dict[str, Any]]] = {}
    for (case, draw, seed), run in runs.items():
        per_case.setdefault(case_name(case, draw), {})[seed] = headline(run)
    agg = {name: aggregate(rows) for name, rows in per_case.items()}
    # Every draw's after-calibration seeds pooled: "a miscalibrated cell" over the draws.
    pooled = {f"{seed}/draw{draw}": per_case[case_name('after_calibration', draw)][seed]
              for draw in draws for seed in seeds}
    agg_pooled = aggregate({i: h for i, h in enumerate(pooled.values())})
    agg_pooled["seeds"] = list(pooled)
    comparisons: dict[str, Any] = {
        f"after_calibration_draw{d}_vs_calibrated": compare(agg["calibrated"], agg[case_name("after_calibration", d)])
        for d in draws}
    if len(draws) > 1:
        comparisons["after_calibration_all_draws_vs_calibrated"] = compare(agg["calibrated"], agg_pooled)
    if args.oracle:
        for d in draws[:1]:
            comparisons[f"after_calibration_draw{d}_vs_perfect_calibration"] = compare(
                agg[case_name("perfect_calibration", d)], agg[case_name("after_calibration", d)])
            comparisons[f"perfect_calibration_draw{d}_vs_calibrated"] = compare(
                agg["calibrated"], agg[case_name("perfect_calibration", d)])
    goal_key = ("after_calibration_all_draws_vs_calibrated" if len(draws) > 1
                else f"after_calibration_draw{draws[0]}_vs_calibrated")
    codes = {f"{case_name(c, d)}/seed{s}": r["code"] for (c, d, s), r in runs.items()}
    code_list = list(codes.values())
    result = {
        "plan": str(args.plan), "seeds": seeds, "miscalibration_draws": draws, "out": str(out),
        "figure": "region_map_error (mislabelled area fraction of the object's true top within the plan's tilt and "
                  "the arm's reach; cloud_region_map_error: the same over the run's scanned cloud)",
        "per_seed": {name: {str(s): h for s, h in sorted(rows.items())} for name, rows in per_case.items()},
        "aggregate": {**agg, **({"after_calibration_all_draws": agg_pooled} if len(draws) > 1 else {})},
        "comparisons": comparisons,
        "goal": f"|mean(after) - mean(calibrated)| / mean(calibrated) <= {GOAL_REL_DIFF} (issue #6), "
                f"over the seeds{' and draws' if len(draws) > 1 else ''}",
        "goal_comparison": goal_key,
        "goal_met_strict": comparisons[goal_key]["strict_met"],
        "goal_met_floored": comparisons[goal_key]["floored_met"],
        **restated_goal(comparisons, goal_key, draws[0] if args.oracle else None),
        "calibration": {f"draw{d}": c for d, c in calibrations.items()},
        "wall_time_s": {"runs": {f"{case_name(c, d)}/seed{s}": r["wall_time_s"] for (c, d, s), r in runs.items()},
                        "total": round(time.perf_counter() - t0, 1)},
        "code": codes,
        "same_code": bool(all(c == code_list[0] and c is not None and not c.get("dirty") for c in code_list)),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
