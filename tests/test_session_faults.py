"""Every fault the simulated cell can inject, in a session: the arm stops, the plan's fault
policy is followed, and no step is committed done with incomplete data (docs/design.md §5, §6).

Sessions run in this process (``Session.run`` returns the CLI's exit codes) on a tiny plan
whose survey has eleven contacts (two angles per target), with faults placed at contacts'
first steps through the cell file's ``simulation.faults`` (steps fixed by the committed
survey plan). One session carries the nine device faults under the default retry policy;
another walks the pausing ones (emergency stop, disk error, a fault the plan says to
pause on) through resumes to the end. Abort and skip policies are checked in short
sessions. The fault a device shows is what the controller journals; the simulator's own
list of what it injected is the ground truth it is judged against.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from test_session_util import copy_cell, done_step_facts, outcome, plan_for

from elastoprobe.controller.core.config import load_session_inputs
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.journal import Journal
from elastoprobe.controller.session import EXIT_DONE, EXIT_FAULT, EXIT_PAUSED, Session

SEED = 2
REPO = Path(__file__).resolve().parent.parent
SIM_CELL = REPO / "config" / "cells" / "sim.yaml"
SCANS_PER_STEP = 5
FORCE_TOLERANCE_N = 0.5

# The survey: the targets kept when planned (five with seed 2: two more would have the
# scanner meet the box wall on the way down) x angles [90, 80] x forces [4, 12], step ids
# 0-19; each contact's first step id is even. The object's move (12 mm) takes a direction
# drawn per step: only a move the scan lines can see counts. At step 0 it runs along -y and
# the first target's line (along y) reaches the pillow's rounded rim beyond the dent (tried
# at the target beside the box wall, steps 4 and 6: along x at 4, and at 6 no scan showed it).
SURVEY_EDITS = {
    "    angles_deg: [90]\n    forces_n: [4.0, 12.0]": "    angles_deg: [90, 80]\n    forces_n: [4.0, 12.0]",
    "    angles_deg: [75, 90, 105]": "    angles_deg: [90]",
    "    rounds: 1": "    rounds: 0",
}
# Device faults -> the fault kind the controller sees (its policy key).
RETRY_FAULTS = {
    "force_spike": (6, {"force", "force_rate"}),
    "ft_stall": (2, {"stale"}),
    "ft_frozen": (4, {"frozen"}),
    "scanner_timeout": (8, {"scanner"}),
    "scanner_short_burst": (10, {"scanner"}),
    "protective_stop": (12, {"protective_stop"}),
    "connection_loss": (14, {"connection", "device"}),
    "slip": (16, {"slip"}),
    "object_moved": (0, {"object_moved"}),
}


def _setup(tmp: Path, name: str, faults: list[dict[str, Any]], policy: str | None = None) -> Path:
    cell = copy_cell(SIM_CELL, tmp, name)
    text = cell.read_text()
    items = "".join(f"    - {json.dumps(f)}\n" for f in faults)
    cell.write_text(text.rstrip("\n") + "\n  faults:\n" + items)
    edits = dict(SURVEY_EDITS)
    if policy is not None:
        edits["fault_policy:\n  default: {action: retry, retries: 2}\n  kinds:\n    no_contact: {action: skip_target}\n"] = policy
    return plan_for(cell, tmp, edits=edits)


def _run(plan: Path, out: Path, resume: bool = False) -> tuple[int, Session]:
    session = Session(load_session_inputs(plan), out, SEED)
    return session.run(resume=resume), session


def _fault_events(out: Path) -> list[dict[str, Any]]:
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    return [e for e in events if e["event"] == "fault"]


def _assert_complete_data(out: Path) -> None:
    """No step is done with incomplete data: full scans, valid checksums, force at its level."""
    facts = done_step_facts(out)
    assert facts, "no step was done"
    for f in facts:
        assert f["n_scans"] == SCANS_PER_STEP, f
        assert f["finite"], f
        allowed = max(3 * FORCE_TOLERANCE_N, 0.15 * f["force_target_n"])
        assert f["force_target_n"] - allowed <= f["force_min_n"] <= f["force_max_n"] <= f["force_target_n"] + allowed, f
    got = outcome(out)
    assert got.integrity == ["ok"] and got.problems == []


def _assert_stopped_at_faults(out: Path) -> None:
    for e in _fault_events(out):
        if "arm" in e:
            assert e["arm"]["is_moving"] is False, e
            assert e["arm"]["tcp_speed_mm_s"] < 1.0, e


@pytest.fixture(scope="module")
def retry_session(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp = tmp_path_factory.mktemp("faults_retry")
    faults = [{"kind": k, "step": s} for k, (s, _) in RETRY_FAULTS.items()]
    plan = _setup(tmp, "faults-retry-cell", faults)
    out = tmp / "session"
    code, session = _run(plan, out)
    injected = [k for k, _ in session.cell.faults.injected]   # type: ignore[union-attr]
    true_placement = session.cell.world.base_to_object       # type: ignore[union-attr]
    return {"code": code, "out": out, "injected": injected, "true_placement": true_placement}


def test_every_device_fault_is_injected_and_the_session_ends_done(retry_session: dict[str, Any]) -> None:
    assert retry_session["code"] == EXIT_DONE
    assert set(retry_session["injected"]) == set(RETRY_FAULTS)


@pytest.mark.parametrize("kind", list(RETRY_FAULTS))
def test_fault_is_journaled_retried_and_the_contact_completes(retry_session: dict[str, Any], kind: str) -> None:
    out = retry_session["out"]
    step, seen_as = RETRY_FAULTS[kind]
    j = Journal.open_readonly(out)
    try:
        group = [r for r in j.steps() if r.phase == "sampling" and r.step_id in (step, step + 1)]
        faults = [f for f in j.faults() if f.step_id in (step, step + 1)]
        assert faults, f"{kind} at step {step} was not journaled (faults: {[(f.kind, f.step_id) for f in j.faults()]})"
        assert faults[0].kind in seen_as, (kind, faults[0].kind, faults[0].message)
        if faults[0].kind in ("no_contact",):
            assert faults[0].policy_action == "skip_target"
            assert all(r.status == "skipped" for r in group if r.step_id >= faults[0].step_id)
        else:
            assert faults[0].policy_action == "retry"
            # The retry finished the contact: both levels done, each once.
            assert [r.status for r in group] == ["done", "done"], [(r.step_id, r.status) for r in group]
        if faults[0].kind in ("force", "force_rate", "stale", "frozen", "slip"):
            assert faults[0].raw is not None and len(faults[0].raw) > 0   # the last seconds of F/T data
    finally:
        j.close()


def test_a_moved_object_is_registered_again_where_it_really_is(retry_session: dict[str, Any]) -> None:
    """The re-registration after object_moved finds the simulator's true placement."""
    j = Journal.open_readonly(retry_session["out"])
    try:
        events = j.events(kind="object_registered")
    finally:
        j.close()
    assert len(events) == 1, events
    rec = events[0]["record"]
    believed = Pose.from_list(rec["base_to_object"])
    true = retry_session["true_placement"]
    moved_mm = float(np.linalg.norm(rec["shift_mm"]))
    assert moved_mm > 6.0, rec                      # the 12 mm shift was found, not a sliver of it
    error_mm = float(np.linalg.norm(believed.position_mm - true.position_mm))
    assert error_mm < 1.0, (error_mm, rec, true.to_list())
    assert rec["rms_mm"] < 0.5, rec


