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
from elastoprobe.controller.toolhead import Toolhead

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
def test_a_retried_kind_met_during_recovery_is_journaled_and_recovered_once(
        tmp_path: Path, first: str, second: str, after_s: float, seen_as: str) -> None:
    """docs/design.md, fault policy: a fault during recovery whose kind's policy is retry
    gets ONE nested recovery (journaled as its own fault, action retry); the sweep goes on."""
    code, injected, journaled, status = _run_sweep_faults(tmp_path, [(first, 0.0), (second, after_s)])
    assert injected[:2] == [first, second], injected
    assert journaled[1][0] == seen_as and journaled[1][1].startswith("during recovery from "), journaled
    assert journaled[1][2] == "retry", journaled
    # The session went on to the later e-stop, and paused on that alone.
    assert [k for k, _, _ in journaled[2:]] == ["emergency_stop"], journaled
    assert code == EXIT_PAUSED and status["status_reason"].startswith("emergency_stop"), status["status_reason"]


@pytest.mark.parametrize("first, second, after_s, seen_as", [
    # Lost 1.5 s into a protective stop's 5 s unlock and back 1 s later, before the unlock ends:
    # the link is up at every status read; only its generation count shows the loss (the
    # full night of seed 1, step 647: never journaled, the session went on).
    ("protective_stop", "connection_loss", 1.5, "connection"),
    # The UR's own protective stop along with a force trip, met while retracting from it.
    ("force_spike", "protective_stop", 0.2, "protective_stop"),
])
def test_a_fault_hidden_inside_a_recovery_is_named(tmp_path: Path, first: str, second: str, after_s: float,
                                                    seen_as: str) -> None:
    code, injected, journaled, status = _run_sweep_faults(tmp_path, [(first, 0.0), (second, after_s)])
    assert injected[:2] == [first, second], injected
    assert len(journaled) == 3, journaled
    assert journaled[1][0] == seen_as and journaled[1][1].startswith(f"during recovery from {journaled[0][0]}: "), \
        journaled
    assert journaled[1][2] == "retry" and journaled[2][0] == "emergency_stop", journaled


def test_a_second_fault_during_a_nested_recovery_pauses(tmp_path: Path) -> None:
    """The soak's quarter night, seed 2, step 88: an F/T spike 0.12 s into a lost connection,
    a protective stop 0.9 s into it. The stop is the nested recovery's fault; the guard's
    trip, met inside that nested recovery, is a second one: journaled, and the session pauses
    naming it (never two nested recoveries)."""
    code, injected, journaled, status = _run_sweep_faults(
        tmp_path, [("connection_loss", 0.0), ("force_spike", 0.12), ("protective_stop", 0.9)])
    assert injected[:3] == ["connection_loss", "force_spike", "protective_stop"], injected
    assert [(k, a) for k, _, a in journaled] == [("connection", "retry"), ("protective_stop", "retry"),
                                                  ("force", "pause")], journaled
    assert all(m.startswith("during recovery from connection: ") for _, m, _ in journaled[1:]), journaled
    assert code == EXIT_PAUSED and status["status"] == "paused"
    assert status["status_reason"].startswith("connection"), status["status_reason"]
    assert "force waiting to recover" in status["status_reason"], status["status_reason"]


def test_a_fault_during_recovery_whose_policy_is_pause_pauses(tmp_path: Path) -> None:
    code, injected, journaled, status = _run_sweep_faults(
        tmp_path, [("connection_loss", 0.0), ("protective_stop", 0.4)],
        edits={"    no_contact: {action: skip_target}":
               "    no_contact: {action: skip_target}\n    protective_stop: {action: pause}"})
    assert [(k, a) for k, _, a in journaled] == [("connection", "retry"), ("protective_stop", "pause")], journaled
    assert code == EXIT_PAUSED and "protective_stop waiting to recover" in status["status_reason"]


