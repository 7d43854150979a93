"""Issue #6's last goal: the demo on the miscalibrated cell, after calibration, maps the object
as well as the calibrated cell does, judged by ``elastoprobe evaluate`` against the
simulator's ground truth (bench/calibrated_demo.py runs the sessions: seeds 1-3, two
miscalibration draws; about 25 min here).

Figures (revision 3ff8a64 + the bench docstring, seeds 1-5, draws 0 and 1,
``--oracle``): region_map_error per seed
  calibrated cell:            6.5e-5, 0, 0, 0, 0                   mean 1.3e-5 (sem 1.3e-5)
  after calibration, draw 0:  1.23e-4, 4.9e-5, 2.5e-5, 7.4e-5, 1.71e-4  mean 8.8e-5
  after calibration, draw 1:  4.7e-5, 9.4e-5, 2.4e-5, 4.7e-5, 1.41e-4   mean 7.1e-5
  exact calibration, draw 0:  1.47e-4, 4.9e-5, 4.9e-5, 4.9e-5, 0.127 (a third region on seed 5)
  uncalibrated: 8 of 10 runs pause asking for calibration; 1 pauses on a force-rate guard;
                the 2 that finish score 0.396 (one region) and 0.0069.
Every after-calibration run finds the two regions with worst IoU >= 0.9996, but its mean
error is ~6x the calibrated cell's (a few points out of ~40 000 versus almost none): the
10 % goal is not met, strictly nor within the noise floor (difference 6.7e-5, floor
4.1e-5 = 2 standard errors of the difference). Those two stay declared xfails.
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
                           "--parallel", "2"], capture_output=True, text=True, timeout=7000, cwd=ROOT)
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
@pytest.mark.xfail(strict=False, reason="seeds 1-5, two draws: mean 7.95e-5 after calibration vs 1.3e-5 "
                                        "calibrated (5.1x relative); see the module docstring")
def test_region_map_error_within_ten_percent_of_the_calibrated_cell_strict(comparison: dict) -> None:
    assert comparison["goal_met_strict"], json.dumps(comparison["comparisons"])


@pytest.mark.slow
@pytest.mark.timeout(7200)
@pytest.mark.xfail(strict=False, reason="the difference (6.7e-5) exceeds the noise floor (4.1e-5, 2 standard "
                                        "errors) on seeds 1-5; see the module docstring")
def test_region_map_error_within_ten_percent_or_the_noise_floor(comparison: dict) -> None:
    assert comparison["goal_met_floored"], json.dumps(comparison["comparisons"])