def test_journaled_transitions_name_the_step_in_flight(retry_session: dict[str, Any]) -> None:
    """A transition inside a contact (the force levels, a fault and its recovery) names the
    step the arm was pressing; travel between targets names none. Before, every journaled
    transition had step_id NULL: the step was only known while its result was written."""
    j = Journal.open_readonly(retry_session["out"])
    try:
        transitions, faults = j.transitions(), j.faults()
        steps = {r.step_id for r in j.steps()}
    finally:
        j.close()
    inside = [t for t in transitions if t["trigger"] in ("contact", "at_force", "settled", "next_level")]
    assert inside and all(t["step_id"] in steps for t in inside), [t for t in inside if t["step_id"] not in steps][:3]
    travel = [t for t in transitions if t["trigger"] == "go_to_target"]
    assert travel and all(t["step_id"] is None for t in travel)
    fault_steps = sorted(t["step_id"] for t in transitions if t["trigger"] == "fault" and t["step_id"] is not None)
    contact_faults = sorted(f.step_id for f in faults if f.step_id is not None)
    assert contact_faults and set(contact_faults) <= set(fault_steps), (contact_faults, fault_steps)


def test_arm_stopped_at_every_fault_and_no_incomplete_step_is_done(retry_session: dict[str, Any]) -> None:
    _assert_stopped_at_faults(retry_session["out"])
    _assert_complete_data(retry_session["out"])


