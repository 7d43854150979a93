"""The plan's region settings reach the session's clustering, and the evaluation counts and
places what a wrong map mislabels (real tiny runs on the simulated cell: by default one run
beside the shared tiny session, with -m slow two full runs of seed 1)."""
from __future__ import annotations

from pathlib import Path

import pytest
from ruamel.yaml import YAML

from elastoprobe.controller.evaluation import evaluate_session
from elastoprobe.controller.journal import Journal

from test_session_util import TINY_PLAN, child_env, plan_for, run_cli


# A plan that asks for 100x before calling two regions different (box and foam dent ~10x apart).
HIGH_CONTRAST = {"    angles_deg: [90]\n    forces_n: [4.0, 12.0]\n":
                 "    angles_deg: [90]\n    forces_n: [4.0, 12.0]\n    min_contrast: 100.0\n"}
# Densification cannot split one region into two: the merged run skips its round.
NO_DENSIFY = {"    rounds: 1\n": "    rounds: 0\n"}


def _regions(session: Path) -> tuple[int, int]:
    """(regions found, merged by contrast) of the survey's clustering."""
    with Journal.open_readonly(session) as j:
        rec = j.phase("regions", 0)
    assert rec is not None
    return rec.outputs["n_regions"], rec.outputs["stats"].get("merged_by_contrast", 0)


def test_plan_min_contrast_decides_whether_box_and_foam_are_two_regions(tiny_session: dict, tmp_path: Path) -> None:
    """Two regions at the default contrast (the shared tiny session, seed 2); one, merged by
    contrast, for the same plan asking for 100x (one run, without its densify round)."""
    plan = plan_for(tiny_session["cell"], tmp_path, edits={**HIGH_CONTRAST, **NO_DENSIFY})
    one = tmp_path / "session_100"
    child = run_cli(["run", str(plan), "--out", str(one), "--seed", str(tiny_session["seed"]), "--quiet"],
                    tiny_session["env"])
    assert child.returncode == 0, child.stderr[-2000:]
    two = tiny_session["finished"]
    assert _regions(two)[0] == 2
    assert _regions(one) == (1, 1)
    _assert_evaluation_places_the_mislabelled(one, two)


@pytest.mark.slow
def test_plan_min_contrast_two_full_runs_seed_1(tmp_path: Path) -> None:
    """The same on seed 1, both runs the whole tiny plan (densify round included)."""
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
        found[contrast] = _regions(out)
    assert found[None][0] == 2
    assert found[100.0] == (1, 1)
    _assert_evaluation_places_the_mislabelled(tmp_path / "session_100.0", tmp_path / "session_None")


def _assert_evaluation_places_the_mislabelled(one_dir: Path, two_dir: Path) -> None:
    """One region where there are two: every point of the smaller material is mislabelled,
    up to the farthest one from the seam; the evaluation counts and places them (on the
    scanned cloud) and weighs them (on the true surface: the box's whole top, 25 600 mm^2)."""
    one, two = evaluate_session(one_dir), evaluate_session(two_dir)
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
    # The ceiling is the cloud's, not the map's: both sessions scanned the same box on the
    # same pillow, and labelled with the truth their clouds carry both materials.
    for ev in (one, two):
        ceiling = ev["map_ceiling"]
        assert sorted(ceiling["per_region_iou"]) == ["cardboard", "foam"]
        assert ceiling["worst_region_iou"] > 0.9 and ceiling["region_map_error"] < 0.05
    assert one["map_ceiling"]["worst_region_iou"] > one["worst_region_iou"]
    _assert_region_figures_make_up_the_object_s(two)


def _assert_region_figures_make_up_the_object_s(ev: dict) -> None:
    """Per region, the full-span figures and what they are judged against (the region's own
    noise floor and deepest true dent) add up to the object's."""
    regions = ev["profile_full_by_region"]
    assert sorted(regions) == sorted(ev["served_bounds"])
    assert max(r["peak_depth_mm"] for r in regions.values()) == ev["peak_depth_mm"]
    assert all(r["noise_floor_mm"] > 0.0 for r in regions.values())
    for kind, whole in ev["profile_rmse_full_mm"].items():
        if whole is None:
            continue
        parts = [r["profile_rmse_full_mm"][kind] for r in regions.values() if r["profile_rmse_full_mm"][kind] is not None]
        assert min(parts) - 1e-6 <= whole <= max(parts) + 1e-6, (kind, whole, parts)
        worst = [r["profile_max_abs_error_mm"][kind] for r in regions.values()
                 if r["profile_max_abs_error_mm"][kind] is not None]
        assert max(worst) == ev["profile_max_abs_error_mm"][kind]
