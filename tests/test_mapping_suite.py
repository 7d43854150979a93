"""The mapping suite (bench/mapping_suite.py): generated objects through the real session, scored
on their true surface.

The default run is the bench's ``--quick``: two small suite objects (1004, a block with a strip
of a near material; 1005, a plain block), one seed, the plan rule's plans shortened the same
way for both. Its figures say nothing about the product's maps: this checks that every run
maps, that each figure is what the session's evaluation gives and lies where it can, that the
plan is the rule's (no per-object change), and that the aggregate is computed from the runs.
The baseline (densification off) is left out here: it doubles the run time, and its pairing
is checked on records below.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ruamel.yaml import YAML

from bench import mapping_suite as ms

QUICK_OBJECTS = {"1004-block-strip": 2, "1005-block-plain": 1}     # object -> materials


def _no_nan(text: str) -> Any:
    def refuse(name: str) -> None:
        raise AssertionError(f"{name} in the bench's JSON")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("mapping_suite_quick")
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert ms.main(["--quick", "--baseline", "none", "--out", str(out)]) == 0
    return _no_nan(buf.getvalue()), out


# The first test to ask for `quick` pays for it: two short sessions and their evaluations
# (~2 min of CPU, more wall time on a busy machine).
@pytest.mark.timeout(1200)
def test_quick_suite_maps_every_object_and_reports_truth_surface_figures(quick) -> None:
    result, out = quick
    assert result["bench"] == "mapping_suite" and result["quick"] is True
    assert result["seeds"] == [1]
    assert {o["object"] for o in result["objects"]} == set(QUICK_OBJECTS)
    runs = result["runs"]
    assert sorted(r["object"] for r in runs) == sorted(QUICK_OBJECTS)
    for r in runs:
        assert r["status"] == "done", (r["object"], r["status"], r["reason"])
        n_materials = QUICK_OBJECTS[r["object"]]
        assert r["regions_true"] == n_materials
        assert 1 <= r["regions_found"] <= 8
        assert 0.0 <= r["region_map_error"] <= 1.0
        assert 0.0 <= r["worst_region_iou"] <= 1.0
        assert len(r["per_region_iou"]) == n_materials
        assert math.isclose(min(r["per_region_iou"].values()), r["worst_region_iou"], abs_tol=1e-6)
        assert 0.0 < r["coverage"] <= 1.0
        # The ceiling: the same cloud, every point labelled with its true region.
        assert sorted(r["ceiling"]["per_region_iou"]) == sorted(r["per_region_iou"])
        assert 0.0 <= r["ceiling"]["region_map_error"] <= 1.0
        assert math.isclose(min(r["ceiling"]["per_region_iou"].values()), r["ceiling"]["worst_region_iou"],
                            abs_tol=1e-6)
        assert r["probes"] > 0 and r["robot_hours"] > 0
        assert len(r["densify"]) == 1 and r["densify"][0]["new_targets"] is not None   # the quick plan: 1 round
        if n_materials == 1:
            # One material: any map of one region is exact, and no boundary is drawn or due.
            assert r["regions_found"] != 1 or (r["region_map_error"] == 0.0 and r["boundary_mm_mean"] == 0.0)
        # The figures are the session's own evaluation (the JSON `elastoprobe evaluate` printed).
        session = Path(r["session"])
        assert session.parent.parent == out and (session / "journal.sqlite").exists()
        assert (session / "report" / "index.html").exists()


@pytest.mark.timeout(1200)
def test_quick_plan_is_the_rule_plan_shortened_the_same_way_for_every_object(quick) -> None:
    """No per-object tuning: the bench's plan differs from the rule's only where quick_plan
    changes every plan, and by the same rule."""
    _, out = quick
    yaml = YAML(typ="safe")
    for label in QUICK_OBJECTS:
        rule = yaml.load((out / label / "plan.yaml").read_text(encoding="utf-8"))
        short = yaml.load((out / label / "plan_quick.yaml").read_text(encoding="utf-8"))
        assert short == ms.quick_plan(yaml.load((out / label / "plan.yaml").read_text(encoding="utf-8")))
        assert short["sampling"]["units"] == max(8, rule["sampling"]["units"] // 3)
        for key in ("cloud", "probing", "limits", "fault_policy", "simulated_object"):
            assert short[key] == rule[key]
        assert short["phases"]["survey"] == rule["phases"]["survey"]


@pytest.mark.timeout(1200)
def test_quick_aggregate_is_computed_from_the_runs(quick) -> None:
    result, _ = quick
    runs, agg = result["runs"], result["aggregate"]
    errors = [r["region_map_error"] for r in runs]
    assert agg["runs"] == agg["mapped"] == len(runs) == 2
    assert agg["regions_true_runs"] == sum(r["regions_found"] == r["regions_true"] for r in runs)
    assert math.isclose(agg["median_region_map_error"], float(np.median(errors)), abs_tol=1e-6)
    assert math.isclose(agg["worst_region_map_error"], max(errors), abs_tol=1e-6)
    assert math.isclose(agg["lowest_worst_region_iou"], min(r["worst_region_iou"] for r in runs), abs_tol=1e-6)
    assert math.isclose(agg["lowest_coverage"], min(r["coverage"] for r in runs), abs_tol=1e-6)
    assert agg["probes_total"] == sum(r["probes"] for r in runs)
    assert set(result["goal_reached"]) == set(ms.GOALS) | {"all"}
    assert result["goal_reached"]["all"] == all(v for k, v in result["goal_reached"].items() if k != "all")
    assert result["baseline"] is None and result["vs_baseline"] is None
    assert result["wall_s"]["suite"] > 0 and result["cpu_s_children"] > 0


def _run(obj: str, seed: int, status: str = "done", error: float | None = 0.01, iou: float | None = 0.9,
         probes: int = 40, hours: float = 0.1, found: int = 2, true: int = 2) -> dict[str, Any]:
    mapped = status == "done"
    return {"object": obj, "seed": seed, "status": status, "reason": None if mapped else "paused: e-stop",
            "regions_found": found if mapped else None, "regions_true": true if mapped else None,
            "region_map_error": error if mapped else None, "worst_region_iou": iou if mapped else None,
            "boundary_mm_mean": 2.0 if mapped else None, "boundary_mm_p90": 4.0 if mapped else None,
            "coverage": 0.99 if mapped else None, "probes": probes, "robot_hours": hours, "wall_s": 10.0}


def test_an_unmapped_run_counts_against_the_suite_and_makes_the_worst_figures_null() -> None:
    runs = [_run("a", 1, error=0.01), _run("b", 1, error=0.03, iou=0.7, found=1),
            _run("c", 1, status="paused")]
    agg = ms.aggregate(runs)
    assert agg["mapped"] == 2 and agg["by_status"] == {"done": 2, "paused": 1}
    assert agg["regions_true_runs"] == 1 and math.isclose(agg["regions_true_fraction"], 1 / 3, abs_tol=1e-6)
    assert agg["median_region_map_error"] == 0.03          # the paused run counts as infinitely bad
    assert agg["worst_region_map_error"] is None and agg["worst_region_map_error_of_mapped"] == 0.03
    assert agg["lowest_worst_region_iou"] is None and agg["lowest_worst_region_iou_of_mapped"] == 0.7
    assert agg["boundary_mm_mean"] is None and agg["lowest_coverage"] is None
    assert agg["not_mapped"] == [{"object": "c", "seed": 1, "status": "paused", "reason": "paused: e-stop"}]
    reached = ms.goal_reached(agg)
    assert reached["worst_region_map_error"] is False and reached["all"] is False
    json.dumps(agg, allow_nan=False)


def test_baseline_pairs_show_what_the_densify_rounds_changed() -> None:
    full = [_run("a", 1, error=0.01, probes=48, hours=0.12), _run("b", 1, error=0.05, probes=40),
            _run("c", 1, status="failed"), _run("d", 2, error=0.02)]
    base = [_run("a", 1, error=0.04, probes=40, hours=0.10, found=1), _run("b", 1, error=0.05, probes=40),
            _run("c", 1, error=0.02)]
    p = ms.paired(full, base)
    assert p["compared"] == 2 and len(p["pairs"]) == 3        # d has no baseline; c did not map in full
    a = p["pairs"][0]
    assert a["error_change"] == -0.03 and a["probes_added"] == 8 and a["robot_hours_added"] == 0.02
    assert a["regions"] == [2, 1, 2]
    assert (p["densify_lowered_error"], p["densify_raised_error"], p["unchanged"]) == (1, 0, 1)
    assert p["regions_true_full"] == 2 and p["regions_true_baseline"] == 1
