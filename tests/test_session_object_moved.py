"""An object that moves during a session: detected, re-registered, and remembered across a
resume (resume continues from the journaled registration).

The simulated object is shifted 12 mm at a survey contact; a later emergency stop pauses
the session. The simulator's world is rebuilt on resume with the object back at the cell
file's placement (a simulator does not outlive its controller), so the resumed session
starts from the journaled registration, finds the object 12 mm from it, and registers it
again — where the simulator really has it. Every figure is judged against the simulator's
true placement.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from test_session_faults import _run, _setup
from test_session_util import outcome

from elastoprobe.controller.core.config import load_session_inputs
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.journal import Journal
from elastoprobe.controller.session import EXIT_DONE, EXIT_PAUSED, Session


def _registrations(out: Path) -> list[dict]:
    j = Journal.open_readonly(out)
    try:
        return [e["record"] for e in j.events(kind="object_registered")]
    finally:
        j.close()


@pytest.mark.slow          # a whole tiny session and its resume (~1-2 min); detection itself is in the default run
def test_moved_object_is_registered_and_the_registration_survives_a_resume(tmp_path: Path) -> None:
    plan = _setup(tmp_path, "moved-cell", [{"kind": "object_moved", "step": 22},
                                           {"kind": "emergency_stop", "step": 26}])
    out = tmp_path / "session"
    code, session = _run(plan, out)
    assert code == EXIT_PAUSED                         # the emergency stop
    true_moved = session.cell.world.base_to_object     # type: ignore[union-attr]
    regs = _registrations(out)
    assert len(regs) == 1, regs
    assert np.linalg.norm(Pose.from_list(regs[0]["base_to_object"]).position_mm - true_moved.position_mm) < 1.0

    code, resumed = _run(plan, out, resume=True)
    assert code == EXIT_DONE
    regs = _registrations(out)
    # The resumed controller began from the journaled placement, met the object where the
    # rebuilt simulator has it (the cell file's placement), and registered it there.
    assert len(regs) == 2, regs
    assert np.allclose(regs[1]["previous"], regs[0]["base_to_object"])
    nominal = resumed.cell.world.base_to_object        # type: ignore[union-attr]
    assert np.linalg.norm(Pose.from_list(regs[1]["base_to_object"]).position_mm - nominal.position_mm) < 1.0
    got = outcome(out)
    assert got.integrity == ["ok"] and got.problems == []
    assert set(got.step_status.values()) <= {"done", "skipped"}


@pytest.mark.slow          # a whole generated-object session (~2 min alone)
@pytest.mark.timeout(1800)  # the default 300 s ran out in characterization with the 2 cores ~10x oversubscribed
def test_a_still_object_is_not_taken_for_moved(tmp_path: Path) -> None:
    """Generated object 1003 (a slab with two inclusions and a strip): its survey target 46, on
    the flat top, has a 90-degree probe pose 6e-6 rad short of a half turn; the pose's rotation
    vector was wrong there (geometry.matrix_to_rotvec), the reference scans were placed 30 mm
    off the object, and the session paused at step 64 with a false object_moved, again on
    every resume. It now runs to the end without one."""
    from elastoprobe.controller.cli import main as cli_main

    obj = tmp_path / "gen1003"
    assert cli_main(["sim", "object", "--seed", "1003", "--shape", "slab", "--pattern",
                     "two_inclusions_and_strip", "--pairs", "far", "--out", str(obj)]) == 0
    out = tmp_path / "session"
    session = Session(load_session_inputs(obj / "plan.yaml"), out, 1)
    assert session.run() == EXIT_DONE
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert not [e for e in events if e["event"] == "fault" and e["kind"] == "object_moved"]
    assert not [e for e in events if e["event"] in ("registration_rejected", "object_registered")]


def test_a_step_is_measured_again_with_the_placement_of_its_time() -> None:
    # The quarter night of bench/soak.py (seed 1) met it: the object moved twice during
    # characterization, and the first learning phase re-measured the first survey steps'
    # scans with the latest placement: they fell 10 mm beside their targets, no sample was
    # seen by two scans, and the session ended in an internal error (exit 1).
    from elastoprobe.controller.phases import placement_at

    original, first, second = (Pose.from_list([400.0 + dx, 0.0, 0.0, 0.0, 0.0, 0.0]) for dx in (0.0, -7.0, -0.5))
    registrations = [
        {"t_wall_utc": "2026-11-26T03:29:09.944+00:00",
         "record": {"previous": original.to_list(), "base_to_object": first.to_list()}},
        {"t_wall_utc": "2026-11-26T03:30:13.737+00:00",
         "record": {"previous": first.to_list(), "base_to_object": second.to_list()}}]
    current = second
    at = lambda utc: placement_at(registrations, utc, current).position_mm[0]   # noqa: E731
    assert at("2026-11-26T03:10:00.000001+00:00") == 400.0            # before any move: the original
    assert at("2026-11-26T03:29:09.944+00:00") == 393.0               # the moment it was registered
    assert at("2026-11-26T03:29:55.5+00:00") == 393.0
    assert at("2026-11-26T03:31:00+00:00") == 399.5
    assert placement_at([], "2026-11-26T03:31:00+00:00", current) is current
    assert placement_at(registrations, None, current) is current
