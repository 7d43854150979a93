"""A fault that strikes while the controller recovers from another one is seen, journaled
and named in the pause: the guard's trip latched during the wait for the connection or
the protective-stop unlock is never re-armed unseen (issue #15's soak found an F/T stall
during a lost connection in the cloud sweep, and a frozen stream during a protective
stop's recovery, re-armed with the first fault's retry and never journaled; then a
connection lost just after a protective stop, waited out by the recovery and never
journaled; then a protective stop met while the connection was lost, unlocked by that
recovery and never journaled).

Sessions run in this process on the tiny plan; both faults are placed in the cloud sweep
(its simulator key, with delays), and an emergency stop later in the sweep bounds the
session whatever the controller does with them.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from test_session_util import copy_cell, plan_for

from elastoprobe.controller.core.config import load_session_inputs
from elastoprobe.controller.journal import Journal
from elastoprobe.controller.phases import SWEEP_STEP_KEY
from elastoprobe.controller.session import EXIT_PAUSED, Session

REPO = Path(__file__).resolve().parent.parent
SIM_CELL = REPO / "config" / "cells" / "sim.yaml"
SEED = 1
FIRST_AT_S = 3.0        # into the sweep: the arm is travelling or scanning a line


@pytest.mark.parametrize("first, second, after_s, seen_as", [
    # A lost connection lasts 1 s; the stream stalls 0.4 s into it (the stale limit is 30 ms).
    ("connection_loss", "ft_stall", 0.4, "stale"),
    # A protective stop is unlocked 5 s after it; the stream freezes 0.5 s into the wait.
    ("protective_stop", "ft_frozen", 0.5, "frozen"),
    # The connection drops 0.03 s after a protective stop, as the controller stops the arm.
    ("protective_stop", "connection_loss", 0.03, "connection"),
    # The robot stops itself (a collision, a joint limit) 0.4 s into a lost connection: the
    # recovery finds it once the link is back and must not unlock it unseen.
    ("connection_loss", "protective_stop", 0.4, "protective_stop"),
])
def test_a_fault_during_recovery_is_journaled_and_pauses(tmp_path: Path, first: str, second: str,
                                                             after_s: float, seen_as: str) -> None:
    code, injected, journaled, status = _run_sweep_faults(tmp_path, [(first, 0.0), (second, after_s)])
    assert injected[:2] == [first, second], injected
    # The first fault, then the second as a fault of its own, met while recovering; the
    # session paused on it (the first fault's recovery failed), not on the later e-stop.
    assert len(journaled) == 2, journaled
    assert journaled[1][0] == seen_as and journaled[1][1].startswith("during recovery from "), journaled
    assert journaled[1][2] == "pause", journaled
    assert code == EXIT_PAUSED and status["status"] == "paused"
    assert f"{seen_as} waiting to recover" in status["status_reason"], status["status_reason"]


def test_a_protective_stop_and_a_trip_both_met_while_the_connection_was_lost_are_journaled(tmp_path: Path) -> None:
    """The soak's quarter night, seed 2, step 88: an F/T spike 0.12 s into a lost connection,
    a protective stop 0.9 s into it. Journaling the stop must not hide the guard's trip."""
    code, injected, journaled, status = _run_sweep_faults(
        tmp_path, [("connection_loss", 0.0), ("force_spike", 0.12), ("protective_stop", 0.9)])
    assert injected[:3] == ["connection_loss", "force_spike", "protective_stop"], injected
    during = {kind for kind, message, action in journaled[1:]
              if message.startswith("during recovery from ") and action == "pause"}
    assert len(journaled) == 3 and during == {"protective_stop", "force"}, journaled
    assert code == EXIT_PAUSED and status["status"] == "paused"
    assert "protective_stop waiting to recover" in status["status_reason"], status["status_reason"]
    assert "force waiting to recover" in status["status_reason"], status["status_reason"]


def _run_sweep_faults(tmp_path: Path, kinds_at_s: list[tuple[str, float]]) -> tuple[int, list[str], list, dict]:
    """Run the tiny plan with these faults in its cloud sweep (s after ``FIRST_AT_S``) and an
    e-stop later; the exit code, the kinds injected, the journaled (kind, message, action)
    and the session's status."""
    faults = [{"kind": kind, "step": SWEEP_STEP_KEY, "delay_s": FIRST_AT_S + at_s} for kind, at_s in kinds_at_s]
    faults.append({"kind": "emergency_stop", "step": SWEEP_STEP_KEY, "delay_s": 40.0})
    cell = copy_cell(SIM_CELL, tmp_path, "recovery-" + "-".join(k for k, _ in kinds_at_s[1:]) + "-cell")
    items = "".join(f"    - {json.dumps(f)}\n" for f in faults)
    cell.write_text(cell.read_text().rstrip("\n") + "\n  faults:\n" + items)
    plan = plan_for(cell, tmp_path)
    out = tmp_path / "session"
    session = Session(load_session_inputs(plan), out, SEED)
    code = session.run()
    injected = [k for k, _ in session.cell.faults.injected]   # type: ignore[union-attr]
    j = Journal.open_readonly(out)
    try:
        journaled = [(f.kind, f.message, f.policy_action) for f in j.faults()]
        status = j.session()
    finally:
        j.close()
    return code, injected, journaled, status
