"""The ``elastoprobe`` command line (DESIGN §11).

Exit codes: 0 done; 1 ended in a fault or aborted; 2 bad input (``path:line:col:
message``, never a traceback); 3 paused and resumable. Heavy modules (torch, the
simulator, trimesh) are imported inside the commands so start-up stays fast.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable, Sequence

from .errors import ElastoprobeError, InputError

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
def cmd_check(args: argparse.Namespace) -> int:
    from .config import load_session_inputs
    from .estimate import estimate_plan

    inputs = load_session_inputs(args.plan, args.cell)
    est = estimate_plan(inputs)
    report = {
        "plan": inputs.plan.name,
        "cell": inputs.cell.name,
        "contacts": est.contacts,
        "force_steps": est.steps,
        "robot_hours": round(est.hours(), 3),
        "robot_s_per_phase": {k: round(v, 1) for k, v in est.per_phase_s.items()},
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
        for k, v in est.per_phase_s.items():
            print(f"    {k:<13} {v / 60:7.1f} min")
        if travel is not None:
            print(f"  travel by ordering: {travel[0]:.0f} mm -> {travel[1]:.0f} mm "
                  f"(saved {travel[0] - travel[1]:.0f} mm)")
        else:
            print("  travel saved by ordering: known once the neural gas has placed the targets "
                  "(the plan lists no explicit targets)")
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
    from .atomic import atomic_write_text
    from .machine import diagram_markdown

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, diagram_markdown())
    print(f"wrote {out}")
    return EXIT_DONE


COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "check": cmd_check,
    "diagram": cmd_diagram,
}


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="elastoprobe", description="Robotic probing of deformable objects: plan, run, resume, "
                                                "learn and report (see README.md).")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    c = sub.add_parser("check", help="validate a plan (and its cell), estimate robot time and travel saved")
    c.add_argument("plan")
    c.add_argument("--cell", help="cell file (default: the plan's cell, else the simulated cell)")
    c.add_argument("--json", action="store_true", help="print one JSON object")

    d = sub.add_parser("diagram", help="write the state machine's Mermaid diagram")
    d.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "docs" / "state_machine.md"))
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except InputError as exc:
        print(exc.format(), file=sys.stderr)
        return EXIT_BAD_INPUT
    except ElastoprobeError as exc:
        print(f"elastoprobe: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        return EXIT_DONE


if __name__ == "__main__":   # pragma: no cover
    sys.exit(main())
