"""The simulated overnight soak: a night of probing with faults, kills and resumes (issues #7, #15).

A private copy of the simulated cell injects rate-based faults of every kind of
``InjectedFault`` in controller/core/faultkinds.py (about one every ten force steps in total; the emergency stop with
``clear_after_s``, a disk error on the journal's write among them), follow-up faults that
strike while the controller recovers from another one (``rate_per_100_faults``), and
faults fixed in the cloud sweep and in learning phases (the simulator is keyed there as
at a step: ``phases.SWEEP_STEP_KEY``, ``session.LEARN_STEP_KEY``). The real CLI runs
``config/plans/soak.yaml`` (>= 8 h of robot time) in a child process; the driver SIGKILLs
it at seeded random moments (a random wall-clock delay, aimed inside a journal
transaction, or in a learning phase), plays the operator when the session pauses (an
e-stop: wait, release, resume; a disk error: the disk is fixed, resume) and resumes until
the session is done or a bounded number of children is spent.

Ground truth, not the controller's word:
- injected faults come from the simulator's durable record (``ELASTOPROBE_SIM_FAULT_LOG``,
  one line per fault that fired, with the process id, virtual time and step key); a
  fault fired in a process that was then killed before journaling it is re-drawn under
  the same key by the resumed process, so faults are counted once per (kind, key);
- each is matched to the journaled fault of the same run (runs.pid) within a short
  robot-time window, and judged: recovered (retried or skipped per policy, the step
  later done or skipped), paused (the child exited 3 on it, then was resumed),
  undetected (never journaled), without effect (a scanner fault with no scan asked,
  a slip with no contact), lost to a kill, or unresolved;
- a step counts as committed when its ``step_done`` line is in DIR/log.jsonl (written
  after each commit) or a poll of the journal saw it done; steps_lost = committed once
  but not done at the end, plus planned steps neither done nor skipped at the end;
  steps_duplicated = steps with more than one ``step_done`` line.

Memory: the child's RSS (/proc/PID/status VmRSS) every ``sample_s`` with the journal's
robot time; peak_rss_mb is the largest VmHWM sampled from the children (peak since exec).
rss_growth_mb_per_h is the RSS slope against ROBOT hours over the probing stretches
(samples where robot time advances; start-up, each child's first 0.1 robot hours of
warm-up and learning phases excluded): per stretch of at least 9 samples, the median RSS of
its last third less that of its first third over the hours between them, averaged weighted
by each stretch's robot hours. rss_growth_across_children_mb_per_h is the slope of each child's
settled RSS (its median past warm-up) from child to child over the night. baseline_rss_mb is the
peak RSS of ``elastoprobe check`` on the same plan (the CLI with plan and cell loaded).

    python bench/soak.py [--quick | --part 2|4] [--seed N] [--keep DIR]

Prints ONE JSON object.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import random
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SOAK_PLAN = ROOT / "config" / "plans" / "soak.yaml"
SIM_CELL = ROOT / "config" / "cells" / "sim.yaml"
COMPOSITE = ROOT / "config" / "objects" / "composite.yaml"
CLI = [sys.executable, "-m", "elastoprobe.controller.cli"]
FAULT_LOG_ENV = "ELASTOPROBE_SIM_FAULT_LOG"

# What the controller journals for each injected kind (its fault-policy key).
SEEN_AS: dict[str, set[str]] = {
    "force_spike": {"force", "force_rate", "lateral_force", "torque"},
    "ft_stall": {"stale", "ft_status", "device"},
    "ft_frozen": {"frozen", "stale", "ft_status"},
    "scanner_timeout": {"scanner"},
    "scanner_short_burst": {"scanner"},
    "protective_stop": {"protective_stop", "device"},
    "connection_loss": {"connection", "device"},
    "emergency_stop": {"emergency_stop", "device"},
    "object_moved": {"object_moved", "no_contact", "force", "slip", "lateral_force"},
    "slip": {"slip", "lateral_force", "force"},
    "disk_error": {"disk_error"},
}
# A device shows an injected fault within milliseconds (F/T checks per block) to a few
# seconds (a connection loss is seen at the next command; a scanner fault at the end of
# the burst): the journaled fault follows the injection within this much robot time.
MATCH_WINDOW_S = 20.0
# Aimed kills: a SIGKILL inside these journal transactions (controller/journal.py), at the
# n-th pass in the child, n drawn from these ranges: a child lives a few dozen steps between
# pauses (a fault every ten steps or so, a few of them pause), so a pass far beyond that is
# never reached; a fault is journaled once or twice per child, a phase committed seldom
# (then the kill lands as the survey ends and characterization is planned).
AIMED_NTH: dict[str, tuple[int, int]] = {
    "commit_step:half_arrays": (1, 12), "commit_step:before_commit": (1, 12),
    "begin_step:before_commit": (1, 12), "record_fault:before_commit": (1, 2),
    "commit_phase:half_steps": (1, 1)}
# A kill in a learning phase: after the first region's model is fitted, before it is saved
# (controller/phases.py crash points). Armed beside every other kill until its quota has
# landed: no child knows in advance whether it will live to learn.
LEARNING_POINT = "models:before_save@1"
_CRASH_LINE = re.compile(r"^crash point (\S+)", re.MULTILINE)
# The simulator keys of the sweep and of learning phases (controller/phases.py, session.py).
SWEEP_KEY = 2**32 - 2
LEARN_KEY = 2**32 - 1002
# Faults of these kinds follow up others (a burst: one lands while the controller recovers).
FOLLOW_UPS = {"protective_stop": 3.0, "connection_loss": 3.0, "force_spike": 2.0, "ft_frozen": 2.0}


@dataclass(frozen=True)
class SoakConfig:
    """One soak: the plan, the faults, the kills and the bounds (wall seconds unless named)."""

    plan_overrides: dict[str, Any] = field(default_factory=dict)   # dotted keys over soak.yaml
    seed: int = 1
    fault_rate_per_100_steps: float = 12.0          # all kinds together: a fault every eight to ten steps
    rates_per_100_steps: dict[str, float] | None = None   # per kind, overrides the even split
    # (kind, step key, delay s or None): at that key's first attempt (a step id, or the
    # sweep's or a learning phase's key)
    step_faults: tuple[tuple[str, int, float | None], ...] = ()
    follow_ups_per_100_faults: dict[str, float] = field(default_factory=lambda: dict(FOLLOW_UPS))
    estop_clear_after_s: float = 60.0               # robot time: the operator walks over
    operator_delay_s: float = 1.0                   # wall: before the operator resumes
    kills: int = 24                                 # landed on a live child, every kind together
    learning_kills: int = 4                         # of them, in a learning phase
    # Robot seconds between two kills of the rotation, so they spread over every phase of the
    # night instead of all landing in its first hour: its 20 over ~7 of its ~8.5 hours. A
    # progress kill not due when its child starts is armed for its robot moment (a child
    # runs for hours between pauses); an aimed one waits for the first child started after it.
    kill_every_robot_s: float = 1200.0
    # A "progress" kill: after the child has committed this many steps of its own (0: during
    # its start-up, resume and re-registration), then a random wall delay within the next
    # step (uniform over kill_jitter_s): a moment read from the child's own progress, so it
    # lands on a running child instead of after its exit.
    kill_after_steps: tuple[int, int] = (0, 6)
    kill_jitter_s: tuple[float, float] = (0.0, 8.0)
    # The kind of each rotation kill in turn: a moment of the child's progress, or inside a
    # journal transaction (AIMED_NTH); learning kills are armed beside them (LEARNING_POINT).
    kill_modes: tuple[str, ...] = ("progress", "aimed")
    max_children: int = 300
    child_timeout_s: float = 3600.0
    sample_s: float = 2.0
    min_robot_hours: float = 8.0                    # what the full night must reach


# About 13 faults per 100 steps: the kinds that pause the night (the e-stop waits for the
# operator, a disk error for the disk) and the moved object (each is a sweep and a
# registration, and the object wanders by 12 mm a time) less often than the rest. Faults
# fixed where rates reach seldom: the cloud sweep (one key a night) mid-way through it, and
# the first learning phases; two disk errors at survey steps (listed after the rate
# faults: their draws are unchanged).
FULL_RATES = {"force_spike": 1.6, "ft_stall": 1.6, "ft_frozen": 1.6, "protective_stop": 1.6, "connection_loss": 1.6,
              "scanner_timeout": 1.3, "scanner_short_burst": 1.3, "slip": 1.0, "emergency_stop": 0.5,
              "disk_error": 0.5, "object_moved": 0.4}
FULL = SoakConfig(rates_per_100_steps=FULL_RATES, step_faults=(
    ("protective_stop", SWEEP_KEY, 40.0), ("connection_loss", SWEEP_KEY, 150.0),
    ("emergency_stop", LEARN_KEY, None), ("protective_stop", LEARN_KEY - 1, None),
    ("connection_loss", LEARN_KEY - 2, None), ("force_spike", LEARN_KEY - 3, None),
    ("disk_error", 801, None), ("disk_error", 1601, None)))
# A part of the night, for a machine that cannot give the night its ~1.5 h of wall time:
# the same faults at the same rates and the same kinds of kill, on the night's plan cut
# down in every phase (survey, characterize, densify rounds, the models' training), so it
# still goes through all of them and through the learning phases. ``--part 2``: half.
def part_of_night(divisor: int) -> SoakConfig:
    """The night's soak with its plan, kills and bounds divided by ``divisor`` (2 or 4)."""
    quarter = divisor >= 4
    return replace(FULL, plan_overrides={
        "name": f"soak-1-{divisor}", "sampling.units": 400 // divisor,
        "phases.characterize.points_per_region": 10 // divisor,
        "phases.densify.rounds": 2 if quarter else 4, "phases.densify.points_per_round": 10,
        **({"model.ensemble": 1, "model.max_epochs": 300} if quarter else {})},
        kills=24 // divisor, learning_kills=max(4 // divisor, 2), kill_every_robot_s=FULL.kill_every_robot_s,
        step_faults=tuple(f for f in FULL.step_faults if f[1] not in (801, 1601)) + (("disk_error", 101, None),),
        min_robot_hours=8.0 / divisor)


