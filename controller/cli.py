"""The ``elastoprobe`` command line (docs/design.md §11).

Exit codes: 0 done; 1 ended in a fault or aborted; 2 bad input (``path:line:col:
message``, never a traceback); 3 paused and resumable. Heavy modules (torch, the
simulator, trimesh) are imported inside the commands so start-up stays fast.
"""
from __future__ import annotations

import argparse
import io
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Callable, Sequence

from .core.errors import ElastoprobeError, InputError

EXIT_DONE, EXIT_FAULT, EXIT_BAD_INPUT, EXIT_PAUSED = 0, 1, 2, 3


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:   # argparse's own usage errors: exit 2, no traceback
        self.print_usage(sys.stderr)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)


def _existing_dir(value: str) -> Path:
    p = Path(value)
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{value}: no such session directory")
    return p


def _output_dir(value: str) -> str:
    """A folder to create or fill: an empty name (``--out "$UNSET"``) is refused, not read as
    the default or as the current folder. (Each command says itself what it finds there.)"""
    if not value.strip():
        raise argparse.ArgumentTypeError("the folder name is empty")
    return value


def _output_file(value: str) -> Path:
    """A file to write: absent, or a regular file to replace (never a device, a pipe or a folder)."""
    if not value.strip():
        raise argparse.ArgumentTypeError("the file name is empty")
    p = Path(value)
    if p.exists() and not p.is_file():
        raise argparse.ArgumentTypeError(f"{value}: exists and is not a regular file")
    return p


def _seed(value: str) -> int:
    try:
        v = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"seed must be an integer, got {value!r}") from None
    if not 0 <= v < 2**31:
        raise argparse.ArgumentTypeError("seed must be in [0, 2^31)")
    return v


def _finite_float(value: str) -> float:
    import math
    try:
        v = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {value!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"not a finite number: {value!r}")
    return v


# --------------------------------------------------------------------------- commands
def _load_object(inputs):   # type: ignore[no-untyped-def]
    """The plan's object, loaded and checked as the session loads it; its warnings and the
    calibration's (what the session logs when it starts) on stderr."""
    from .cellfactory import calibration_warnings, load_object_model

    model = load_object_model(inputs)
    for warning in model.warnings + calibration_warnings(inputs):
        print(f"warning: {warning}", file=sys.stderr)
    return model


def cmd_check(args: argparse.Namespace) -> int:
    from .core.config import load_session_inputs
    from .estimate import estimate_plan, survey_units

    inputs = load_session_inputs(args.plan, args.cell)
    model = _load_object(inputs)
    est = estimate_plan(inputs, n_units=survey_units(inputs, model.mesh))
    budget_warning = est.budget_warning()
    report = {
        "plan": inputs.plan.name,
        "cell": inputs.cell.name,
        "contacts": est.contacts,
        "force_steps": est.steps,
        "survey_targets": est.survey_targets,
        "min_feature_mm": inputs.plan.sampling.min_feature_mm,
        "robot_hours": round(est.hours(), 3),
        "robot_s_per_phase": {k: round(v, 1) for k, v in est.per_phase_s.items()},
        "budget_warning": budget_warning,
    }
    travel = _travel_saved(inputs)
    if travel is not None:
        report["travel_mm_natural_order"], report["travel_mm_ordered"] = travel
        report["travel_saved_mm"] = round(travel[0] - travel[1], 1)
    if args.json:
        print(json.dumps(report))
    else:
        print(f"{args.plan}: valid (cell {inputs.cell.name!r})")
        print(f"  estimated robot time: {est.hours():.2f} h over {est.contacts} contacts, {est.steps} force steps")
        feature_mm = inputs.plan.sampling.min_feature_mm
        print(f"  survey: about {est.survey_targets} targets"
              + (f" (units {inputs.plan.sampling.units} raised so every {feature_mm:g} mm disc on the "
                 "probe-able top holds one: sampling.min_feature_mm)"
                 if feature_mm is not None and est.survey_targets > inputs.plan.sampling.units + len(inputs.plan.targets)
                 else ""))
        for k, v in est.per_phase_s.items():
            print(f"    {k:<13} {v / 60:7.1f} min")
        if budget_warning is not None:
            print(f"  warning: {budget_warning}")
        if travel is not None:
            print(f"  travel by ordering: {travel[0]:.0f} mm -> {travel[1]:.0f} mm "
                  f"(saved {travel[0] - travel[1]:.0f} mm)")
        elif inputs.plan.sampling.units > 0:
            print("  travel saved by ordering: known once the neural gas has placed the targets "
                  f"(the plan lists {len(inputs.plan.targets)} explicit targets)")
        else:
            print(f"  travel saved by ordering: nothing to order ({len(inputs.plan.targets)} explicit targets)")
    return EXIT_DONE


