"""A plan with ``sampling.units: 0`` presses exactly the points it lists (no neural gas): the
shipped loopback plan on its cell's in-process twin (``--dry-run``), whose steps the loopback
comparison (issue 5) matches one to one.

By default one dry run checks both: the shipped plan with its scan direction turned half over
(the run of the half-turn regression below) presses only its listed point, at every angle.
The shipped plan as it is: -m slow (tests/test_loopback_run.py runs it on the real drivers)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.cli import main
from elastoprobe.controller.core.config import load_session_inputs
from elastoprobe.controller.journal import Journal

ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "config" / "plans" / "loopback.yaml"
CELL = ROOT / "config" / "cells" / "loopback.yaml"


def _dry_run(plan: Path, out: Path) -> Path:
    assert main(["run", str(plan), "--cell", str(CELL), "--seed", "3" if plan == PLAN else "1", "--dry-run",
                 "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def half_turn(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(plan, finished session): the shipped plan with the scan direction along +y (seed 1).

    The ball's top with the scan direction along +y: from the 45 deg approach to 135 deg the
    tool turns half over about its axis, and the geodesic straight move (and the one by the
    park pose) wanted the last wrist joint past +360 deg; every 135 deg step was refused as
    'no joint path'. The travel now turns the tool at travel height first."""
    tmp = tmp_path_factory.mktemp("half_turn")
    text = PLAN.read_text().replace("reference_direction: [0.0, -1.0, 0.0]", "reference_direction: [0.0, 1.0, 0.0]")
    assert "[0.0, 1.0, 0.0]" in text
    text = text.replace("cell: ../cells/", f"cell: {ROOT / 'config' / 'cells'}/")
    text = text.replace("simulated_object: ../objects/", f"simulated_object: {ROOT / 'config' / 'objects'}/")
    plan_path = tmp / "plan.yaml"
    plan_path.write_text(text)
    return plan_path, _dry_run(plan_path, tmp / "session")


def _assert_only_listed_points_at_every_angle(plan_path: Path, out: Path) -> None:
    plan = load_session_inputs(plan_path, CELL).plan
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


def test_units_zero_plan_probes_only_its_listed_points(half_turn: tuple[Path, Path]) -> None:
    _assert_only_listed_points_at_every_angle(*half_turn)


@pytest.mark.slow
def test_the_shipped_loopback_plan_probes_only_its_listed_points(tmp_path: Path) -> None:
    _assert_only_listed_points_at_every_angle(PLAN, _dry_run(PLAN, tmp_path / "session"))


def test_a_half_turn_of_the_tool_between_approaches_is_travelled_not_refused(half_turn: tuple[Path, Path]) -> None:
    _, out = half_turn
    with Journal.open_readonly(out) as j:
        refused = [f for f in j.faults() if f.kind == "motion_refused"]
        angles = sorted(r.plan.angle_deg for r in j.steps(statuses=["done"]))
    assert not refused, [(f.step_id, f.message) for f in refused]
    assert angles == [45.0, 45.0, 90.0, 90.0, 90.0, 90.0, 135.0, 135.0]