QUICK = SoakConfig(
    plan_overrides={
        "name": "soak-quick", "cloud.sweep_spacing_mm": 5.0, "cloud.max_points": 20000,
        "sampling.units": 30, "sampling.steps_per_unit": 40,
        "probing.scans_per_step": 5, "probing.settle_s": 0.5, "probing.standoff_mm": 10.0,
        "probing.force_rate_n_s": 20.0,
        "phases.survey.forces_n": [4.0, 8.0, 12.0],
        "phases.characterize.points_per_region": 1, "phases.characterize.angles_deg": [75, 90, 105],
        "phases.characterize.forces_n": [5.0, 12.0],
        "phases.densify.rounds": 0,
        "budget.max_robot_hours": 2.0,
        "model.ensemble": 1, "model.max_epochs": 60, "model.profile_samples": 64,
    },
    # A short run has ~40 steps: a fault every few steps, of the kinds that pause
    # (e-stop, disk error) and of kinds that are retried.
    rates_per_100_steps={"emergency_stop": 1.5, "disk_error": 3.0, "force_spike": 3.0,
                         "protective_stop": 3.0, "scanner_timeout": 3.0, "connection_loss": 3.0},
    follow_ups_per_100_faults={"protective_stop": 20.0},
    operator_delay_s=0.2, kills=3, learning_kills=1, kill_every_robot_s=0.0, kill_after_steps=(1, 4),
    kill_jitter_s=(0.0, 2.0), kill_modes=("aimed", "progress"), max_children=20, child_timeout_s=300.0, sample_s=0.5, min_robot_hours=0.0,
    # A disk error at a middle force level of a contact that no other fault touches with
    # this seed and a protective stop in the sweep (listed after the rate faults, so their
    # draws are unchanged): the short run is sure to meet them, whatever the rate draws
    # give. (Its one learning phase is its last: no motion follows to meet a fault there.)
    step_faults=(("disk_error", 10, None), ("protective_stop", SWEEP_KEY, 5.0)),
)


# ----------------------------------------------------------------------------- set-up
def fault_rates(cfg: SoakConfig) -> dict[str, float]:
    """Per-kind rates (per 100 force steps): the even split of the total over every kind."""
    from elastoprobe.controller.core.faultkinds import INJECTED_FAULT_NAMES

    if cfg.rates_per_100_steps is not None:
        return dict(cfg.rates_per_100_steps)
    return {k: cfg.fault_rate_per_100_steps / len(INJECTED_FAULT_NAMES) for k in INJECTED_FAULT_NAMES}


def write_cell(dst_dir: Path, name: str, rates: dict[str, float], estop_clear_after_s: float,
               step_faults: tuple[tuple[str, int, float | None], ...] = (),
               follow_ups: dict[str, float] | None = None) -> Path:
    """A private copy of the simulated cell (its own lock name) with rate-based faults
    (then the step faults, then the follow-ups)."""
    lines = SIM_CELL.read_text().splitlines()
    lines = [f"name: {name}" if ln.startswith("name:") else ln for ln in lines]
    lines = [ln.replace("../objects/composite.yaml", str(COMPOSITE)) for ln in lines]
    assert lines[-1].startswith("  ") and any(ln.startswith("simulation:") for ln in lines), \
        "config/cells/sim.yaml should end with its simulation section"
    lines.append("  faults:")
    for kind, rate in rates.items():
        extra = f", clear_after_s: {estop_clear_after_s}" if kind == "emergency_stop" else ""
        lines.append(f"    - {{kind: {kind}, rate_per_100_steps: {rate:.6g}{extra}}}")
    for kind, step, delay_s in step_faults:
        extra = f", clear_after_s: {estop_clear_after_s}" if kind == "emergency_stop" else ""
        extra += f", delay_s: {delay_s}" if delay_s is not None else ""
        lines.append(f"    - {{kind: {kind}, step: {step}{extra}}}")
    for kind, rate in (follow_ups or {}).items():
        extra = f", clear_after_s: {estop_clear_after_s}" if kind == "emergency_stop" else ""
        lines.append(f"    - {{kind: {kind}, rate_per_100_faults: {rate:.6g}{extra}}}")
    out = dst_dir / f"{name}.yaml"
    out.write_text("\n".join(lines) + "\n")
    return out


def write_plan(dst_dir: Path, cell: Path, overrides: dict[str, Any]) -> Path:
    """config/plans/soak.yaml naming ``cell``, with dotted-key overrides."""
    from ruamel.yaml import YAML

    yaml = YAML()
    doc = yaml.load(SOAK_PLAN.read_text())
    doc["cell"] = str(cell)
    doc["simulated_object"] = str(COMPOSITE)
    for key, value in overrides.items():
        node = doc
        *parents, last = key.split(".")
        for p in parents:
            node = node[p]
        if last not in node and key != "name":
            node[last] = value      # a field the shipped plan leaves at its default
        node[last] = value
    out = dst_dir / "plan.yaml"
    with open(out, "w", encoding="utf-8") as f:
        yaml.dump(doc, f)
    return out