def test_an_emergency_stop_during_recovery_is_named_and_pauses(tmp_path: Path) -> None:
    """Pressed while a protective stop is being unlocked: the e-stop is the operator's, never
    a nested recovery, and is journaled as met during that recovery."""
    code, injected, journaled, status = _run_sweep_faults(
        tmp_path, [("protective_stop", 0.0), ("emergency_stop", 0.5)], later_estop=False)
    assert injected[:2] == ["protective_stop", "emergency_stop"], injected
    assert [(k, a) for k, _, a in journaled] == [("protective_stop", "retry"), ("emergency_stop", "pause")], journaled
    assert journaled[1][1].startswith("during recovery from protective_stop: "), journaled
    assert code == EXIT_PAUSED and status["status_reason"].startswith("protective_stop"), status["status_reason"]
    # The operator (and the soak's driver) reads which stop to release from the reason.
    assert "emergency_stop waiting to recover" in status["status_reason"], status["status_reason"]


def test_the_retract_waits_for_a_fresh_stream(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A frozen F/T stream is still frozen when its own recovery would retract: a retract then
    meets the same fault again (the night's "move_linear ended tripped" pauses). Recovery
    waits (bounded, robot time) for fresh samples first: the retract starts after the freeze."""
    retract_at_s: list[float] = []
    original = Toolhead.safe_retract

    def timed_retract(self: Toolhead, *args: object) -> None:
        retract_at_s.append(self.cell.clock.now_s())
        original(self, *args)

    monkeypatch.setattr(Toolhead, "safe_retract", timed_retract)
    freeze_s = 0.4
    code, injected, journaled, status, fired = _run_sweep_faults(tmp_path, [("ft_frozen", 0.0)], duration_s=freeze_s,
                                                                 with_times=True)
    assert [(k, a) for k, _, a in journaled] == [("frozen", "retry"), ("emergency_stop", "pause")], journaled
    frozen_from_s = next(t for k, t in fired if k == "ft_frozen")
    assert retract_at_s and retract_at_s[0] >= frozen_from_s + freeze_s, (retract_at_s, frozen_from_s)


def _run_sweep_faults(tmp_path: Path, kinds_at_s: list[tuple[str, float]], later_estop: bool = True,
                      edits: dict[str, str] | None = None,
                      duration_s: float | None = None, with_times: bool = False) -> tuple:
    """Run the tiny plan (with ``edits``) with these faults in its cloud sweep (s after
    ``FIRST_AT_S``; the first lasting ``duration_s`` if given) and an e-stop later; the exit
    code, the kinds injected, the journaled (kind, message, action) and the session's status."""
    faults = [{"kind": kind, "step": SWEEP_STEP_KEY, "delay_s": FIRST_AT_S + at_s} for kind, at_s in kinds_at_s]
    if duration_s is not None:
        faults[0]["duration_s"] = duration_s
    if later_estop:
        faults.append({"kind": "emergency_stop", "step": SWEEP_STEP_KEY, "delay_s": 40.0})
    cell = copy_cell(SIM_CELL, tmp_path, "recovery-" + "-".join(k for k, _ in kinds_at_s[1:]) + "-cell")
    items = "".join(f"    - {json.dumps(f)}\n" for f in faults)
    cell.write_text(cell.read_text().rstrip("\n") + "\n  faults:\n" + items)
    plan = plan_for(cell, tmp_path, edits=edits)
    out = tmp_path / "session"
    session = Session(load_session_inputs(plan), out, SEED)
    code = session.run()
    fired = list(session.cell.faults.injected)   # type: ignore[union-attr]
    injected = [k for k, _ in fired]
    j = Journal.open_readonly(out)
    try:
        journaled = [(f.kind, f.message, f.policy_action) for f in j.faults()]
        status = j.session()
    finally:
        j.close()
    return (code, injected, journaled, status, fired) if with_times else (code, injected, journaled, status)
