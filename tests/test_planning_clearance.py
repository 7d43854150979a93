"""Targets whose contact search would hit the object with more than the probe's tip are
dropped when the targets are planned, and grazing angles a characterized target cannot be
approached at are left out of its plan, instead of motions refused one by one at run time
(the demo on seed 2 had 14 such refusals and 37 skipped steps)."""
from __future__ import annotations

import json
from pathlib import Path

from elastoprobe.controller.cli import main
from elastoprobe.controller.journal import Journal

from test_sim_helpers import composite_targets_plan

PLAN = composite_targets_plan(
    "clearance",
    characterize="{points_per_region: 1, angles_deg: [10, 90, 170], forces_n: [5.0]}",
    densify="{rounds: 0}",
    budget="{max_steps: 40, max_robot_hours: 0.5}",
    targets="""\
  # The box top 18 mm from its south edge: clear along the normal; at 170 deg the tool
  # leans out over the edge and the F/T sensor meets the top.
  - {point_mm: [-31.3, -62.4, 140.0], normal: [0.0, 0.0, 1.0]}
  # The pillow 13 mm from the box's south wall: on the way down the scanner, which rides
  # beside the probe, comes within ~3 mm of the wall (the demo refused it at run time).
  - {point_mm: [-5.7, -93.1, 80.0], normal: [0.0, 0.0, 1.0]}""",
    tail="""\
fault_policy:
  default: {action: retry, retries: 2}
  kinds:
    no_contact: {action: skip_target}
""")


def test_colliding_targets_and_angles_are_left_out_of_the_plan_not_refused(tmp_path: Path) -> None:
    plan = tmp_path / "plan.yaml"
    plan.write_text(PLAN)
    out = tmp_path / "session"
    assert main(["run", str(plan), "--seed", "1", "--out", str(out), "--quiet"]) == 0
    with Journal.open_readonly(out) as j:
        sampling = j.phase("sampling", 0)
        assert sampling is not None
        kept = sampling.arrays["target_points_mm"].tolist()
        faults = j.faults()
        done = {r.plan.target_index for r in j.steps(statuses=["done"])}
        characterized = sorted({r.plan.angle_deg for r in j.steps(phase="regions")})
    assert kept == [[-31.3, -62.4, 140.0]]
    assert sampling.outputs["dropped_unreachable"] == 1
    assert not [f for f in faults if f.kind == "motion_refused"], [f.message for f in faults]
    assert done == {0}
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    dropped = [e for e in events if e.get("event") == "targets_dropped"]
    assert dropped and dropped[0]["what"] == "sampling" and dropped[0]["contact_search_collides"] == 1
    assert characterized == [10.0, 90.0]
    blocked = [e for e in events if e.get("event") == "angles_blocked"]
    assert blocked and blocked[0]["targets"] == {"0": [170.0]}
