"""A budget spent in the middle of the plan ends the session with what was measured: the
regions and models of the data at hand, the final map and its report (docs/design.md §2, §4)."""
from __future__ import annotations

from pathlib import Path

from elastoprobe.controller.cli import main
from elastoprobe.controller.journal import Journal

from test_sim_helpers import composite_targets_plan


def _plan(max_steps: int) -> str:
    return composite_targets_plan(
        "budget",
        characterize="{points_per_region: 1, angles_deg: [50, 90, 130], forces_n: [5.0]}",
        densify="{rounds: 1}",
        budget=f"{{max_steps: {max_steps}, max_robot_hours: 2.0}}",
        targets="""\
  - {point_mm: [-20.0, -20.0, 140.0], normal: [0.0, 0.0, 1.0]}   # the box top
  - {point_mm: [20.0, 30.0, 140.0], normal: [0.0, 0.0, 1.0]}     # the box top
  - {point_mm: [150.0, 0.0, 80.0], normal: [0.0, 0.0, 1.0]}      # the pillow
  - {point_mm: [-150.0, 40.0, 80.0], normal: [0.0, 0.0, 1.0]}    # the pillow""")


def test_a_budget_spent_while_characterizing_still_ends_with_models_and_a_map(tmp_path: Path) -> None:
    """Four survey steps, then the budget runs out two steps into characterization: the
    session logs why, clusters what it has (regions round 0 again, from the journal),
    fits that round's models and writes the final map and report."""
    plan = tmp_path / "plan.yaml"
    plan.write_text(_plan(6))
    out = tmp_path / "session"
    assert main(["run", str(plan), "--seed", "1", "--out", str(out), "--quiet"]) == 0
    with Journal.open_readonly(out) as j:
        spent = j.events("budget_spent")
        done = j.status_counts().get("done", 0)
        regions, models, final = j.phase("regions", 0), j.phase("models", 0), j.phase("final", 0)
        assert j.phase("regions", 1) is None and j.phase("densify", 1) is None
    assert len(spent) == 1 and "step budget of 6" in spent[0]["record"]["reason"]
    assert done == 6
    assert regions is not None and models is not None and final is not None
    assert int(regions.outputs["n_regions"]) == 2
    assert (out / "report" / "index.html").is_file()
