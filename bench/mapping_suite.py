"""Mapping suite: generated objects mapped by the real session on the simulated cell, scored on
their true surface.

For each object of the fixed suite (``generate.suite()``: twelve painted objects, seeds
1001-1012, docs/generated_objects.md) and each run seed, what a user types:

    elastoprobe sim object --seed N --shape S --pattern P --pairs X --out OBJ --json
    elastoprobe run OBJ/plan.yaml --out OBJ/seedK --seed K --quiet
    elastoprobe evaluate OBJ/seedK --json

each a CLI subprocess (the session, its phases, its fault policy and the truth-surface
scoring are the product's own; nothing is skipped). The plan is the one ``sim object``
writes by the plan rule (controller/planrule.py): sized from the object's outline and the
cell alone, never tuned per object.

Baseline, measured in the same run: **densification off** (``densify_off``): the same
plan with ``phases.densify.rounds: 0``, same object, same seed. The session is
deterministic for a seed, so this run is the full run's exact prefix (same sweep, survey,
first regions, characterization, models) and the pair isolates what the densify rounds
bought: the map's error with and without them, and the probes and robot time they cost.
That is the question the suite's goals put to densification (a seam found where the
survey missed it); a raster survey at the same probe budget is answered, cheaper and
over more seeds, by bench/sampling_efficiency.py. By default the baseline runs on the
first seed of each object (``--baseline-seeds``; it costs about a full run each);
``vs_baseline`` pairs the runs that have both.

``--quick`` (the default tests): two small suite objects (1004: a block with a strip of a
near material; 1005: a plain block), one seed, and a short plan: the rule's plan with
units / 3 (>= 8) and no ``min_feature_mm`` (the survey it raises is the slow part),
characterization at 1 point per region, 3 angles (45, 90, 135) and the rule's smallest
and largest force, ensembles of 2 up to 300 epochs, 1 densify round of
4 points. The same change for every object (no per-object tuning); its figures say
nothing about the product's maps, only that the bench and the pipeline work.

Printed: ONE JSON object (``null``, never NaN or Infinity, where a figure was not reached):

- ``runs``: per object and seed: status (done / paused / failed / error / timeout) and
  why, regions found / true, ``region_map_error``, ``worst_region_iou``,
  ``per_region_iou``, boundary mean / p90 (mm, truth surface), coverage, probes, robot
  hours, the densify rounds' added points and reasons, wall seconds of the run and the
  evaluation; ``ceiling``: the same error and IoUs for the best map the run's cloud can
  carry (every cloud point labelled with its true region), so a small region's low IoU
  reads as the map's loss or the scan's;
- ``aggregate``: runs with regions_found == regions_true (count and fraction), median and
  worst region_map_error, lowest worst_region_iou, boundary mean / p90 (mean over runs and
  worst), coverage (mean and lowest), probes, robot hours and wall seconds (total and
  median). A run that did not map (paused, failed) has not reached any figure: it counts
  against the region count, and makes the worst error, lowest IoU and worst boundary
  ``null``; medians count it as infinitely bad (``null`` if that is the median);
  ``*_of_mapped`` give the same over the mapped runs only;
- ``goals`` (issue 16's suite goals, each with what it is computed on) and
  ``goal_reached`` (per goal, and ``all``);
- ``baseline`` (runs and aggregate, as above) and ``vs_baseline`` (paired differences);
- ``wall_s`` (the whole bench; the suite's runs alone, i.e. until the last full run
  ended; the baseline's), ``cpu_s_children``, ``workers``, ``code`` (git revision).

    python bench/mapping_suite.py [--objects 12] [--seeds 2] [--quick] [--workers 2]
        [--select 1003,1007] [--baseline densify_off|none] [--baseline-seeds 1]
        [--out DIR] [--reuse]

Sessions are kept under ``--out`` (default: a new temporary folder): OBJ = DIR/<seed>-<shape>-
<pattern>/, sessions OBJ/seedK and OBJ/seedK-densify_off. ``--reuse`` keeps objects and
finished sessions already there. Wall time depends on the machine's load (the runs of
other users share the cores); CPU seconds of the children are reported beside it.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from ruamel.yaml import YAML

# Run as a script (python bench/NAME.py) the repository's root is not on the path; the
# benches' shared helpers are imported as the package they are.
if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench import cli_runs  # noqa: E402
from elastoprobe.controller.core.yamlio import dump_yaml_text  # noqa: E402
from elastoprobe.controller.provenance import git_revision  # noqa: E402
from elastoprobe.sim import generate as gen  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RUN_TIMEOUT_S = 3 * 3600.0        # bounds a hung run only; a suite run takes minutes
QUICK_SUITE_INDICES = (3, 4)      # generate.suite(): 1004 block/strip (near pair), 1005 block/plain
BASELINE = "densify_off"
WALL_AIM_S = 1800.0               # issue 16: the default suite (12 x 2) in under 30 minutes on the 2-core machine

# Issue 16's goals for the suite, and what each is computed on.
GOALS: dict[str, dict[str, Any]] = {
    "regions_true_fraction": {"at_least": 0.90, "on": "fraction of runs with regions_found == regions_true"},
    "median_region_map_error": {"at_most": 0.02, "on": "median over runs (an unmapped run counts as infinite)"},
    "worst_region_map_error": {"at_most": 0.05, "on": "every run (null if a run did not map)"},
    "lowest_worst_region_iou": {"at_least": 0.80, "on": "every run (null if a run did not map)"},
    "boundary_mm_mean": {"at_most": 3.0, "on": "mean over runs of each run's boundary_mm_mean (truth surface; "
                                                "null if a run drew no boundary where the truth has one)"},
    "lowest_coverage": {"at_least": 0.98, "on": "every run: fraction of the reachable true top within 2 mm "
                                                 "of the cloud"},
}


# --------------------------------------------------------------------------- the CLI

def cli(*args: str, timeout_s: float = RUN_TIMEOUT_S, env: dict[str, str] | None = None
        ) -> subprocess.CompletedProcess:
    """``elastoprobe ARGS`` in a subprocess (bench/cli_runs.py)."""
    return cli_runs.cli(*args, timeout_s=timeout_s, env=env)


def last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][-500:] if lines else ""


def child_env(workers: int) -> dict[str, str]:
    """Children's environment: with several runs at once each keeps to one BLAS/OpenMP thread
    (the cores are shared already; the session's training is single-threaded anyway)."""
    env = dict(os.environ)
    if workers > 1:
        for key in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env[key] = "1"
    return env


# --------------------------------------------------------------------------- objects and plans

@dataclass(frozen=True)
class SuiteObject:
    """One generated object on disk: its suite entry, folder, ``sim object`` summary and plans."""

    entry: Any                    # generate.SuiteEntry
    folder: Path
    summary: dict[str, Any]

    @property
    def label(self) -> str:
        return f"{self.entry.seed}-{self.entry.shape}-{self.entry.pattern}"

    def plan(self, variant: str) -> Path:
        return self.folder / ("plan.yaml" if variant == "rule" else f"plan_{variant}.yaml")


def make_object(entry: Any, out: Path, reuse: bool, env: dict[str, str]) -> SuiteObject:
    """``elastoprobe sim object`` for a suite entry (kept when ``reuse`` and already written)."""
    folder = out / f"{entry.seed}-{entry.shape}-{entry.pattern}"
    summary_path = folder / "summary.json"
    if reuse and summary_path.exists() and (folder / "plan.yaml").exists():
        return SuiteObject(entry, folder, json.loads(summary_path.read_text(encoding="utf-8")))
    proc = cli("sim", "object", *entry.cli_args(), "--out", str(folder), "--json", timeout_s=1800.0, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"sim object {' '.join(entry.cli_args())} exited {proc.returncode}: "
                         f"{proc.stderr.strip()[-2000:]}")
    summary = json.loads(proc.stdout)
    summary_path.write_text(json.dumps(summary), encoding="utf-8")
    return SuiteObject(entry, folder, summary)


def quick_plan(plan: dict[str, Any]) -> dict[str, Any]:
    """The short plan of ``--quick``: the same change for every object (module docstring)."""
    plan["sampling"]["units"] = max(8, int(plan["sampling"]["units"]) // 3)
    plan["sampling"].pop("min_feature_mm", None)    # the raised survey is 4-7x the units: not quick
    ch = plan["phases"]["characterize"]
    forces = list(ch["forces_n"])
    ch["points_per_region"] = 1
    ch["angles_deg"] = [45.0, 90.0, 135.0]
    ch["forces_n"] = [forces[0], forces[-1]]
    plan["phases"]["densify"]["rounds"] = 1
    plan["phases"]["densify"]["points_per_round"] = 4
    plan["model"]["ensemble"] = 2
    plan["model"]["max_epochs"] = 300
    return plan


def densify_off(plan: dict[str, Any]) -> dict[str, Any]:
    """The baseline's plan: the same with no densify round."""
    plan["phases"]["densify"]["rounds"] = 0
    return plan


def write_variant(source: Path, dest: Path, change: Any, why: str) -> Path:
    """``dest``: the plan at ``source`` with ``change(plan dict)`` applied, a header saying why."""
    doc = YAML().load(source.read_text(encoding="utf-8"))
    change(doc)
    dest.write_text(f"# {why}: bench/mapping_suite.py from {source.name} (the plan rule's plan)\n"
                    + dump_yaml_text(doc), encoding="utf-8")
    return dest


# --------------------------------------------------------------------------- one run

@dataclass(frozen=True)
class Job:
    obj: SuiteObject
    seed: int
    variant: str                  # "full" (the plan as the rule wrote it, or its quick form) or BASELINE

    @property
    def session(self) -> Path:
        return self.obj.folder / (f"seed{self.seed}" if self.variant == "full" else f"seed{self.seed}-{self.variant}")


def session_status(session_dir: Path) -> dict[str, Any] | None:
    """``elastoprobe status DIR --json`` (None when there is no session)."""
    return cli_runs.session_status(session_dir)


def densify_rounds(session_dir: Path) -> list[dict[str, Any]]:
    """The session's densify rounds from its log: points added and the reason given."""
    log = session_dir / "log.jsonl"
    if not log.exists():
        return []
    out = []
    for line in log.read_text(encoding="utf-8").splitlines():
        try:
            e = json.loads(line)
        except json.JSONDecodeError:
            continue
        if e.get("event") == "phase" and e.get("name") == "densify":
            out.append({"round": e.get("round"), "new_targets": e.get("new_targets"), "reason": e.get("reason")})
    return out


RUN_KEYS = ("regions_found", "regions_true", "region_map_error", "worst_region_iou", "per_region_iou",
            "boundary_mm_mean", "boundary_mm_p90", "coverage", "probes", "robot_hours")


def run_job(job: Job, plan: Path, reuse: bool, env: dict[str, str], t0: float) -> dict[str, Any]:
    """Run one session and evaluate it; a record of what happened (never raises for a run that
    paused or failed: that is a result)."""
    e = job.obj.entry
    rec: dict[str, Any] = {"object": job.obj.label, "object_seed": e.seed, "name": job.obj.summary.get("name"),
                           "seed": job.seed, "variant": job.variant, "session": str(job.session),
                           "status": None, "reason": None, **{k: None for k in RUN_KEYS}}
    started = time.perf_counter()
    status = session_status(job.session) if reuse else None
    ran = False
    if not (status is not None and status.get("status") == "done"):
        if job.session.exists() and any(job.session.iterdir()):
            if not reuse:
                raise SystemExit(f"{job.session} exists: remove it, pick another --out, or --reuse")
            status = status or {}
        else:
            try:
                proc = cli("run", str(plan), "--out", str(job.session), "--seed", str(job.seed), "--quiet", env=env)
            except subprocess.TimeoutExpired:
                rec.update(status="timeout", reason=f"the run took longer than {RUN_TIMEOUT_S:.0f} s")
                return _finish(rec, started, t0, None)
            ran = True
            status = session_status(job.session) or {}
            if proc.returncode == 2:
                rec.update(status="error", reason=f"bad input: {last_line(proc.stderr)}")
                return _finish(rec, started, t0, None)
            if proc.returncode not in (0, 1, 3):
                rec.update(status="error", reason=f"exit {proc.returncode}: {last_line(proc.stderr)}")
                return _finish(rec, started, t0, None)
    rec["ran_now"] = ran
    run_s = time.perf_counter() - started
    if status.get("status") != "done":
        steps = status.get("steps") or {}
        rec.update(status={"paused": "paused", "created": "killed"}.get(status.get("status"), "failed"),
                   reason=status.get("status_reason") or status.get("status"),
                   probes=steps.get("done"), robot_hours=status.get("robot_hours"))
        return _finish(rec, started, t0, run_s)
    ev = cli("evaluate", str(job.session), "--json", timeout_s=3600.0, env=env)
    if ev.returncode != 0:
        rec.update(status="error", reason=f"evaluate exited {ev.returncode}: {last_line(ev.stderr)}")
        return _finish(rec, started, t0, run_s)
    result = json.loads(ev.stdout)
    rec.update({k: result.get(k) for k in RUN_KEYS}, status="done",
               uncovered_area_mm2=(result.get("truth_surface") or {}).get("uncovered_area_mm2"),
               ceiling=_ceiling(result.get("map_ceiling") or {}),
               densify=densify_rounds(job.session))
    return _finish(rec, started, t0, run_s)


def _ceiling(found: dict[str, Any]) -> dict[str, Any]:
    """The best map the run's cloud can carry (``elastoprobe evaluate``'s ``map_ceiling``):
    its error, worst IoU and per-region IoU, beside which the run's own say what the map lost."""
    return {k: found.get(k) for k in ("region_map_error", "worst_region_iou", "per_region_iou")}


def _finish(rec: dict[str, Any], started: float, t0: float, run_s: float | None) -> dict[str, Any]:
    now = time.perf_counter()
    rec["wall_s"] = round(now - started, 1)
    rec["run_wall_s"] = None if run_s is None else round(run_s, 1)
    rec["evaluate_wall_s"] = None if run_s is None else round(now - started - run_s, 1)
    rec["ended_at_s"] = round(now - t0, 1)          # since the bench started (the suite's wall time)
    return rec


# --------------------------------------------------------------------------- aggregates

def _as_inf(values: list[float | None], bad: float) -> np.ndarray:
    """Values with None (not reached) as ``bad`` (+inf or -inf)."""
    return np.array([bad if v is None else float(v) for v in values], dtype=float)


def _finite(x: float) -> float | None:
    return round(float(x), 6) if math.isfinite(x) else None


def _median(values: list[float | None], bad: float = math.inf) -> float | None:
    return _finite(float(np.median(_as_inf(values, bad)))) if values else None


def _extreme(values: list[float | None], worst_is_max: bool) -> float | None:
    if not values:
        return None
    v = _as_inf(values, math.inf if worst_is_max else -math.inf)
    return _finite(float(v.max() if worst_is_max else v.min()))


def _mean(values: list[float | None]) -> float | None:
    if not values or any(v is None for v in values):
        return None
    return _finite(float(np.mean(values)))


def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The suite's figures over ``runs`` (module docstring: how unmapped runs count)."""
    mapped = [r for r in runs if r["status"] == "done"]

    def col(key: str, rows: list[dict[str, Any]]) -> list[Any]:
        return [r.get(key) for r in rows]

    match = sum(1 for r in mapped if r["regions_found"] == r["regions_true"])
    # A run that did not map reached no figure: every per-run figure is None for it.
    err, iou = col("region_map_error", runs), col("worst_region_iou", runs)
    bmean, bp90, cov = col("boundary_mm_mean", runs), col("boundary_mm_p90", runs), col("coverage", runs)
    probes = [r["probes"] for r in runs if r["probes"] is not None]
    hours = [r["robot_hours"] for r in runs if r["robot_hours"] is not None]
    walls = [r["wall_s"] for r in runs]
    by_status: dict[str, int] = {}
    for r in runs:
        by_status[r["status"]] = by_status.get(r["status"], 0) + 1
    return {
        "runs": len(runs), "mapped": len(mapped), "by_status": by_status,
        "not_mapped": [{"object": r["object"], "seed": r["seed"], "status": r["status"], "reason": r["reason"]}
                       for r in runs if r["status"] != "done"],
        "regions_true_runs": match,
        "regions_true_fraction": _finite(match / len(runs)) if runs else None,
        "median_region_map_error": _median(err),
        "worst_region_map_error": _extreme(err, True),
        "worst_region_map_error_of_mapped": _extreme(col("region_map_error", mapped), True),
        "lowest_worst_region_iou": _extreme(iou, False),
        "lowest_worst_region_iou_of_mapped": _extreme(col("worst_region_iou", mapped), False),
        "boundary_mm_mean": _mean(bmean),
        "boundary_mm_mean_worst": _extreme(bmean, True),
        "boundary_mm_p90_mean": _mean(bp90),
        "boundary_mm_p90_worst": _extreme(bp90, True),
        "coverage_mean": _mean(cov),
        "lowest_coverage": _extreme(cov, False),
        "probes_total": int(sum(probes)), "probes_median": _median(probes),
        "robot_hours_total": _finite(float(sum(hours))), "robot_hours_median": _median(hours),
        "wall_s_total": _finite(float(sum(walls))), "wall_s_median": _median(walls),
    }


def goal_reached(agg: dict[str, Any]) -> dict[str, bool]:
    out: dict[str, bool] = {}
    for key, goal in GOALS.items():
        v = agg.get(key)
        if v is None:
            out[key] = False
        elif "at_most" in goal:
            out[key] = bool(v <= goal["at_most"])
        else:
            out[key] = bool(v >= goal["at_least"])
    out["all"] = all(out.values())
    return out


def paired(full: list[dict[str, Any]], base: list[dict[str, Any]]) -> dict[str, Any]:
    """Each (object, seed) that has both runs mapped: what the densify rounds changed."""
    by_key = {(r["object"], r["seed"]): r for r in base}
    pairs = []
    for r in full:
        b = by_key.get((r["object"], r["seed"]))
        if b is None:
            continue
        row: dict[str, Any] = {"object": r["object"], "seed": r["seed"], "status": r["status"],
                               "baseline_status": b["status"]}
        if r["status"] == b["status"] == "done":
            row.update(region_map_error=r["region_map_error"], baseline_region_map_error=b["region_map_error"],
                       error_change=_finite(r["region_map_error"] - b["region_map_error"]),
                       regions=[r["regions_found"], b["regions_found"], r["regions_true"]],
                       probes_added=r["probes"] - b["probes"],
                       robot_hours_added=_finite(r["robot_hours"] - b["robot_hours"]))
        pairs.append(row)
    both = [p for p in pairs if "error_change" in p]
    eps = 1e-6           # a change below a few mm^2 in 1e5 is a tie
    return {
        "pairs": pairs,
        "compared": len(both),
        "densify_lowered_error": sum(1 for p in both if p["error_change"] < -eps),
        "densify_raised_error": sum(1 for p in both if p["error_change"] > eps),
        "unchanged": sum(1 for p in both if abs(p["error_change"]) <= eps),
        "median_error_change": _median([p["error_change"] for p in both]) if both else None,
        "median_probes_added": _median([p["probes_added"] for p in both]) if both else None,
        "regions_true_full": sum(1 for p in both if p["regions"][0] == p["regions"][2]),
        "regions_true_baseline": sum(1 for p in both if p["regions"][1] == p["regions"][2]),
    }


# --------------------------------------------------------------------------- main

def positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {v}")
    return v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--objects", type=positive, default=12, help="the suite's first N objects (generate.suite(N))")
    ap.add_argument("--select", type=cli_runs.parse_ints, default=None,
                    help="only these suite objects, by object seed (e.g. 1003,1007)")
    ap.add_argument("--seeds", type=positive, default=2, help="run seeds per object")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true",
                    help="objects 1004 and 1005, one seed, a short plan (the default tests' run)")
    ap.add_argument("--workers", type=positive, default=2, help="sessions at once (processes)")
    ap.add_argument("--baseline", choices=(BASELINE, "none"), default=BASELINE)
    ap.add_argument("--baseline-seeds", type=int, default=1,
                    help="baseline runs on each object's first K seeds (0: none; default 1)")
    ap.add_argument("--out", type=Path, default=None, help="folder for objects and sessions (default: temporary)")
    ap.add_argument("--reuse", action="store_true", help="keep objects and finished sessions already in --out")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    out = args.out or Path(tempfile.mkdtemp(prefix="mapping_suite_"))
    out.mkdir(parents=True, exist_ok=True)
    if args.quick:
        everything = gen.suite(max(QUICK_SUITE_INDICES) + 1)
        entries = [everything[i] for i in QUICK_SUITE_INDICES]
        args.seeds = 1
    else:
        entries = gen.suite(args.objects)
    if args.select is not None:
        unknown = sorted(set(args.select) - {e.seed for e in entries})
        if unknown:
            ap.error(f"--select: {unknown} not among the suite's objects {[e.seed for e in entries]}")
        entries = [e for e in entries if e.seed in args.select]
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    baseline_seeds = seeds[:max(0, args.baseline_seeds)] if args.baseline != "none" else []
    env = child_env(args.workers)

    with ThreadPoolExecutor(max_workers=args.workers) as pool:
        objects = list(pool.map(lambda e: make_object(e, out, args.reuse, env), entries))
    for obj in objects:
        rule_plan = obj.plan("rule")
        full = (write_variant(rule_plan, obj.plan("quick"), quick_plan, "the short plan of --quick")
                if args.quick else rule_plan)
        if baseline_seeds:
            write_variant(full, obj.plan(BASELINE), densify_off, "the baseline: densification off")

    def plan_of(job: Job) -> Path:
        if job.variant == BASELINE:
            return job.obj.plan(BASELINE)
        return job.obj.plan("quick") if args.quick else job.obj.plan("rule")

    # The full runs first (their wall time is the suite's), then the baseline.
    jobs = [Job(o, s, "full") for o in objects for s in seeds]
    jobs += [Job(o, s, BASELINE) for o in objects for s in baseline_seeds]
    taken = [str(j.session) for j in jobs if not args.reuse and j.session.exists() and any(j.session.iterdir())]
    if taken:
        ap.error(f"--out: sessions already there ({', '.join(taken)}): remove them, pick another --out, or --reuse")
    prepared_s = time.perf_counter() - t0
    with ThreadPoolExecutor(max_workers=args.workers) as pool:
        results = list(pool.map(lambda j: run_job(j, plan_of(j), args.reuse, env, t0), jobs))
    full_runs = [r for r in results if r["variant"] == "full"]
    base_runs = [r for r in results if r["variant"] == BASELINE]

    agg = aggregate(full_runs)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    result: dict[str, Any] = {
        "bench": "mapping_suite",
        "quick": bool(args.quick),
        "objects": [{"object": o.label, **{k: o.summary.get(k) for k in
                                           ("name", "seed", "shape", "pattern", "pairs", "size_mm", "materials",
                                            "contrast")}}
                    for o in objects],
        "seeds": seeds,
        "plan": ("the plan rule's (controller/planrule.py), as `elastoprobe sim object` writes it"
                 + (", shortened the same way for every object (bench/mapping_suite.py quick_plan)"
                    if args.quick else "")),
        "scored_on": "elastoprobe evaluate: the object's true top within the plan's tilt, inside reach "
                     "(docs/generated_objects.md)",
        "runs": full_runs,
        "aggregate": agg,
        "goals": GOALS,
        "goal_reached": goal_reached(agg),
        "baseline": None,
        "vs_baseline": None,
        "workers": args.workers,
        "out": str(out),
    }
    if base_runs:
        result["baseline"] = {
            "what": "the same plan with phases.densify.rounds: 0 (densification off), same objects and seeds "
                    f"{baseline_seeds}",
            "why": "the session is deterministic for a seed, so this is the full run's exact prefix: the pair "
                   "isolates what the densify rounds changed in the map and what they cost",
            "runs": base_runs,
            "aggregate": aggregate(base_runs),
        }
        result["vs_baseline"] = paired(full_runs, base_runs)
    suite_end = max((r["ended_at_s"] for r in full_runs), default=prepared_s)
    result["wall_s"] = {"total": round(time.perf_counter() - t0, 1), "objects": round(prepared_s, 1),
                        "suite": round(suite_end, 1),
                        "suite_runs_sum": agg["wall_s_total"],
                        "baseline_runs_sum": _finite(float(sum(r["wall_s"] for r in base_runs)))}
    result["wall_aim"] = {"suite_s_at_most": WALL_AIM_S, "reached": bool(suite_end <= WALL_AIM_S),
                          "note": "wall time of the full runs on this machine under its load at the time "
                                  "(load_average_at_end); not a goal of the maps"}
    result["cpu_s_children"] = round(children.ru_utime + children.ru_stime, 1)
    result["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    result["code"] = git_revision()
    print(json.dumps(result, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