def _travel_saved(inputs) -> tuple[float, float] | None:   # type: ignore[no-untyped-def]
    import numpy as np

    from .ordering import order_targets

    if len(inputs.plan.targets) < 3:
        return None
    pts = np.array([t.point_mm for t in inputs.plan.targets])
    _, natural, ordered = order_targets(pts, travel_z_mm=float(pts[:, 2].max()) + 60.0)
    return round(natural, 1), round(ordered, 1)


def cmd_diagram(args: argparse.Namespace) -> int:
    from .core.atomic import atomic_write_text
    from .journal import refuse_session_file
    from .machine import diagram_markdown

    out = Path(args.out)
    refuse_session_file(out, "diagram --out")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, diagram_markdown())
    print(f"wrote {out}")
    return EXIT_DONE


def _default_out_dir(plan_name: str) -> Path:
    import datetime as dt

    return Path("sessions") / f"{dt.date.today().isoformat()}-{plan_name}"


def _progress_printer(quiet: bool) -> Callable[[object], None]:
    """A one-line progress display (state, target, steps, robot time, ETA) on stderr."""
    import time

    last = [0.0]
    tty = sys.stderr.isatty()

    def show(p: object) -> None:
        now = time.monotonic()
        if quiet or now - last[0] < (0.2 if tty else 5.0):
            return
        last[0] = now
        eta = p.eta_robot_s()   # type: ignore[attr-defined]
        eta_txt = f"{eta / 60:5.1f} min" if eta is not None else "   --   "
        line = (f"{p.phase:<16} {p.state:<18} target {p.target if p.target is not None else '-':>4}  "  # type: ignore[attr-defined]
                f"steps {p.steps_done}/{p.steps_total}  robot {p.robot_s / 60:6.1f} min  ETA {eta_txt}")  # type: ignore[attr-defined]
        print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)

    return show


def _run_session(inputs, out_dir: Path, seed: int, dry_run: bool, resume: bool, quiet: bool) -> int:  # type: ignore[no-untyped-def]
    from .session import Session

    model = _load_object(inputs)
    session = Session(inputs, out_dir, seed, dry_run=dry_run, on_progress=_progress_printer(quiet),
                      object_model=model)
    code = session.run(resume=resume)
    if sys.stderr.isatty() and not quiet:
        print(file=sys.stderr)
    words = {0: "done", 1: "ended in a fault or was aborted", 3: "paused; continue with: elastoprobe resume " + str(out_dir)}
    print(f"session {out_dir}: {words.get(code, code)}")
    report = out_dir / "report" / "index.html"
    if report.exists():
        print(f"report: {report}")
    return code


def cmd_run(args: argparse.Namespace) -> int:
    from .core.config import load_session_inputs

    inputs = load_session_inputs(args.plan, args.cell)
    if inputs.cell.kind != "simulated" and not args.dry_run:       # ur and loopback: the real drivers
        from .cellfactory import check_real_cell_ready
        check_real_cell_ready(inputs, allow_stale_calibration=args.allow_stale_calibration)
    seed = args.seed if args.seed is not None else inputs.plan.seed
    out = Path(args.out) if args.out else _default_out_dir(inputs.plan.name)
    return _run_session(inputs, out, seed, args.dry_run, resume=False, quiet=args.quiet)


