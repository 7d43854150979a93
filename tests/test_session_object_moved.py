"""An object that moves during a session: detected, re-registered, and remembered across a
resume (DESIGN §6, §7: resume continues from the journaled registration).

The simulated object is shifted 12 mm at a survey contact; a later emergency stop pauses
the session. The simulator's world is rebuilt on resume with the object back at the cell
file's placement (a simulator does not outlive its controller), so the resumed session
starts from the journaled registration, finds the object 12 mm from it, and registers it
again — where the simulator really has it. Every figure is judged against the simulator's
true placement.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_session_faults import _run, _setup
from test_session_util import outcome

from elastoprobe.controller.geometry import Pose
from elastoprobe.controller.journal import Journal
from elastoprobe.controller.session import EXIT_DONE, EXIT_PAUSED


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