# ----------------------------------------------------------------------------- children
@dataclass
class ChildRun:
    """One CLI child: how it ended, how it was killed, what it said, its memory."""

    args: list[str]
    pid: int
    returncode: int
    killed: str | None                 # "progress 3 steps +1.2 s" / "aimed commit_step:half_arrays@7" / None
    wall_s: float
    max_rss_mb: float
    samples: list[tuple[float, ...]]   # (wall s since start, RSS MB, robot s, committed phases)
    pause_reason: str | None = None
    stderr_tail: str = ""
    kill_phase: str | None = None      # where a kill landed: sweeping, survey, ..., learning
    kill_due: bool = False             # the armed kill's moment came (a child that exits after is a miss)


@dataclass(frozen=True)
class ProgressKill:
    """SIGKILL the child ``jitter_s`` wall seconds after it has committed ``after_steps`` steps
    of its own (0: from its start), counted from when the session's robot time reached
    ``at_robot_s`` (0: from the child's start): a child that runs on for hours is killed when
    the night's schedule says, not only a child that starts after that moment."""

    after_steps: int
    jitter_s: float
    at_robot_s: float = 0.0

    def describe(self) -> str:
        at = f" from {self.at_robot_s / 3600.0:.2f} robot h" if self.at_robot_s > 0 else ""
        return f"progress {self.after_steps} steps +{self.jitter_s:.1f} s{at}"


def _vm_mb(pid: int, field_name: str = "VmRSS") -> float | None:
    """A /proc/<pid>/status memory line in MB (VmRSS now, VmHWM the peak since exec).

    Not ru_maxrss: on Linux a child's ru_maxrss includes the parent it was forked from
    (under pytest that is the test process itself, a gigabyte)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(field_name + ":"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        return None
    return None


def _vm_rss_mb(pid: int) -> float | None:
    return _vm_mb(pid, "VmRSS")


def _journal_poll(session_dir: Path) -> tuple[float, set[int], int] | None:
    """Robot time (s), done step ids and committed phases, read-only (safe while the child writes)."""
    from elastoprobe.controller.journal import Journal

    if not (session_dir / "journal.sqlite").exists():
        return None
    try:
        j = Journal.open_readonly(session_dir, check="none")
    except Exception:   # noqa: BLE001 - being created, or locked for a moment: next poll
        return None
    try:
        done = {r.step_id for r in j.steps(statuses=["done"])}
        return j.robot_time_s()["total"], done, len(j.phases())
    except (sqlite3.Error, Exception):   # noqa: BLE001
        return None
    finally:
        j.close()


def _save_state(work_dir: Path, state: dict[str, Any], children: list[ChildRun], ever_done: set[int]) -> None:
    """What judging needs, kept beside the session after every child (see --judge)."""
    data = {**state, "children": [asdict(c) for c in children], "ever_done": sorted(ever_done)}
    (work_dir / "state.json").write_text(json.dumps(data))


def run_child(args: list[str], env: dict[str, str], session_dir: Path, kill: ProgressKill | None,
              sample_s: float, timeout_s: float, ever_done: set[int], log_path: Path,
              cli: list[str] = CLI) -> ChildRun:
    """Run the CLI, sampling RSS and the journal; SIGKILL it at ``kill``'s moment of its progress.

    The kill is sent only to a child not yet reaped (waited for with WNOHANG just before): one
    that exited first (a pause) is not killed, and its exit code says so. A kill counts as
    landed only when the child's own status says SIGKILL."""
    before = _journal_poll(session_dir)
    done_before = set(before[1]) if before is not None else set()
    log_offset = log_path.stat().st_size if log_path.exists() else 0
    with open(log_path, "ab") as err:
        proc = subprocess.Popen(cli + args, env=env, stdout=subprocess.DEVNULL, stderr=err)
    t0 = time.monotonic()
    samples: list[tuple[float, ...]] = []
    killed = None
    robot_s = 0.0
    phases = 0
    peak_mb = 0.0
    # Steps are counted from the kill's robot moment (the done set then); None: not due yet.
    due_done: set[int] | None = None
    if kill is not None and (before[0] if before is not None else 0.0) >= kill.at_robot_s:
        due_done = done_before
    kill_at_s = None if kill is None or due_done is None or kill.after_steps > 0 else kill.jitter_s
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid != 0:
            break
        t = time.monotonic() - t0
        if kill_at_s is not None and t >= kill_at_s:
            os.kill(proc.pid, signal.SIGKILL)      # alive a moment ago: wait4 has not reaped it
            assert kill is not None
            killed, kill_at_s, kill = kill.describe(), None, None
            continue
        if t > timeout_s:
            os.kill(proc.pid, signal.SIGKILL)
            killed = "timeout"
            continue
        polled = _journal_poll(session_dir)
        if polled is not None:
            robot_s, phases = polled[0], polled[2]
            ever_done |= polled[1]
            if kill is not None and due_done is None and robot_s >= kill.at_robot_s:
                due_done = set(polled[1])
            if kill is not None and kill_at_s is None and due_done is not None \
                    and len(polled[1] - due_done) >= kill.after_steps:
                kill_at_s = t + kill.jitter_s
        rss = _vm_rss_mb(proc.pid)
        if rss is not None:
            samples.append((t, rss, robot_s, phases))
            peak_mb = max(peak_mb, _vm_mb(proc.pid, "VmHWM") or rss)
        wait_s = sample_s if kill_at_s is None else min(sample_s, max(kill_at_s - t, 0.0))
        time.sleep(wait_s)
    proc.returncode = os.waitstatus_to_exitcode(status)
    own_err = b""
    if log_path.exists():
        with open(log_path, "rb") as f:
            f.seek(log_offset)
            own_err = f.read()
    own_text = own_err.decode("utf-8", "replace")
    if proc.returncode == -signal.SIGKILL and killed is None:
        points = _CRASH_LINE.findall(own_text)
        killed = f"aimed {points[-1]}" if points else None
    elif proc.returncode != -signal.SIGKILL and killed is not None and killed != "timeout":
        killed = None                                # it had exited on its own: the kill hit nothing
    return ChildRun(args, proc.pid, proc.returncode, killed, time.monotonic() - t0, peak_mb, samples,
                    stderr_tail=own_text[-3000:], kill_due=kill is None or due_done is not None)


def _session_status(session_dir: Path) -> tuple[str | None, str | None]:
    from elastoprobe.controller.journal import Journal

    if not (session_dir / "journal.sqlite").exists():
        return None, None
    j = Journal.open_readonly(session_dir, check="none")
    try:
        s = j.session()
        return s["status"], s.get("status_reason")
    finally:
        j.close()


def kill_phase(session_dir: Path, pid: int) -> str | None:
    """Where the run of process ``pid`` was when it died: learning, the sweep, planning, the
    phase of the step it was last at (survey, characterize, densify), or start-up."""
    from elastoprobe.controller.journal import Journal

    if not (session_dir / "journal.sqlite").exists():
        return None
    j = Journal.open_readonly(session_dir, check="none")
    try:
        run = [r["run_id"] for r in j.runs() if r["pid"] == pid]
        transitions = j.transitions(run_id=run[-1], last=1) if run else []
        step = j.last_step_of_run(run[-1]) if run else None
        step_phase = step.phase if step is not None else None
    finally:
        j.close()
    if not transitions:
        return "start-up"
    state = transitions[-1]["to_state"]
    if state in ("learning", "sweeping", "planning"):
        return state
    if state in ("preflight", "idle"):
        return "start-up"
    return PHASE_NAMES.get(step_phase, step_phase) if step_phase else "start-up"