def cmd_resume(args: argparse.Namespace) -> int:
    from .core.config import load_session_inputs
    from .journal import Journal

    j = Journal.open_readonly(args.dir, check="none")     # Journal.open checks it all before writing
    try:
        prov = j.provenance()
        session = j.session()
    finally:
        j.close()
    plan_path = prov.get("plan", {}).get("path")
    cell_path = prov.get("cell", {}).get("path")
    if not plan_path or not cell_path:
        raise InputError("the journal does not name its plan and cell files", path=str(args.dir))
    inputs = load_session_inputs(plan_path, cell_path)
    # Refused here, read-only: the session's own check comes after it opened the journal to write.
    with Journal.open_readonly(args.dir, check="none") as j:
        j.verify_inputs(inputs.plan_path.read_bytes(), inputs.cell_path.read_bytes())
    dry_run = bool(prov.get("dry_run", False))
    if inputs.cell.kind != "simulated" and not dry_run:      # the night goes on with the same guard as its start
        from .cellfactory import check_real_cell_ready
        check_real_cell_ready(inputs, allow_stale_calibration=args.allow_stale_calibration)
    return _run_session(inputs, Path(args.dir), int(session["seed"]), dry_run, resume=True, quiet=args.quiet)


def cmd_status(args: argparse.Namespace) -> int:
    from .status import show_status

    return show_status(Path(args.dir), follow=args.follow, as_json=args.json)


def cmd_pause(args: argparse.Namespace) -> int:
    from .signals import request_pause

    pid = request_pause(Path(args.dir))
    print(f"asked the controller (pid {pid}) to pause after the step in flight")
    return EXIT_DONE


def cmd_stop(args: argparse.Namespace) -> int:
    from .signals import request_stop

    pid = request_stop(Path(args.dir))
    print(f"asked the controller (pid {pid}) to stop safely now")
    return EXIT_DONE


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_session

    result = evaluate_session(Path(args.dir))
    if args.json:
        print(json.dumps(result, allow_nan=False))
    else:
        for k, v in result.items():
            print(f"{k:>18}: {v}")
    return EXIT_DONE


def cmd_predict(args: argparse.Namespace) -> int:
    from .learning.support import SUPPORT_NAMES
    from .predict import predict_profile

    served, source = predict_profile(Path(args.dir), args.region, args.force, args.angle, args.extrapolate)
    names = [SUPPORT_NAMES[c] if 0 <= c < len(SUPPORT_NAMES) else "unknown" for c in served.support.tolist()]
    x_mm, depth_mm, spread_mm = served.x_mm, served.depth_mm, served.spread_mm
    if args.json:
        print(json.dumps({"region": args.region, "force_n": args.force, "angle_deg": args.angle, "models": source,
                          "extrapolated": served.extrapolated,
                          "x_mm": [round(v, 4) for v in x_mm.tolist()],
                          "depth_mm": [None if v != v else round(v, 5) for v in depth_mm.tolist()],
                          "ensemble_std_mm": [None if v != v else round(v, 5) for v in spread_mm.tolist()],
                          "support": names, "clipped": served.clipped.tolist()},
                         allow_nan=False))
    else:
        i = int(depth_mm.argmax())
        counts = {n: names.count(n) for n in dict.fromkeys(names)}
        print(f"region {args.region}, F = {args.force} N, angle = {args.angle} deg ({source}): peak depth "
              f"{depth_mm[i]:.3f} mm (ensemble spread {spread_mm[i]:.3f} mm) at x = {x_mm[i]:.1f} mm")
        print("  support of the samples: " + ", ".join(f"{n} {c}" for n, c in counts.items()))
        if served.extrapolated:
            print("  EXTRAPOLATED: outside the trained forces and angles (bounded, not validated)")
        for xv, dv, nv in zip(x_mm[::16], depth_mm[::16], names[::16]):
            print(f"  x {xv:7.2f} mm  depth {dv:7.3f} mm  {nv}")
    return EXIT_DONE


