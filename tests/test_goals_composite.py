"""Issue 3's composite-object goals on a full simulated session of the shipped demo plan
(slow: a few minutes of wall time), judged against the simulator's ground truth on the
object's true top (issue 16: at most 0.1 % mislabelled)."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


@pytest.mark.parametrize("seed", [1, 2])
def test_demo_plan_maps_the_box_and_the_pillow(tmp_path: Path, seed: int) -> None:
    from elastoprobe.controller.cli import main
    from elastoprobe.controller.evaluation import evaluate_session

    out = tmp_path / "session"
    assert main(["run", str(ROOT / "config" / "plans" / "demo.yaml"), "--out", str(out), "--seed", str(seed)]) == 0
    ev = evaluate_session(out)
    assert ev["regions_found"] == 2 == ev["regions_true"]
    # On the true top (the box's top and the pillow around it, within the plan's 50 degrees):
    # issue 16's goal for the composite, at most 0.1 % of the area mislabelled.
    assert ev["region_map_error"] <= 0.001
    assert ev["worst_region_iou"] >= 0.99
    # The two materials meet only at the foot of the box's wall, which is not on the top:
    # a map that draws no boundary across a face scores 0 here (None: it drew one).
    assert ev["boundary_mm_mean"] is not None and ev["boundary_mm_mean"] <= 3.0
    assert ev["boundary_mm_p90"] <= 3.0
    # What is mislabelled is a tie at the fold, closer to the seam than half the sweep spacing.
    assert ev["mislabelled_max_from_true_boundary_mm"] <= 2.0
    assert 0.0 < ev["coverage"] <= 1.0
    # The same map on the scanned cloud (the figures before the truth surface).
    assert ev["cloud"]["region_map_error"] <= 0.03 and ev["cloud"]["worst_region_iou"] >= 0.9
    assert_whole_profile_goals(ev)


def assert_whole_profile_goals(ev: dict) -> None:
    """Issue 14: what predict serves is right over the whole profile, tip and shadow included."""
    peak, floor = ev["peak_depth_mm"], ev["noise_floor_mm"]
    assert ev["profile_rmse_full_mm"]["held_out_angles"] <= max(2.0 * floor, 0.05 * peak), ev["profile_rmse_full_mm"]
    assert ev["profile_max_abs_error_mm"]["held_out_angles"] <= 0.25 * peak, ev["profile_max_abs_error_mm"]
    assert ev["profile_full_scored_fraction"]["held_out_angles"] >= 0.8
    for region, bounds in ev["served_bounds"].items():
        assert bounds["queries"] == 10_000 and bounds["violations"] == 0, (region, bounds)
