"""A budget spent in the middle of the plan ends the session with what was measured: the
regions and models of the data at hand, the final map and its report (docs/design.md §2, §4)."""
from __future__ import annotations

from pathlib import Path

from elastoprobe.controller.cli import main
from elastoprobe.controller.journal import Journal

ROOT = Path(__file__).resolve().parent.parent

PLAN = f"""
name: budget
cell: {ROOT / 'config' / 'cells' / 'sim.yaml'}
simulated_object: {ROOT / 'config' / 'objects' / 'composite.yaml'}
seed: 1
cloud: {{source: scan, sweep_spacing_mm: 6.0, sweep_height_mm: 40.0, max_points: 20000}}
sampling:
  units: 0
  edge_clearance_mm: 15.0
  max_tilt_deg: 50.0
  reference_direction: [0.0, 1.0, 0.0]
probing: {{scans_per_step: 5, settle_s: 0.5, standoff_mm: 15.0, force_rate_n_s: 20.0, force_tolerance_n: 0.5}}
phases:
  survey: {{angles_deg: [90], forces_n: [4.0, 12.0]}}
  characterize: {{points_per_region: 1, angles_deg: [50, 90, 130], forces_n: [5.0]}}
  densify: {{rounds: 1}}
budget: {{max_steps: {{max_steps}}, max_robot_hours: 2.0}}
targets:
  - {{point_mm: [-20.0, -20.0, 140.0], normal: [0.0, 0.0, 1.0]}}   # the box top
  - {{point_mm: [20.0, 30.0, 140.0], normal: [0.0, 0.0, 1.0]}}     # the box top
  - {{point_mm: [150.0, 0.0, 80.0], normal: [0.0, 0.0, 1.0]}}      # the pillow
  - {{point_mm: [-150.0, 40.0, 80.0], normal: [0.0, 0.0, 1.0]}}    # the pillow
model: {{hidden_units: 45, ensemble: 2, max_epochs: 100, profile_span_mm: 80.0, profile_samples: 64}}
"""


def test_a_budget_spent_while_characterizing_still_ends_with_models_and_a_map(tmp_path: Path) -> None:
    """Four survey steps, then the budget runs out two steps into characterization: the
    session logs why, clusters what it has (regions round 0 again, from the journal),
    fits that round's models and writes the final map and report."""
    plan = tmp_path / "plan.yaml"
    plan.write_text(PLAN.replace("{max_steps}", "6"))
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