def test_pausing_faults_emergency_stop_disk_error_and_pause_policy_resume_to_the_end(tmp_path: Path) -> None:
    policy = ("fault_policy:\n  default: {action: retry, retries: 2}\n  kinds:\n    no_contact: {action: skip_target}\n"
              "    scanner: {action: pause}\n")
    plan = _setup(tmp_path, "faults-pause-cell",
                  [{"kind": "emergency_stop", "step": 2}, {"kind": "disk_error", "step": 9},
                   {"kind": "scanner_timeout", "step": 14}], policy)
    out = tmp_path / "session"

    # 1. Emergency stop: pause (exit 3); the controller never clears it.
    code, session = _run(plan, out)
    assert code == EXIT_PAUSED
    assert session.cell.arm.status().emergency_stop, "the controller cleared the emergency stop"  # type: ignore[union-attr]
    j = Journal.open_readonly(out)
    try:
        assert j.session()["status"] == "paused"
        # The pause reason tells the operator what stands in the way, not only what happened.
        reason = j.session()["status_reason"]
        assert reason.startswith("emergency_stop: ") and "recovery failed: the emergency stop is still engaged" in reason, reason
        f = j.faults()[-1]
        assert (f.kind, f.step_id, f.policy_action) == ("emergency_stop", 2, "pause")
        assert j.step(2).status != "done" and j.step(0).status == "done"
    finally:
        j.close()
    session.cell.operator_clear_estop()   # type: ignore[union-attr]   # the operator, not the controller

    # 2. Resume: the contact is done now; a disk error on step 9's write pauses cleanly.
    code, _ = _run(plan, out, resume=True)
    assert code == EXIT_PAUSED
    j = Journal.open_readonly(out)
    try:
        assert j.step(2).status == "done" and j.step(3).status == "done"
        assert j.step(8).status == "done" and j.step(9).status != "done"
        assert [f.kind for f in j.faults()][-1] == "disk_error"
        assert j.verify() == []
    finally:
        j.close()

    # 3. Resume: a scanner timeout at step 14, whose policy is pause.
    code, _ = _run(plan, out, resume=True)
    assert code == EXIT_PAUSED
    j = Journal.open_readonly(out)
    try:
        assert j.step(9).status == "done"
        f = j.faults()[-1]
        assert (f.kind, f.step_id, f.policy_action) == ("scanner", 14, "pause")
    finally:
        j.close()

    # 4. Resume to the end: every planned step done or skipped, data complete.
    code, _ = _run(plan, out, resume=True)
    assert code == EXIT_DONE
    got = outcome(out)
    assert set(got.step_status.values()) <= {"done", "skipped"}
    assert all(got.step_status[s] == "done" for s in (2, 3, 9, 14, 15))
    _assert_stopped_at_faults(out)
    _assert_complete_data(out)