def cmd_report(args: argparse.Namespace) -> int:
    from .report import write_report

    print(f"wrote {write_report(Path(args.dir))}")
    return EXIT_DONE


def cmd_export(args: argparse.Namespace) -> int:
    from .export import export_hdf5
    from .journal import refuse_session_file

    out = Path(args.out) if args.out else Path(args.dir) / "export.h5"
    refuse_session_file(out, "export --out")
    print(f"wrote {export_hdf5(Path(args.dir), out)}")
    return EXIT_DONE


def cmd_train(args: argparse.Namespace) -> int:
    from .retrain import retrain_session

    for line in retrain_session(Path(args.dir)):
        print(line)
    return EXIT_DONE


def cmd_salvage(args: argparse.Namespace) -> int:
    from .salvage import salvage

    out = Path(args.out)
    report = salvage(Path(args.dir), out)
    for line in report.lines(out):
        print(line)
    return EXIT_DONE


def cmd_calibrate(args: argparse.Namespace) -> int:
    from elastoprobe.calibration.runner import run_calibration

    from .core.config import DEFAULT_CELL
    from .journal import refuse_session_file

    cell = Path(args.cell) if args.cell else DEFAULT_CELL
    if args.out:
        refuse_session_file(args.out, "calibrate --out")
    summary = run_calibration(args.kind, cell, seed=args.seed, out_path=Path(args.out) if args.out else None)
    print(json.dumps(summary, indent=None if args.json else 2, allow_nan=False, default=str))
    return EXIT_DONE


def cmd_sim(args: argparse.Namespace) -> int:
    if args.sim_command == "object":
        return cmd_sim_object(args)
    from elastoprobe.sim.servers.serve import main_serve

    from .core.config import DEFAULT_CELL

    return main_serve(Path(args.cell) if args.cell else DEFAULT_CELL, args.seed, run_dir=args.run_dir)