def journal_soundness(session_dir: Path) -> list[str]:
    """PRAGMA integrity_check and Journal.verify(): empty when sound."""
    from elastoprobe.controller.journal import Journal

    if not (session_dir / "journal.sqlite").exists():
        return []
    j = Journal.open_readonly(session_dir, check="none")
    try:
        return j.verify()          # SQLite's integrity check among the rest
    finally:
        j.close()


def baseline_rss_mb(plan: Path, env: dict[str, str]) -> float:
    """Peak RSS of ``elastoprobe check PLAN`` (the CLI, plan and cell loaded, no session)."""
    proc = subprocess.Popen(CLI + ["check", str(plan)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    peak_mb = 0.0
    while proc.poll() is None:           # sampled: the peak since exec, until it exits
        peak_mb = max(peak_mb, _vm_mb(proc.pid, "VmHWM") or 0.0)
        time.sleep(0.02)
    return peak_mb


# ----------------------------------------------------------------------------- accounting
def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of a JSON-lines file (the simulator's fault record, the session's log);
    a line cut by a kill mid-write is left out; [] when the file does not exist."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text(errors="replace").splitlines():
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:     # a line cut by a kill mid-write
                continue
    return out


def step_done_counts(session_dir: Path) -> dict[int, int]:
    """``step_done`` lines per step in DIR/log.jsonl (one per commit, written after it)."""
    counts: dict[int, int] = {}
    for rec in read_jsonl(session_dir / "log.jsonl"):
        if rec.get("event") == "step_done":
            counts[int(rec["step"])] = counts.get(int(rec["step"]), 0) + 1
    return counts


def judge_faults(records: list[dict[str, Any]], session_dir: Path, children: list[ChildRun]) -> dict[str, Any]:
    """Each injected fault (once per kind and step key) against the journal: its fate."""
    from elastoprobe.controller.journal import Journal

    j = Journal.open_readonly(session_dir, check="none")
    try:
        run_of_pid = {int(r["pid"]): int(r["run_id"]) for r in j.runs()}
        faults = j.faults(with_raw=False)
        transitions = j.transitions()
        steps = j.steps()
    finally:
        j.close()
    run_of_fault = {f.fault_id: f.run_id for f in faults}
    status = {r.step_id: r.status for r in steps}
    step_phase = {r.step_id: r.phase for r in steps}
    # How far each run's robot clock got (its last transition or fault): a killed run
    # that went on past a fault's match window had its chance to see it.
    last_t_of_run: dict[int, float] = {}
    for run_id, t in [(t["run_id"], t["t_robot_s"]) for t in transitions] + [(f.run_id, f.t_robot_s) for f in faults]:
        if run_id is not None and t is not None:
            last_t_of_run[int(run_id)] = max(float(t), last_t_of_run.get(int(run_id), -math.inf))
    paused_fault_ids = _paused_fault_ids(children, faults, run_of_fault, run_of_pid)
    injected = [r for r in records if r.get("event") == "injected"]
    effect_at = {(r["kind"], tuple(r["key"] or ()), r["plan"], r["pid"]): r["t_s"]
                 for r in records if r.get("event") == "effect"}
    effects = set(effect_at)
    claimed: set[int] = set()
    fates: dict[tuple, list[dict[str, Any]]] = {}    # identity (kind, step key, plan) -> its firings
    for rec in judging_order(injected, run_of_pid):
        ident = (rec["kind"], tuple(rec["key"] or ()), rec["plan"])
        run_id = run_of_pid.get(rec["pid"])
        match = journaled_match(rec, run_id, faults, run_of_fault, claimed)
        fate: dict[str, Any] = {"kind": rec["kind"], "key": list(ident[1]), "run_id": run_id,
                                "t_s": round(rec["t_s"], 3), "phase": phase_of_key(ident[1], step_phase)}
        if rec.get("follows"):
            fate["follows"] = rec["follows"]
        if (rec["kind"], ident[1], rec["plan"], rec["pid"]) in effect_at:
            fate["effect_t_s"] = round(effect_at[(rec["kind"], ident[1], rec["plan"], rec["pid"])], 3)
        if match is not None:
            claimed.add(match.fault_id)
            fate.update(fault_id=match.fault_id, seen_as=match.kind, step=match.step_id, action=match.policy_action,
                        detected_after_s=round(match.t_robot_s - rec["t_s"], 1))
            if match.fault_id in paused_fault_ids:
                fate["fate"] = "paused"
            elif match.policy_action in ("retry", "skip_target") and (
                    match.step_id is None or status.get(match.step_id) in ("done", "skipped")):
                fate["fate"] = "recovered"     # retried or skipped per policy, and the session went on
            elif match.policy_action == "pause" and _killed_run(run_id, children, run_of_pid) and (
                    match.step_id is None or status.get(match.step_id) in ("done", "skipped")):
                # Journaled as a pause, then a SIGKILL landed before the process could exit 3:
                # the resume finished the step, as it would have after the pause.
                fate.update(fate="paused", killed_while_pausing=True)
            else:
                fate["fate"] = "unresolved"
        elif rec.get("effective") is False or rec["kind"] in ("scanner_timeout", "scanner_short_burst", "slip") and \
                (rec["kind"], ident[1], rec["plan"], rec["pid"]) not in effects:
            # A scanner fault with no scan asked, a slip with no contact, a stop of an arm
            # already stopped (or a lost connection already lost): nothing any device showed.
            fate["fate"] = "no_effect"
        elif (during := _paused_during_recovery(rec, run_id, faults, run_of_fault, paused_fault_ids)) is not None:
            # It struck while the controller recovered from an earlier fault: recovery
            # failed and the session paused cleanly, naming the earlier fault.
            fate.update(fate="paused", journaled=False, paused_recovering_from=during)
        elif (retry := absorbed_by_retry(rec, run_id, faults, run_of_fault, status)) is not None:
            # It struck a contact the controller had already given up on (a retry fault of
            # that step was journaled first): the retry pressed the contact again from its
            # first level under a new key, so nothing it touched was kept.
            fate.update(fate="recovered", journaled=False, absorbed_by=retry)
        elif lost_to_kill(rec, run_id, children, run_of_pid, last_t_of_run):
            fate["fate"] = "lost_to_kill"     # the process died before journaling it
        else:
            fate["fate"] = "undetected"
        earlier = fates.get(ident, [])
        if earlier and earlier[-1]["fate"] == "lost_to_kill":
            # The same fault drawn again by the resumed process: one fault, judged by its last firing.
            fate["after_kill"] = earlier[-1].get("after_kill", 0) + 1
            earlier[-1] = fate
        else:
            if earlier:
                # Journaled before, and met again by a resumed process under the same step key.
                fate["repeat_of_fault_id"] = earlier[-1].get("fault_id")
            earlier.append(fate)
        fates[ident] = earlier
        if rec.get("follows") and fate["fate"] in ("recovered", "paused") and "fault_id" in fate:
            _supersede(fates, rec["follows"], ident[1], run_id, fate["fault_id"])
    all_fates = [f for group in fates.values() for f in group]
    share_burst(all_fates)
    other = [f for f in faults if f.fault_id not in claimed]
    during = [f for f in faults if _RECOVERY_PREFIX.match(f.message or "")]
    return {"fates": all_fates, "raw_injections": len(injected),
            "journaled_other": _histogram(f.kind for f in other),
            # Faults the controller met while recovering from another (journaled "during
            # recovery from K"): retried in a nested recovery, or paused on.
            "journaled_during_recovery": _histogram(f"{f.kind} {f.policy_action}" for f in during),
            "nested_recoveries": sum(f.policy_action == "retry" for f in during)}


SCANNER_KINDS = ("scanner_timeout", "scanner_short_burst")


def share_burst(fates: list[dict[str, Any]]) -> None:
    """Two scanner faults that spoiled the same burst (their first effect at the same robot
    instant in the same run) show as one: the burst came short, one scanner fault is
    journaled and retried. The one left unmatched is judged by that fault, not undetected."""
    seen = {(f["run_id"], f["effect_t_s"]): f for f in fates
            if f["kind"] in SCANNER_KINDS and "effect_t_s" in f and "fault_id" in f}
    for f in fates:
        if f["kind"] in SCANNER_KINDS and f["fate"] == "undetected" and "effect_t_s" in f:
            other = seen.get((f["run_id"], f["effect_t_s"]))
            if other is not None and other["fate"] in ("recovered", "paused"):
                f.update(fate=other["fate"], same_burst_as=other["fault_id"])


def judging_order(injected: list[dict[str, Any]], run_of_pid: dict[int, int]) -> list[dict[str, Any]]:
    """The order in which injections claim journaled faults: by run, then by robot time.

    A moved object may be seen many contacts later (its match window is open-ended), so it
    claims a journaled fault only after every fault of its run with a closed window has
    claimed its own: else it takes the slip fault a later slip caused, and that slip is
    judged undetected while the move, never seen, is judged recovered."""
    return sorted(injected, key=lambda r: (run_of_pid.get(r["pid"], 10**9), r["kind"] == "object_moved", r["t_s"]))


def _supersede(fates: dict[tuple, list[dict[str, Any]]], kind: str, key: tuple, run_id: int | None,
               fault_id: int) -> None:
    """A follow-up fault struck before the controller could see the one it follows (a scanner
    timeout is seen only when the burst's deadline passes): the follow-up was journaled and
    recovered, and its retry repeated the work the first one spoiled. The first is judged
    recovered by that retry, not undetected."""
    for group in fates.values():
        for fate in reversed(group):
            if fate["kind"] == kind and tuple(fate["key"]) == key and fate["run_id"] == run_id \
                    and fate["fate"] == "undetected":
                fate.update(fate="recovered", superseded_by=fault_id)
                return


def journaled_match(rec: dict[str, Any], run_id: int | None, faults: list[Any], run_of_fault: dict[int, int],
                    claimed: set[int]) -> Any:
    """The first unclaimed journaled fault of the same run that reports an injection ``rec``:
    a kind the controller reports it as, journaled within the match window after it."""
    if rec.get("effective") is False:
        # A stop of an arm already stopped changed nothing: it claims no journaled fault
        # (else it would take the one a later, real fault caused).
        return None
    # A moved object stays moved: it is seen when a scan line first crosses relief that
    # shows the shift, which may be many contacts later (in the same process).
    window_s = math.inf if rec["kind"] == "object_moved" else MATCH_WINDOW_S
    for f in faults:
        if (f.fault_id not in claimed and run_of_fault[f.fault_id] == run_id and f.t_robot_s is not None
                and rec["t_s"] - 1e-6 <= f.t_robot_s <= rec["t_s"] + window_s
                and f.kind in SEEN_AS[rec["kind"]]):
            return f
    return None


PHASE_NAMES = {"sampling": "survey", "regions": "characterize", "densify": "densify"}


def phase_of_key(key: tuple[int, ...], step_phase: dict[int, str]) -> str:
    """The phase a fault was drawn in, from its simulator key (seed, step, attempt)."""
    if not key:
        return "outside any step"
    step = int(key[1])
    if step >= SWEEP_KEY - 100:
        return "sweeping"
    if LEARN_KEY - 100 <= step <= LEARN_KEY:
        return "learning"
    return PHASE_NAMES.get(step_phase.get(step, ""), "probing")


_RECOVERY_PREFIX = re.compile(r"during recovery from ([a-z_]+): ")


def _paused_fault_ids(children: list[ChildRun], faults: list[Any], run_of_fault: dict[int, int],
                      run_of_pid: dict[int, int]) -> set[int]:
    """The last fault of each run whose child exited 3 on it (its pause reason names the
    fault) and that a later child resumed.

    A fault journaled while recovering from an earlier one ("during recovery from K: ...")
    ends the run with the pause reason of the fault it interrupted (K): it counts as paused
    on that reason too."""
    last_of_run: dict[int, Any] = {}
    for f in faults:
        last_of_run[run_of_fault[f.fault_id]] = f
    paused: set[int] = set()
    for i, child in enumerate(children[:-1]):
        run_id = run_of_pid.get(child.pid)
        last = last_of_run.get(run_id)
        if child.returncode != 3 or not child.pause_reason or last is None:
            continue
        reason = child.pause_reason
        interrupted = _RECOVERY_PREFIX.match(last.message or "")
        if (reason.startswith(last.kind) or (last.kind == "disk_error" and reason.startswith("journal write failed"))
                or (interrupted is not None and reason.startswith(interrupted.group(1)))):
            paused.add(last.fault_id)
            if interrupted is None:
                continue
            # One recovery may meet more than one fault (a protective stop and a trip latched
            # while the link was down): each journaled "during recovery from K" just before
            # it is named in the same pause.
            of_run = [f for f in faults if run_of_fault[f.fault_id] == run_id]
            for f in reversed(of_run[:-1]):
                also = _RECOVERY_PREFIX.match(f.message or "")
                if also is None or also.group(1) != interrupted.group(1):
                    break
                paused.add(f.fault_id)
    return paused


def _paused_during_recovery(rec: dict[str, Any], run_id: int | None, faults: list[Any],
                            run_of_fault: dict[int, int], paused_fault_ids: set[int]) -> int | None:
    """The fault id a run paused on, if ``rec`` fired after it was journaled (within the
    match window) and nothing was journaled after it in that run."""
    of_run = [f for f in faults if run_of_fault[f.fault_id] == run_id]
    if not of_run or of_run[-1].fault_id not in paused_fault_ids:
        return None
    last = of_run[-1]
    if last.t_robot_s is not None and last.t_robot_s - 1e-6 <= rec["t_s"] <= last.t_robot_s + MATCH_WINDOW_S:
        return int(last.fault_id)
    return None


# Faults whose effect ends with the contact in flight (a moved object stays moved, and a
# stop or a lost link is seen by the recovery itself).
CONTACT_KINDS = ("slip", "force_spike", "ft_frozen", "ft_stall", "scanner_timeout", "scanner_short_burst")


def absorbed_by_retry(rec: dict[str, Any], run_id: int | None, faults: list[Any], run_of_fault: dict[int, int],
                      status: dict[int, str]) -> int | None:
    """The journaled fault whose retry absorbed ``rec``: a contact fault that fired under a
    step key the controller had already left, because it journaled a retry fault of that
    step in the same run (within the match window before ``rec``), and the step was then
    done. The key (seed, step, attempt) names the attempt in flight: an attempt index below
    the number of faults journaled against the step by then is an attempt already being
    discarded (the night of issue #15 met it: a slip 1 s after a lost connection, during
    the recovery's retract, at step 2091 of run 49)."""
    key = rec.get("key") or ()
    if rec["kind"] not in CONTACT_KINDS or len(key) < 3 or status.get(int(key[1])) != "done":
        return None
    step_id, attempt = int(key[1]), int(key[2])
    in_run = [f for f in faults if f.step_id == step_id and f.t_robot_s is not None
              and run_of_fault[f.fault_id] == run_id and f.t_robot_s - 1e-6 <= rec["t_s"]]
    if not in_run:
        return None
    last = in_run[-1]
    # Fault ids grow through the night, across resumed runs: every fault of the step up to
    # ``last``. The key counted the faults of the whole contact (every level) when it was
    # drawn, so this undercounts it, never the other way: a doubt keeps it undetected.
    journaled = sum(f.step_id == step_id and f.fault_id <= last.fault_id for f in faults)
    if journaled <= attempt:
        return None       # nothing journaled against this attempt: it was the one in flight
    if last.policy_action == "retry" and rec["t_s"] <= last.t_robot_s + MATCH_WINDOW_S:
        return int(last.fault_id)
    return None


def _killed_run(run_id: int | None, children: list[ChildRun], run_of_pid: dict[int, int]) -> bool:
    """Whether the child that made journal run ``run_id`` was SIGKILLed."""
    return any(run_of_pid.get(c.pid) == run_id and c.returncode == -9 for c in children)


def lost_to_kill(rec: dict[str, Any], run_id: int | None, children: list[ChildRun], run_of_pid: dict[int, int],
                 last_t_of_run: dict[int, float]) -> bool:
    """Whether an unjournaled injection died with its process: the run was SIGKILLed before
    its robot clock passed the end of the injection's match window. A run that went on
    longer had the time to see it, and did not: that is undetected, whatever killed it later."""
    if not _killed_run(run_id, children, run_of_pid):
        return False
    last_t = last_t_of_run.get(run_id) if run_id is not None else None
    return last_t is None or last_t < rec["t_s"] + MATCH_WINDOW_S


def _histogram(items: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for k in items:
        out[k] = out.get(k, 0) + 1
    return dict(sorted(out.items()))


def step_accounting(session_dir: Path, ever_done: set[int]) -> dict[str, Any]:
    from elastoprobe.controller.journal import Journal

    counts = step_done_counts(session_dir)
    committed = set(counts) | ever_done
    j = Journal.open_readonly(session_dir, check="none")
    try:
        steps = j.steps()
        robot_h = j.robot_time_s()["total"] / 3600.0
    finally:
        j.close()
    final = {r.step_id: r.status for r in steps}
    lost_after_done = sorted(s for s in committed if final.get(s) != "done")
    never_finished = sorted(s for s, st in final.items() if st not in ("done", "skipped"))
    duplicated = sorted(s for s, n in counts.items() if n > 1)
    return {"robot_hours": robot_h, "steps_planned": len(final),
            "steps_done": sum(st == "done" for st in final.values()),
            "steps_skipped": sum(st == "skipped" for st in final.values()),
            "steps_lost": len(lost_after_done) + len(never_finished),
            "steps_lost_ids": (lost_after_done + never_finished)[:50],
            "steps_duplicated": len(duplicated), "steps_duplicated_ids": duplicated[:50]}


# A child's first 0.1 robot hours are its warm-up: a fresh process fills its caches and
# heap (the simulated contact models, SQLite's page cache, numpy's and glibc's pools) over
# its first few dozen steps, then levels off. The night of issue #15 had ~50 children
# between pauses, each living 0.05-0.4 robot hours: their stretches were mostly warm-up,
# and a rise that stops was read as 11.3 MB/h. Re-judged with the warm-up counted it reads
# 9.6 MB/h, past 0.05 h 5.1, past 0.1 h 3.9, past 0.15 h 1.7 (its longest stretch, 0.33 h,
# was flat): a rise that levels off.
WARMUP_ROBOT_H = 0.1


def _probing_stretches(child: ChildRun, warmup_h: float) -> list[list[tuple[float, float]]]:
    """(robot h, RSS MB) runs where robot time advances within one committed phase, past the
    child's warm-up (its first ``warmup_h`` robot hours of probing)."""
    stretches: list[list[tuple[float, float]]] = []
    stretch: list[tuple[float, float]] = []
    prev_robot, prev_rss, prev_phases = None, 0.0, None
    start_h = None
    for sample in list(child.samples) + [(0.0, 0.0, -1.0, None)]:     # a sentinel closes the last stretch
        _, rss, robot_s = sample[:3]
        phases = sample[3] if len(sample) > 3 else None
        # A stretch is probing only: a learning phase committed between two samples
        # (its models, maps and torch stay resident) ends it, as start-up does.
        same_phase = phases == prev_phases or phases is None or prev_phases is None
        advancing = prev_robot is not None and robot_s > prev_robot and same_phase
        if advancing and start_h is None:
            start_h = prev_robot / 3600.0
        warm = start_h is not None and prev_robot is not None and prev_robot / 3600.0 >= start_h + warmup_h
        if advancing and warm:
            if not stretch:
                stretch.append((prev_robot / 3600.0, prev_rss))
            stretch.append((robot_s / 3600.0, rss))
        elif stretch:
            stretches.append(stretch)
            stretch = []
        prev_robot, prev_rss, prev_phases = robot_s, rss, phases
    return stretches


def stretch_growth_mb_per_h(hours: np.ndarray, rss_mb: np.ndarray) -> float:
    """One stretch's growth: the median RSS of its last third less that of its first third,
    over the robot hours between the thirds' middles. A leak's steps (an allocator grows its
    heap by chunks) move it however sparse they are; a sample or two of a passing spike (the
    moment a pause begins, the end of a re-registration) does not."""
    k = len(hours) // 3
    dh = float(np.median(hours[-k:]) - np.median(hours[:k]))
    return float(np.median(rss_mb[-k:]) - np.median(rss_mb[:k])) / dh if dh > 0 else 0.0


def rss_growth_mb_per_h(children: list[ChildRun], min_span_h: float = 0.05, min_samples: int = 9,
                        warmup_h: float = WARMUP_ROBOT_H) -> tuple[float | None, float]:
    """RSS growth (MB per robot hour) within processes, over probing stretches past each
    child's warm-up: :func:`stretch_growth_mb_per_h` per stretch, averaged weighted by its
    robot hours. The night of issue #15 took a Theil-Sen slope per stretch from the
    child's start: its ~50 short-lived children were mostly warm-up, and one stretch of
    0.06 h (7 samples) that began at a re-registration's end read 290 MB/h. Returns
    (growth, robot hours used)."""
    growths, weights = [], []
    for c in children:
        for stretch in _probing_stretches(c, warmup_h):
            span = stretch[-1][0] - stretch[0][0]
            if span >= min_span_h and len(stretch) >= min_samples:
                h, m = np.array(stretch).T
                growths.append(stretch_growth_mb_per_h(h, m))
                weights.append(span)
    if not growths:
        return None, 0.0
    w = np.array(weights)
    return float(np.dot(growths, w) / w.sum()), float(w.sum())


def rss_growth_across_children_mb_per_h(children: list[ChildRun],
                                        warmup_h: float = WARMUP_ROBOT_H) -> tuple[float | None, int]:
    """RSS slope (MB per robot hour) of the settled level from child to child: each child's
    median RSS over its probing past warm-up, against its robot time (Theil-Sen). What a
    session carries from its journal (steps loaded, the object's dents) grows with the
    night however often it is resumed; this sees it where the per-process slope cannot.
    Returns (slope, children used)."""
    from scipy.stats import theilslopes

    level_h, level_mb = [], []
    for c in children:
        points = [p for st in _probing_stretches(c, warmup_h) for p in st]
        if len(points) >= 5:
            h, m = np.array(points).T
            level_h.append(float(np.median(h)))
            level_mb.append(float(np.median(m)))
    if len(level_h) < 3 or max(level_h) - min(level_h) < 0.5:
        return None, len(level_h)
    return float(theilslopes(level_mb, level_h)[0]), len(level_h)


# ----------------------------------------------------------------------------- the soak
def _children_from_state(state: dict[str, Any]) -> list[ChildRun]:
    return [ChildRun(**{**c, "samples": [tuple(x) for x in c["samples"]]}) for c in state["children"]]


# The args of a child reconstructed from the session (see with_lost_children).
LOST_BY_DRIVER = ("(lost by the driver)",)


def with_lost_children(session_dir: Path, children: list[ChildRun]) -> list[ChildRun]:
    """``children`` with those the driver lost, in journal run order: a run of the session
    whose process is not among them is a child that ended while the driver was not there to
    record it (the driver itself was stopped between the child's exit and the state's save,
    before a --carry-on). Its ending is read from the session: a pause its log records within
    the run's span (exit 3, with that reason), done (0), or, with no end journaled, killed with
    the driver (-9, ``killed="with the driver"``, no kill of the schedule). Nothing is known of
    its memory: no samples.

    Why: the night of stop 24 lost one child this way (the driver's own process was stopped
    at 11:02; the child had journaled a disk-error pause and exited 3 a moment before), and
    its one fault counted as unresolved although the session's log names the pause."""
    from elastoprobe.controller.journal import Journal

    if not (session_dir / "journal.sqlite").exists():
        return children
    j = Journal.open_readonly(session_dir, check="none")
    try:
        runs = j.runs()
    finally:
        j.close()
    known = {c.pid for c in children}
    run_of_pid = {int(r["pid"]): int(r["run_id"]) for r in runs}
    log = read_jsonl(session_dir / "log.jsonl")
    merged = list(children)
    for r in runs:
        if int(r["pid"]) in known:
            continue
        ended = r["ended_utc"]
        within = ([e for e in log if _utc(r["started_utc"]) <= _utc(e.get("t_wall_utc")) <= _utc(ended)]
                  if ended is not None else [])
        paused = [e for e in within if e.get("event") == "session_paused"]
        done = any(e.get("event") == "session_done" for e in within)
        code, reason, killed = ((3, paused[-1].get("reason"), None) if paused else (0, None, None) if done
                                else (-9, None, "with the driver"))
        lost = ChildRun(args=list(LOST_BY_DRIVER), pid=int(r["pid"]), returncode=code, killed=killed,
                        wall_s=0.0, max_rss_mb=0.0, samples=[], pause_reason=reason)
        # After the last child whose run came before it.
        at = max((i + 1 for i, c in enumerate(merged) if run_of_pid.get(c.pid, -1) < int(r["run_id"])
                  and c.pid in run_of_pid), default=0)
        merged.insert(at, lost)
    return merged


def _utc(stamp: Any) -> datetime.datetime:
    """An ISO wall time (the journal's runs, the log's events) as a datetime; the epoch if unreadable."""
    try:
        return datetime.datetime.fromisoformat(str(stamp).replace("Z", "+00:00"))
    except ValueError:
        return datetime.datetime.fromtimestamp(0, datetime.timezone.utc)


def run_soak(cfg: SoakConfig, work_dir: Path, carry_on: bool = False) -> dict[str, Any]:
    """Run one soak in ``work_dir`` (created); returns the JSON-able result.

    ``carry_on``: go on with the soak kept in ``work_dir`` (its state.json) after its driver
    stopped (a child exited 1, the driver was stopped): the same session, cell and plan; the
    kills of the rest are drawn from a generator seeded by the seed and the children so far."""
    t_start = time.monotonic()
    work_dir = work_dir.resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    out = work_dir / "session"
    fault_log = work_dir / "sim_faults.jsonl"
    env = dict(os.environ)
    env.pop("ELASTOPROBE_JOURNAL_CRASH_AT", None)
    env.update({"ELASTOPROBE_LOCK_DIR": str(work_dir / "locks"), FAULT_LOG_ENV: str(fault_log)})
    if carry_on:
        state = json.loads((work_dir / "state.json").read_text())
        children = _children_from_state(state)
        ever_done = set(state.pop("ever_done"))
        del state["children"]
        rng = random.Random(cfg.seed * 1000 + len(children))
        plan = work_dir / "plan.yaml"
        t_start -= state["wall_s"]
    else:
        rng = random.Random(cfg.seed)
        rates = fault_rates(cfg)
        cell = write_cell(work_dir, f"soak-cell-{os.getpid()}", rates, cfg.estop_clear_after_s, cfg.step_faults,
                          cfg.follow_ups_per_100_faults)
        plan = write_plan(work_dir, cell, cfg.plan_overrides)
        base_rss = baseline_rss_mb(plan, env)
        children = []
        ever_done = set()
        state = {"seed": cfg.seed, "rates": rates, "follow_ups": cfg.follow_ups_per_100_faults,
                 "min_robot_hours": cfg.min_robot_hours,
                 "baseline_rss_mb": base_rss, "kills": 0, "kills_by_mode": {}, "kills_by_phase": {},
                 "kills_missed": 0, "operator_clears": 0, "journal_problems": [], "wall_s": 0.0}
    mode_index = state["kills"] - state["kills_by_mode"].get("learning", 0)
    next_kill_robot_s = 0.0
    while len(children) < cfg.max_children:
        resume = (out / "journal.sqlite").exists()
        args = (["resume", str(out), "--quiet"] if resume else
                ["run", str(plan), "--out", str(out), "--seed", str(cfg.seed), "--quiet"])
        child_env, kill, mode = dict(env), None, None
        crash_specs = []
        robot_now_s = (_journal_poll(out) or (0.0,))[0]
        # The rotation's kill is armed once the night has gone far enough since the last one;
        # the learning kill is armed beside it in every child until its quota has landed.
        learning_kills = state["kills_by_mode"].get("learning", 0)
        if state["kills"] - learning_kills < cfg.kills - cfg.learning_kills:
            mode = cfg.kill_modes[mode_index % len(cfg.kill_modes)] if robot_now_s >= next_kill_robot_s else "progress"
            if mode == "aimed":
                point = rng.choice(sorted(AIMED_NTH))
                crash_specs.append(f"{point}@{rng.randint(*AIMED_NTH[point])}")
            else:
                # Not due yet: armed for the robot moment it is due (the child may run past it).
                kill = ProgressKill(rng.randint(*cfg.kill_after_steps), rng.uniform(*cfg.kill_jitter_s),
                                    at_robot_s=next_kill_robot_s if robot_now_s < next_kill_robot_s else 0.0)
        # Not in the child right after a learning kill: it would kill the same learning
        # phase again; the next one gets its turn.
        if learning_kills < cfg.learning_kills and not (children and children[-1].killed == f"aimed {LEARNING_POINT}"):
            crash_specs.append(LEARNING_POINT)
        if crash_specs:
            child_env["ELASTOPROBE_JOURNAL_CRASH_AT"] = ",".join(crash_specs)
        child = run_child(args, child_env, out, kill, cfg.sample_s, cfg.child_timeout_s, ever_done,
                          work_dir / "children.stderr")
        session_status, reason = _session_status(out)
        child.pause_reason = reason if child.returncode == 3 else None
        # The operator answers the session's state, not how its process ended: a kill that
        # lands after an e-stop was journaled as a pause, but before the child exited 3,
        # leaves the same paused session and the same e-stop to release.
        estop_paused = session_status == "paused" and bool(reason) and "emergency_stop" in reason
        children.append(child)
        state["journal_problems"] += [f"after child {len(children)}: {p}" for p in journal_soundness(out)]
        stop = False
        if child.returncode == -9 and child.killed not in (None, "timeout"):
            landed = ("learning" if child.killed == f"aimed {LEARNING_POINT}" else
                      "aimed" if child.killed.startswith("aimed") else "progress")
            child.kill_phase = kill_phase(out, child.pid)
            state["kills"] += 1
            state["kills_by_mode"][landed] = state["kills_by_mode"].get(landed, 0) + 1
            state["kills_by_phase"][child.kill_phase or "?"] = state["kills_by_phase"].get(child.kill_phase or "?", 0) + 1
            if landed != "learning":
                mode_index += 1
                next_kill_robot_s = (_journal_poll(out) or (0.0,))[0] + cfg.kill_every_robot_s
            if estop_paused:
                time.sleep(cfg.operator_delay_s)
                state["operator_clears"] += 1
        elif child.returncode == 3:
            if mode is not None and child.kill_due:
                state["kills_missed"] += 1       # its kill's moment had come, and it paused first
            elif mode is not None:
                state["kills_not_due"] = state.get("kills_not_due", 0) + 1   # paused before the moment
            # The operator plays their part whatever kill was armed (a pause on an e-stop
            # while a learning kill waited was left uncounted, and the short run's judge
            # then missed its operator release).
            if estop_paused:
                time.sleep(cfg.operator_delay_s)     # the operator walks over and releases it
                state["operator_clears"] += 1
        else:
            stop = True                              # done (0), or a fault/bad input (1, 2)
        state["wall_s"] = time.monotonic() - t_start
        _save_state(work_dir, state, children, ever_done)
        if stop:
            break
    return summarize(work_dir)


def summarize(work_dir: Path) -> dict[str, Any]:
    """The soak's figures from a work directory (its session, fault record and state.json)."""
    state = json.loads((work_dir / "state.json").read_text())
    out = work_dir / "session"
    children = with_lost_children(out, _children_from_state(state))
    ever_done = set(state["ever_done"])
    status, reason = _session_status(out)
    facts = step_accounting(out, ever_done) if (out / "journal.sqlite").exists() else {}
    judged = judge_faults(read_jsonl(work_dir / "sim_faults.jsonl"), out, children) if facts else {"fates": []}
    fates = judged["fates"]
    count = lambda what: sum(f["fate"] == what for f in fates)   # noqa: E731
    growth, growth_h = rss_growth_mb_per_h(children)
    across, across_n = rss_growth_across_children_mb_per_h(children)
    return {
        "robot_hours": round(facts.get("robot_hours", 0.0), 3),
        "faults_injected": len(fates),
        "faults_with_effect": len(fates) - count("no_effect"),
        "faults_recovered": count("recovered"),
        "faults_paused": count("paused"),
        "kills": state["kills"],
        "steps_lost": facts.get("steps_lost"),
        "steps_duplicated": facts.get("steps_duplicated"),
        "peak_rss_mb": round(max((c.max_rss_mb for c in children), default=0.0), 1),
        "rss_growth_mb_per_h": None if growth is None else round(growth, 2),
        "baseline_rss_mb": round(state["baseline_rss_mb"], 1),
        "faults_undetected": count("undetected"),
        "faults_no_effect": count("no_effect"),
        "faults_lost_to_kill": count("lost_to_kill"),
        "faults_unresolved": count("unresolved"),
        "faults_neither": [f for f in fates if f["fate"] not in ("recovered", "paused")],
        "faults_paused_unjournaled": [f for f in fates if f.get("journaled") is False],
        "faults_repeated_after_resume": [f for f in fates if "repeat_of_fault_id" in f],
        "faults_by_kind": {k: _histogram(f["fate"] for f in fates if f["kind"] == k)
                           for k in sorted({f["kind"] for f in fates})},
        "faults_by_phase": {p: _histogram(f["fate"] for f in fates if f["phase"] == p)
                            for p in sorted({f["phase"] for f in fates})},
        "faults_during_recovery": _histogram(f["fate"] for f in fates if f.get("follows")),
        "nested_recoveries": judged.get("nested_recoveries", 0),
        "journaled_during_recovery": judged.get("journaled_during_recovery", {}),
        "faults_injected_per_8h": (round(len(fates) * 8.0 / facts["robot_hours"], 1)
                                   if facts.get("robot_hours") else None),
        "kills_by_mode": state.get("kills_by_mode", {}),
        "kills_by_phase": state.get("kills_by_phase", {}),
        "kills_missed": state.get("kills_missed", 0),
        "kills_armed_not_due": state.get("kills_not_due", 0),
        "fault_injections_raw": judged.get("raw_injections", 0),
        "faults_journaled_not_injected": judged.get("journaled_other", {}),
        "fault_rates_per_100_steps": state["rates"],
        "follow_ups_per_100_faults": state.get("follow_ups", {}),
        "status": status, "status_reason": reason,
        "children": len(children), "resumes": max(len(children) - 1, 0),
        "children_lost_by_driver": sum(c.args == list(LOST_BY_DRIVER) for c in children),
        "operator_clears": state["operator_clears"],
        "exit_codes": [c.returncode for c in children],
        "kill_moments": [f"{c.killed} ({c.kill_phase})" for c in children if c.killed],
        "pauses": [c.pause_reason for c in children if c.returncode == 3],
        "steps_planned": facts.get("steps_planned"), "steps_done": facts.get("steps_done"),
        "steps_skipped": facts.get("steps_skipped"),
        "steps_lost_ids": facts.get("steps_lost_ids"), "steps_duplicated_ids": facts.get("steps_duplicated_ids"),
        "journal_problems": state["journal_problems"],
        "rss_growth_robot_hours_used": round(growth_h, 3),
        "rss_growth_across_children_mb_per_h": None if across is None else round(across, 2),
        "rss_growth_across_children_used": across_n,
        "min_robot_hours": state["min_robot_hours"],
        "seed": state["seed"], "wall_s": round(state["wall_s"], 1),
        "session_dir": str(out),
        "last_stderr": children[-1].stderr_tail[-1500:] if children and children[-1].returncode not in (0, 3, -9) else "",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the short soak (about a minute) instead of the night")
    ap.add_argument("--part", type=int, choices=(2, 4), default=None,
                    help="half (2) or a quarter (4) of the night: its faults and kills on its plan cut down in "
                         "every phase")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="work in this directory and keep it")
    ap.add_argument("--judge", type=Path, default=None, help="only re-judge a kept work directory")
    ap.add_argument("--carry-on", type=Path, default=None,
                    help="go on with the soak kept in this directory (same options as it was started with)")
    a = ap.parse_args(argv)
    if a.judge is not None:
        print(json.dumps(summarize(a.judge.resolve()), indent=1))
        return 0
    cfg = QUICK if a.quick else part_of_night(a.part) if a.part else FULL
    if a.seed is not None:
        cfg = SoakConfig(**{**asdict(cfg), "seed": a.seed})
    if a.carry_on is not None:
        print(json.dumps(run_soak(cfg, a.carry_on, carry_on=True), indent=1))
        return 0
    work = a.keep if a.keep is not None else Path(tempfile.mkdtemp(prefix="soak-"))
    try:
        result = run_soak(cfg, work)
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
