"""Helpers shared by the session tests: run the CLI as a child, kill it, resume it, read results.

No tests live here (pytest collects the file and finds none). Every session runs the
real command line (``python -m elastoprobe.controller.cli``) in a child process with
its own cell-lock directory, so tests never meet other controllers' cell locks.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from elastoprobe.controller.journal import Journal

DATA = Path(__file__).resolve().parent / "data" / "session"
TINY_PLAN = DATA / "tiny.yaml"
CLI = [sys.executable, "-m", "elastoprobe.controller.cli"]
CHILD_TIMEOUT_S = 600.0          # a stuck child is killed, never waited on forever


@dataclass
class Child:
    """One CLI invocation: its exit code (negative = killed by that signal) and output."""

    args: list[str]
    returncode: int
    stdout: str
    stderr: str
    killed_by_test: bool = False


def child_env(lock_dir: Path, crash_at: str | None = None, extra: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["ELASTOPROBE_LOCK_DIR"] = str(lock_dir)
    env.pop("ELASTOPROBE_JOURNAL_CRASH_AT", None)
    if crash_at:
        env["ELASTOPROBE_JOURNAL_CRASH_AT"] = crash_at
    env.update(extra or {})
    return env


def run_cli(args: list[str], env: dict[str, str], kill_after_s: float | None = None) -> Child:
    """Run the CLI; with ``kill_after_s`` send SIGKILL after that many wall seconds."""
    proc = subprocess.Popen(CLI + args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = False
    try:
        if kill_after_s is not None:
            try:
                proc.wait(timeout=kill_after_s)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGKILL)
                killed = True
        out, err = proc.communicate(timeout=CHILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"{args} did not finish within {CHILD_TIMEOUT_S} s:\n{err[-3000:]}")
    return Child(args, proc.returncode, out, err, killed_by_test=killed)


def start_or_resume(plan: Path, out: Path, seed: int, env: dict[str, str], cell: Path | None = None,
                    kill_after_s: float | None = None) -> Child:
    """``run`` while the directory holds no journal yet, else ``resume``."""
    if (out / "journal.sqlite").exists():
        args = ["resume", str(out), "--quiet"]
    else:
        args = ["run", str(plan), "--out", str(out), "--seed", str(seed), "--quiet"]
        if cell is not None:
            args += ["--cell", str(cell)]
    return run_cli(args, env, kill_after_s)


def copy_cell(src: Path, dst_dir: Path, name: str) -> Path:
    """A copy of a cell file under its own name (cell locks are per name), next to the
    object files it names by a path relative to the repository's config/cells/."""
    text = src.read_text()
    lines = [f"name: {name}" if ln.startswith("name:") else ln for ln in text.splitlines()]
    obj = (Path(__file__).resolve().parent.parent / "config" / "objects" / "composite.yaml")
    lines = [ln.replace("../objects/composite.yaml", str(obj)) for ln in lines]
    out = dst_dir / f"{name}.yaml"
    out.write_text("\n".join(lines) + "\n")
    return out


def plan_for(cell: Path, dst_dir: Path, base: Path = TINY_PLAN, edits: dict[str, str] | None = None) -> Path:
    """A copy of a plan that names ``cell`` (absolute paths), with line edits ``old -> new``."""
    root = Path(__file__).resolve().parent.parent
    text = base.read_text()
    text = text.replace("cell: ../../../config/cells/sim.yaml", f"cell: {cell}")
    text = text.replace("simulated_object: ../../../config/objects/composite.yaml",
                        f"simulated_object: {root / 'config' / 'objects' / 'composite.yaml'}")
    for old, new in (edits or {}).items():
        assert old in text, f"plan edit {old!r} does not match"
        text = text.replace(old, new)
    out = dst_dir / base.name
    out.write_text(text)
    return out


# ----------------------------------------------------------------------------- what a session produced
@dataclass
class Outcome:
    """What a finished session produced, for comparisons between runs."""

    status: str
    step_status: dict[int, str]
    step_data: dict[int, str]                 # step id -> checksum of its raw scans
    model_hashes: dict[str, dict[str, str]]   # "models<round>" -> region -> model hash
    phase_hashes: dict[str, str]
    labels_sha256: str | None
    integrity: list[str]
    problems: list[str]
    extra: dict[str, Any] = field(default_factory=dict)


def outcome(session_dir: Path) -> Outcome:
    j = Journal.open_readonly(session_dir)
    try:
        integrity = [r[0] for r in j._q("PRAGMA integrity_check")]
        problems = j.verify() + j.verify_files()
        status = j.session()["status"]
        steps = j.steps()
        step_status = {r.step_id: r.status for r in steps}
        step_data = {r.step_id: r.summary["arrays"]["scans_xz_mm"] for r in steps if r.status == "done"}
        models, phases = {}, {}
        for p in j.phases():
            rec = j.phase(p["name"], p["round"])
            assert rec is not None
            phases[f"{p['name']}[{p['round']}]"] = rec.outputs_hash
            if p["name"] == "models":
                models[f"models{p['round']}"] = {k: v.get("model_hash", v.get("skipped", ""))
                                                 for k, v in rec.outputs["regions"].items()}
        final = j.phase("final", 0)
        labels = None
        if final is not None:
            labels = hashlib.sha256(np.ascontiguousarray(final.arrays["cloud_labels"]).tobytes()).hexdigest()
    finally:
        j.close()
    return Outcome(status, step_status, step_data, models, phases, labels, integrity, problems)


def done_step_facts(session_dir: Path) -> list[dict[str, Any]]:
    """Per done step: scans stored, finite forces, |F| at the target, checksum verified."""
    j = Journal.open_readonly(session_dir)
    try:
        facts = []
        for rec in j.steps(statuses=["done"]):
            res = j.step_result(rec.step_id)          # raises JournalCorruption on a bad checksum
            mag = np.linalg.norm(res.scan_force_n, axis=1)
            facts.append({"step": rec.step_id, "n_scans": int(res.scans_xz_mm.shape[0]),
                          "force_target_n": rec.plan.force_n, "force_min_n": float(np.min(mag)),
                          "force_max_n": float(np.max(mag)), "finite": bool(np.isfinite(mag).all()),
                          "attempts": rec.attempts})
        return facts
    finally:
        j.close()


def fresh_dir(path: Path) -> Path:
    if path.exists():
        shutil.rmtree(path)
    return path


def wall_s() -> float:
    return time.monotonic()