def cmd_sim_object(args: argparse.Namespace) -> int:
    """Generate a painted object (sim/generate.py) and a plan for it by the plan rule (planrule.py).

    Both are written to a folder beside ``--out`` first and checked there as a session loads
    them (the object on the cell: workspace, keep-outs, physics at the plan's forces); only
    files that pass replace anything in ``--out``."""
    import os
    import shutil
    import tempfile

    from elastoprobe.sim import generate as gen

    from .cellfactory import load_object_model
    from .core.atomic import atomic_write_text
    from .core.config import DEFAULT_CELL, load_cell, load_session_inputs
    from .core.yamlio import dump_yaml_text
    from .planrule import forces_for_height, outline_of, plan_for_object, reach_problems

    cell_path = Path(args.cell) if args.cell else DEFAULT_CELL
    cell, _ = load_cell(cell_path)
    try:
        obj = gen.generate(args.seed, args.shape, args.pattern, args.pairs,
                           forces=lambda height_mm: forces_for_height(height_mm, cell),
                           tip_radius_mm=cell.tool.tip_radius_mm)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    outline = outline_of(obj.mesh())
    problems = reach_problems(outline, cell)
    if problems:
        raise InputError(f"generated object {obj.name} does not fit the cell: " + "; ".join(problems),
                         path=str(cell_path))
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out must be a folder (it is a file)", path=str(out))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as exc:
        raise InputError(f"cannot write the object: {exc.strerror or exc}", path=str(out)) from None
    try:
        try:
            staged_object = gen.write_object(obj, staging)
        except OSError as exc:
            raise InputError(f"cannot write the object: {exc.strerror or exc}", path=str(out)) from None
        plan = plan_for_object(outline, cell, obj.name, staged_object.name,
                               str(cell_path.resolve()) if args.cell else None, seed=1)
        plan_path = out / "plan.yaml"
        header = (f"# The plan for {obj.name} by the plan rule (controller/planrule.py, docs/generated_objects.md):\n"
                  f"# sized from the object alone (height {outline.height_mm:.0f} mm, footprint "
                  f"{outline.footprint_area_mm2:.0f} mm^2). Run: elastoprobe run {plan_path} --seed 1\n")
        atomic_write_text(staging / plan_path.name, header + dump_yaml_text(plan))
        try:    # what was written is a valid plan for the cell, and its object fits the cell
            load_object_model(load_session_inputs(staging / plan_path.name, cell_path))
        except InputError as exc:
            raise InputError(f"generated object {obj.name} does not fit the cell: "
                             + exc.message.replace(str(staging), str(out)), path=str(cell_path)) from None
        out.mkdir(exist_ok=True)
        for staged in sorted(staging.iterdir()):
            os.replace(staged, out / staged.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    object_path = out / staged_object.name
    summary = {**obj.summary(), "object": str(object_path), "plan": str(plan_path)}
    if args.json:
        print(json.dumps(summary, allow_nan=False))
    else:
        mats = ", ".join(f"{m['name']} ({m['family']}, {m['E_mpa']:g} MPa, dent {m['survey_dent_mm']:.3g} mm)"
                         for m in summary["materials"])
        print(f"{obj.name}: {obj.shape.kind} {' x '.join(f'{x:.0f}' for x in summary['size_mm'])} mm, "
              f"pattern {obj.pattern.kind}, {mats}")
        if summary["contrast"]["min"] is not None:
            print(f"  smallest survey-dent contrast {summary['contrast']['min']:.2f}x")
        print(f"wrote {object_path}, {object_path.with_suffix('.ply')}, {plan_path}")
    return EXIT_DONE


COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "calibrate": cmd_calibrate,
    "sim": cmd_sim,
    "evaluate": cmd_evaluate,
    "predict": cmd_predict,
    "report": cmd_report,
    "export": cmd_export,
    "train": cmd_train,
    "check": cmd_check,
    "diagram": cmd_diagram,
    "run": cmd_run,
    "resume": cmd_resume,
    "status": cmd_status,
    "pause": cmd_pause,
    "stop": cmd_stop,
    "salvage": cmd_salvage,
}
# Commands that only compute from a session (no arm): a pause or stop ends them at once,
# with nothing half-written (their files are written atomically), exit 3: run them again.
INTERRUPTIBLE = {"evaluate", "predict", "report", "export", "train", "salvage", "check"}


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="elastoprobe", description="Robotic probing of deformable objects: plan, run, resume, "
                                                "learn and report (see README.md).")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    c = sub.add_parser("check", help="validate a plan (and its cell), estimate robot time and travel saved")
    c.add_argument("plan")
    c.add_argument("--cell", help="cell file (default: the plan's cell, else the simulated cell)")
    c.add_argument("--json", action="store_true", help="print one JSON object")

    r = sub.add_parser("run", help="run a plan (default: on the simulated cell)")
    r.add_argument("plan")
    r.add_argument("--cell", help="cell file (default: the plan's cell, else the simulated cell)")
    r.add_argument("--out", type=_output_dir, help="session directory (default: sessions/<date>-<plan name>)")
    r.add_argument("--seed", type=_seed, help="seed (default: the plan's)")
    r.add_argument("--dry-run", action="store_true",
                   help="simulated devices behind a real cell's limits, tool geometry and workspace")
    r.add_argument("--allow-stale-calibration", action="store_true",
                   help="run a real cell even if its calibration is missing or too old")
    r.add_argument("--quiet", action="store_true", help="no progress display")

    rs = sub.add_parser("resume", help="continue a paused or killed session where it stopped")
    rs.add_argument("dir", type=_existing_dir)
    rs.add_argument("--allow-stale-calibration", action="store_true",
                    help="resume on a real cell even if its calibration is missing or too old")
    rs.add_argument("--quiet", action="store_true")

    st = sub.add_parser("status", help="progress, state, faults and ETA of a session")
    st.add_argument("dir", type=_existing_dir)
    st.add_argument("--follow", action="store_true", help="keep printing new events until the session ends")
    st.add_argument("--json", action="store_true")

    pa = sub.add_parser("pause", help="ask a running session to pause after the step in flight (exit 3)")
    pa.add_argument("dir", type=_existing_dir)
    so = sub.add_parser("stop", help="ask a running session to stop safely now (exit 3)")
    so.add_argument("dir", type=_existing_dir)

    ev = sub.add_parser("evaluate", help="simulated sessions: score regions and models against ground truth")
    ev.add_argument("dir", type=_existing_dir)
    ev.add_argument("--json", action="store_true", help="print one JSON object")

    pr = sub.add_parser("predict", help="the deformation profile a region's model predicts")
    pr.add_argument("dir", type=_existing_dir)
    pr.add_argument("--region", type=int, required=True)
    pr.add_argument("--force", type=_finite_float, required=True, help="force magnitude (N)")
    pr.add_argument("--angle", type=_finite_float, required=True, help="approach angle (deg, 0..180)")
    pr.add_argument("--extrapolate", action="store_true",
                    help="serve (bounded, flagged) a force or angle outside the trained ranges instead of refusing")
    pr.add_argument("--json", action="store_true")

    rp = sub.add_parser("report", help="(re)write DIR/report/index.html")
    rp.add_argument("dir", type=_existing_dir)

    ex = sub.add_parser("export", help="export the whole session")
    ex.add_argument("dir", type=_existing_dir)
    ex.add_argument("--format", choices=["hdf5"], required=True)
    ex.add_argument("--out", type=_output_file, help="output file (default DIR/export.h5)")

    tr = sub.add_parser("train", help="refit the region models from the journal's measurements")
    tr.add_argument("dir", type=_existing_dir)

    sa = sub.add_parser("salvage", help="copy every intact part of a damaged session into a new session "
                                        "directory, from which resume continues")
    sa.add_argument("dir", type=_existing_dir)
    sa.add_argument("--out", required=True, type=_output_dir, help="the new session directory (must not hold a journal)")

    ca = sub.add_parser("calibrate", help="calibrate the F/T payload, probe tip, scanner mount or object pose")
    ca.add_argument("kind", choices=["ft", "tcp", "scanner", "object"])
    ca.add_argument("--cell", help="cell file (default: the simulated cell); a loopback or ur cell is calibrated "
                                   "on its real drivers (ft, tcp and scanner need the reference sphere on the table "
                                   "where the object sits)")
    ca.add_argument("--seed", type=_seed, default=0)
    ca.add_argument("--out", type=_output_file, help="calibration file to write (default: the cell's calibration_file)")
    ca.add_argument("--json", action="store_true", help="one-line JSON")

    sm = sub.add_parser("sim", help="the simulated cell served over the real protocols")
    smsub = sm.add_subparsers(dest="sim_command", required=True, parser_class=_Parser)
    sv = smsub.add_parser("serve", help="serve RTDE/dashboard/script (UR), Net F/T (UDP) and the serial scanner "
                                        "on loopback, in real time, until SIGINT/SIGTERM")
    sv.add_argument("--cell", help="cell file (default: the simulated cell)")
    sv.add_argument("--seed", type=_seed, default=0)
    sv.add_argument("--run-dir", help="write the servers' addresses (state file) here")

    so = smsub.add_parser("object", help="generate a painted object (mesh + object YAML) and a plan for it")
    so.add_argument("--seed", type=_seed, required=True, help="the object's seed (the same seed: the same object)")
    so.add_argument("--out", required=True, type=_output_dir, help="folder to write object.ply, object.yaml and plan.yaml into")
    so.add_argument("--shape", help="slab, block, dome, sheet or composite (default: drawn from the seed)")
    so.add_argument("--pattern", help="plain, disc, ellipse, strip, wavy_seam, curved_seam, ring, two_inclusions, "
                                      "disc_and_strip or two_inclusions_and_strip; a composite's: box or plate "
                                      "(default: drawn from the seed)")
    so.add_argument("--pairs", default="drawn",
                    help="near: one pair of materials about 3x apart in survey dent; far: none; drawn (default): "
                         "near with probability 0.35")
    so.add_argument("--cell", help="cell the object and plan must suit (default: the simulated cell)")
    so.add_argument("--json", action="store_true", help="print one JSON object")

    d = sub.add_parser("diagram", help="write the state machine's Mermaid diagram")
    d.add_argument("--out", type=_output_file, default=str(Path(__file__).resolve().parent.parent / "docs" / "state_machine.md"))
    return p