def test_abort_policy_ends_the_session_with_exit_1(tmp_path: Path) -> None:
    policy = "fault_policy:\n  default: {action: abort}\n"
    plan = _setup(tmp_path, "faults-abort-cell", [{"kind": "protective_stop", "step": 2}], policy)
    out = tmp_path / "session"
    code, session = _run(plan, out)
    assert code == EXIT_FAULT
    j = Journal.open_readonly(out)
    try:
        assert j.session()["status"] == "aborted"
        f = j.faults()[-1]
        assert (f.kind, f.step_id, f.policy_action) == ("protective_stop", 2, "abort")
        assert j.step(2).status != "done"
        assert j.step(0).status == "done"
    finally:
        j.close()
    assert not session.cell.arm.status().is_moving   # type: ignore[union-attr]
    _assert_stopped_at_faults(out)


@pytest.mark.slow
def test_no_retries_left_skips_the_target(tmp_path: Path) -> None:
    policy = "fault_policy:\n  default: {action: retry, retries: 0}\n"
    plan = _setup(tmp_path, "faults-skip-cell", [{"kind": "ft_stall", "step": 6}, {"kind": "force_spike", "step": 12}],
                  policy)
    out = tmp_path / "session"
    code, _ = _run(plan, out)
    assert code == EXIT_DONE
    j = Journal.open_readonly(out)
    try:
        for step, kinds in ((6, {"stale"}), (12, {"force", "force_rate"})):
            f = [x for x in j.faults() if x.step_id == step]
            assert f and f[0].kind in kinds and f[0].policy_action == "skip_target"
            assert j.step(step).status == "skipped" and j.step(step + 1).status == "skipped"
    finally:
        j.close()
    _assert_complete_data(out)


def test_a_device_error_while_planning_the_travel_is_a_retried_fault_not_an_internal_error(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Seen on the loopback cell: the UR link's child died during a status read that plans
    # the travel to a standoff (it was restarted with the arm stopped); the DeviceError
    # escaped the contact and the session ended in an internal error (exit 1).
    from elastoprobe.controller import probe, toolhead
    from elastoprobe.controller.core.errors import DeviceError

    original_sync, original_probe = toolhead.Toolhead.sync_validator, probe.ProbeExecutor.probe
    state = {"calls": 0, "in_contact": False, "died_in_contact": False}

    def contact(self: Any, *args: Any, **kwargs: Any) -> None:
        state["in_contact"] = True
        try:
            original_probe(self, *args, **kwargs)
        finally:
            state["in_contact"] = False

    def dies_in_the_sweep_and_in_a_contact(self: Any) -> None:
        state["calls"] += 1
        if state["calls"] == 3 or (state["in_contact"] and not state["died_in_contact"]):
            state["died_in_contact"] = state["died_in_contact"] or state["in_contact"]
            raise DeviceError("hardware status: DeviceError: UR link child died during state; restarted, arm stopped")
        original_sync(self)

    monkeypatch.setattr(toolhead.Toolhead, "sync_validator", dies_in_the_sweep_and_in_a_contact)
    monkeypatch.setattr(probe.ProbeExecutor, "probe", contact)
    plan = plan_for(copy_cell(SIM_CELL, tmp_path, "device-error-cell"), tmp_path, edits=dict(SURVEY_EDITS))
    out = tmp_path / "session"
    code, _ = _run(plan, out)
    assert code == EXIT_DONE
    faults = [e for e in _fault_events(out) if e["kind"] == "device"]
    assert state["died_in_contact"]
    assert len(faults) == 2 and all(f["action"] == "retry" and "child died" in f["message"] for f in faults), faults
    assert faults[0].get("phase") == "cloud" and faults[1]["step"] is not None, faults
    _assert_stopped_at_faults(out)
    _assert_complete_data(out)
