"""A plan with ``sampling.units: 0`` presses exactly the points it lists (no neural gas): the
shipped loopback plan on its cell's in-process twin (``--dry-run``), whose steps the loopback
comparison (issue 5) matches one to one."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from elastoprobe.controller.cli import main
from elastoprobe.controller.config import load_session_inputs
from elastoprobe.controller.journal import Journal

ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "config" / "plans" / "loopback.yaml"
CELL = ROOT / "config" / "cells" / "loopback.yaml"


def test_units_zero_plan_probes_only_its_listed_points(tmp_path: Path) -> None:
    out = tmp_path / "session"
    assert main(["run", str(PLAN), "--cell", str(CELL), "--seed", "3", "--dry-run", "--out", str(out),
                 "--quiet"]) == 0
    plan = load_session_inputs(PLAN, CELL).plan
    listed = np.array([t.point_mm for t in plan.targets])
    with Journal.open_readonly(out) as j:
        sampling = j.phase("sampling", 0)
        assert sampling is not None
        assert sampling.outputs["n_units"] == 0 and sampling.outputs["ng_qe"] is None
        np.testing.assert_allclose(sampling.arrays["target_points_mm"], listed, atol=1e-6)
        steps = j.steps(statuses=["done"])
        pressed = {tuple(np.round(r.plan.point_mm, 6)) for r in steps}
        angles = sorted({r.plan.angle_deg for r in steps})
    assert pressed == {tuple(np.round(p, 6)) for p in listed}
    # Survey at 90 deg, characterization at every angle the plan lists: none refused.
    assert angles == sorted(set(plan.phases.survey.angles_deg) | set(plan.phases.characterize.angles_deg))
    assert len(steps) == len(listed) * (len(plan.phases.survey.forces_n)
                                        + len(plan.phases.characterize.angles_deg) * len(plan.phases.characterize.forces_n))