def main(argv: Sequence[str] | None = None) -> int:
    # A file name that is not UTF-8 (Python holds its bytes as surrogates) prints as those bytes.
    streams = [(s, s.errors) for s in (sys.stdout, sys.stderr) if isinstance(s, io.TextIOWrapper)]
    for stream, _ in streams:
        stream.reconfigure(errors="surrogateescape")
    # Until a command takes the signals itself (a session, an interruptible command), SIGTERM
    # is what SIGINT is: the command ends before it wrote anything (exit 3; ``run``, which has
    # no session to resume yet, 1), not with a traceback from the import in progress nor a
    # death by signal.
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if in_main_thread else None
    try:
        return _main(argv)
    except KeyboardInterrupt:
        words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
        command = words[0] if words else "elastoprobe"
        print(f"elastoprobe {command}: interrupted before it started; nothing was written", file=sys.stderr)
        return EXIT_FAULT if command == "run" else EXIT_PAUSED
    finally:
        if in_main_thread:
            if argv is None:
                # The command line's own process: its command has finished and its exit code
                # stands; a signal in the last moments of the interpreter must not replace it.
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
            else:
                signal.signal(signal.SIGTERM, previous)
        for stream, errors in streams:
            stream.reconfigure(errors=errors)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # After parsing: --help and usage errors need neither (the journal brings numpy).
    from .journal import JournalCorruption
    from .signals import OperatorFlags, OperatorInterrupt

    flags = OperatorFlags().install() if args.command in INTERRUPTIBLE else None
    try:
        if flags is None:
            return COMMANDS[args.command](args)
        with flags.interruptible():
            return COMMANDS[args.command](args)
    except OperatorInterrupt as exc:
        print(f"elastoprobe {args.command}: {exc}; nothing was half-written, run it again", file=sys.stderr)
        return EXIT_PAUSED
    except InputError as exc:
        print(exc.format(), file=sys.stderr)
        return EXIT_BAD_INPUT
    except JournalCorruption as exc:
        session = getattr(args, "dir", None) or getattr(args, "out", None) or "DIR"
        print(f"elastoprobe: {session}: {exc}\n  nothing was written to it; salvage what is intact into a new "
              f"session directory and continue there:\n    elastoprobe salvage {session} --out NEW_DIR\n"
              f"    elastoprobe resume NEW_DIR", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ElastoprobeError as exc:
        print(f"elastoprobe: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        return EXIT_DONE
    except KeyboardInterrupt:       # before a session took the signals, or a command without handling
        if args.command == "run":
            print("elastoprobe run: interrupted before the session started; nothing was written", file=sys.stderr)
            return EXIT_FAULT
        print(f"elastoprobe {args.command}: interrupted", file=sys.stderr)
        return EXIT_PAUSED
    except OSError as exc:
        # A file the command had to write or read that the disk refused (read-only, full,
        # a file where a directory should be): the path and why, never a traceback.
        where = exc.filename if exc.filename is not None else getattr(args, "dir", None) or "elastoprobe"
        print(f"{where}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if flags is not None:
            flags.restore()


if __name__ == "__main__":   # pragma: no cover
    sys.exit(main())
