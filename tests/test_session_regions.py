"""The plan's region settings reach the session's clustering, and the evaluation counts and
places what a wrong map mislabels (real tiny runs on the simulated cell)."""
from __future__ import annotations

from pathlib import Path

import pytest
from ruamel.yaml import YAML

from elastoprobe.controller.evaluation import evaluate_session
from elastoprobe.controller.journal import Journal

from test_session_util import TINY_PLAN, child_env, run_cli


def test_plan_min_contrast_decides_whether_box_and_foam_are_two_regions(tmp_path: Path) -> None:
    """Box and foam dent ~10x apart: two regions at the default contrast; a plan that asks
    for 100x before calling two regions different gets one, merged by contrast."""
    yaml = YAML()
    doc = yaml.load(TINY_PLAN.read_text(encoding="utf-8"))
    for key in ("cell", "simulated_object"):
        doc[key] = str((TINY_PLAN.parent / doc[key]).resolve())
    env = child_env(tmp_path / "locks")
    found = {}
    for contrast in (None, 100.0):
        if contrast is not None:
            doc["phases"]["survey"]["min_contrast"] = contrast
        plan = tmp_path / f"tiny_{contrast}.yaml"
        with plan.open("w", encoding="utf-8") as f:
            yaml.dump(doc, f)
        out = tmp_path / f"session_{contrast}"
        child = run_cli(["run", str(plan), "--out", str(out), "--seed", "1", "--quiet"], env)
        assert child.returncode == 0, child.stderr[-2000:]
        with Journal.open_readonly(out) as j:
            rec = j.phase("regions", 0)
        assert rec is not None
        found[contrast] = (rec.outputs["n_regions"], rec.outputs["stats"].get("merged_by_contrast", 0))
    assert found[None][0] == 2
    assert found[100.0] == (1, 1)

    # One region where there are two: every point of the smaller material is mislabelled,
    # up to the farthest one from the seam; the evaluation counts and places them (on the
    # scanned cloud) and weighs them (on the true surface: the box's whole top, 25 600 mm^2).
    one, two = evaluate_session(tmp_path / "session_100.0"), evaluate_session(tmp_path / "session_None")
    c1, c2 = one["cloud"], two["cloud"]
    assert one["regions_found"] == 1 and c1["mislabelled_points"] > 1000
    assert c1["mislabelled_points"] == round(c1["region_map_error"] * c1["scored_points"])
    assert c1["mislabelled_max_from_true_boundary_mm"] > 50.0
    assert c2["mislabelled_points"] == round(c2["region_map_error"] * c2["scored_points"])
    assert c2["mislabelled_points"] < c1["mislabelled_points"]
    truth_area = one["truth_surface"]["area_mm2"]
    assert one["region_map_error"] * truth_area == pytest.approx(160.0 * 160.0, rel=0.01)
    # The missed material shows in the IoU; not in the boundary distances, which measure the
    # boundaries drawn across the scored top, where box and pillow never meet.
    assert one["worst_region_iou"] == 0.0 and one["per_region_iou"]["cardboard"] == 0.0
    assert two["region_map_error"] < one["region_map_error"] and 0.0 < two["coverage"] <= 1.0
