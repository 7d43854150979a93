"""Issue #6's last goal: the demo on the miscalibrated cell, after calibration, maps the object
as well as the calibrated cell does, judged by ``elastoprobe evaluate`` against the
simulator's ground truth (bench/calibrated_demo.py runs the sessions: seeds 1-3, two
miscalibration draws, and an exact calibration of draw 0; about 25 min here).

The tests read the bench's top-level figures, which are now those of the object's true top
(``elastoprobe evaluate``, issue 16); the figures below were measured on the scanned cloud,
before that change (the bench reports them as ``cloud_*``).

Figures (revision 682725a, seeds 1-5, draws 0 and 1, ``--oracle``): region_map_error per seed
  calibrated cell:            6.5e-5, 0, 0, 0, 0                        mean 1.3e-5
  after calibration, draw 0:  1.23e-4, 4.9e-5, 2.5e-5, 7.4e-5, 1.71e-4  mean 8.84e-5
  after calibration, draw 1:  4.7e-5, 9.4e-5, 2.4e-5, 4.7e-5, 1.41e-4   mean 7.06e-5
  exact calibration, draw 0:  1.47e-4, 4.9e-5, 4.9e-5, 4.9e-5, 1.47e-4  mean 8.82e-5
  uncalibrated: 8 of 10 runs pause asking for calibration; the 2 that finish score 0.396
                (one region) and 0.0069.
Every after-calibration run finds the two regions with worst IoU >= 0.9996. Its errors are
1-7 points of ~40 000, each within 1.4 mm of the seam at the foot of the box wall (draw 0:
0.3 mm; the calibrated cell: 0.35 mm), closer than the sweep lines are apart (4 mm): ties
at the seam, not a misplaced boundary. After calibration scores what an exact calibration
of the same physical cell scores (8.84e-5 vs 8.82e-5: 0.2 %); both sit 5-6x above the calibrated
cell's mean because that is another physical cell: its scanner mount sees fewer points
right at the wall's foot (the probe shadows ~30 % of its laser line), so it has fewer
ties to lose. Against the calibrated cell the 10 % goal is not met, strictly nor within
the noise floor (difference 6.65e-5, floor 4.1e-5): those two stay declared xfails.
(Revision 3cb23fe scored 0.095 and 0.152 on draw 0 seeds 2 and 3: the box top split into
a third region, centre and rim; fixed by regions.MIN_CONTRAST = 2.5.)
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
SEEDS = (1, 2, 3)
DRAWS = (0, 1)


@pytest.fixture(scope="module")
def comparison(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("calibrated_demo")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "calibrated_demo.py"), "--out", str(out),
                           "--seeds", ",".join(map(str, SEEDS)), "--cell-seeds", ",".join(map(str, DRAWS)),
                           "--parallel", "2", "--oracle"], capture_output=True, text=True, timeout=7000, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_calibration_is_what_lets_the_miscalibrated_cell_map_the_object(comparison: dict) -> None:
    per_seed = comparison["per_seed"]
    for draw in DRAWS:
        assert all(comparison["calibration"][f"draw{draw}"][k]["written"] for k in ("ft", "tcp", "scanner", "object"))
        for seed in SEEDS:
            after = per_seed[f"after_calibration_draw{draw}"][str(seed)]
            assert after["region_map_error"] is not None, json.dumps(after)
            # Without calibration the controller either paused (its placement check asks for
            # calibration, or a guard tripped) or mapped worse than after calibration.
            uncal = per_seed[f"uncalibrated_draw{draw}"][str(seed)]
            if uncal["region_map_error"] is None:
                assert uncal["status"] == "paused", json.dumps(uncal)
            else:
                assert uncal["region_map_error"] > after["region_map_error"], json.dumps([uncal, after])


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_after_calibration_every_run_finds_the_two_materials(comparison: dict) -> None:
    for draw in DRAWS:
        for seed in SEEDS:
            h = comparison["per_seed"][f"after_calibration_draw{draw}"][str(seed)]
            assert h["regions_found"] == h["regions_true"] == 2, json.dumps(h)
            assert h["worst_region_iou"] >= 0.999, json.dumps(h)


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_after_calibration_maps_as_an_exact_calibration_of_the_same_cell_does(comparison: dict) -> None:
    """What calibration can change: draw 0 after calibration against draw 0 with the simulator's
    own truth as its calibration file, within 10 % or the noise floor; every mislabelled
    point within half the sweep spacing (2 mm) of the true seam: a tie, not a misplaced
    boundary."""
    assert comparison["comparisons"]["after_calibration_draw0_vs_perfect_calibration"]["floored_met"], \
        json.dumps(comparison["comparisons"])
    for draw in DRAWS:
        for seed in SEEDS:
            h = comparison["per_seed"][f"after_calibration_draw{draw}"][str(seed)]
            assert h["mislabelled_max_from_true_boundary_mm"] <= 2.0, json.dumps(h)


@pytest.mark.slow
@pytest.mark.timeout(7200)
@pytest.mark.xfail(strict=False, reason="seeds 1-5, two draws: mean 7.95e-5 after calibration vs 1.3e-5 on the "
                                        "calibrated cell (5.1x), 8.82e-5 exact calibration of the same "
                                        "cell; see the module docstring")
def test_region_map_error_within_ten_percent_of_the_calibrated_cell_strict(comparison: dict) -> None:
    assert comparison["goal_met_strict"], json.dumps(comparison["comparisons"])


@pytest.mark.slow
@pytest.mark.timeout(7200)
@pytest.mark.xfail(strict=False, reason="the difference (6.65e-5) exceeds the noise floor (4.1e-5, 2 standard "
                                        "errors) on seeds 1-5; see the module docstring")
def test_region_map_error_within_ten_percent_or_the_noise_floor(comparison: dict) -> None:
    assert comparison["goal_met_floored"], json.dumps(comparison["comparisons"])


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_restated_goal_after_calibration_within_the_margin_of_exact_and_of_the_calibrated_cell(
        comparison: dict) -> None:
    """Issue 16's restatement, on the truth surface: after calibration within max(10 %, the noise
    floor) of an exact calibration of the same cell, and within the same margin of the
    calibrated cell."""
    assert comparison["goal_restated_met"], json.dumps([comparison["goal_restated_parts"],
                                                        comparison["comparisons"]])


def _bench():
    from bench import calibrated_demo

    return calibrated_demo


def test_restated_goal_is_both_floored_verdicts_and_needs_the_exact_calibration() -> None:
    bench = _bench()
    ref = {"region_map_error": {"mean": 1.0e-4, "sem": 1.0e-5}}
    near = {"region_map_error": {"mean": 1.08e-4, "sem": 1.0e-5}}         # within 10 %
    noisy = {"region_map_error": {"mean": 1.2e-4, "sem": 1.0e-5}}         # 20 %, inside 2 x sqrt(2) sem
    far = {"region_map_error": {"mean": 2.0e-4, "sem": 1.0e-5}}           # outside both
    for vs_exact, vs_cal, met in ((near, noisy, True), (near, far, False), (far, near, False)):
        comparisons = {"after_calibration_draw0_vs_perfect_calibration": bench.compare(ref, vs_exact),
                       "after_calibration_draw0_vs_calibrated": bench.compare(ref, vs_cal)}
        got = bench.restated_goal(comparisons, "after_calibration_draw0_vs_calibrated", 0)
        assert got["goal_restated_met"] is met, got
    assert bench.restated_goal({}, "x", None)["goal_restated_met"] is None
