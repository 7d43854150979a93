"""Issue #6's last goal: the demo on the miscalibrated cell, after calibration, maps the object
as well as the calibrated cell does (region-map error within 10 %), judged by
``elastoprobe evaluate`` against the simulator's ground truth (bench/calibrated_demo.py)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_demo_after_calibration_matches_the_calibrated_cell(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "calibrated_demo.py"), "--out", str(tmp_path),
                           "--parallel", "2"], capture_output=True, text=True, timeout=7000, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    ev = out["evaluations"]
    # Every run mapped the object and the calibration wrote all four sections.
    for name in ("calibrated", "uncalibrated", "after_calibration"):
        assert ev[name]["region_map_error"] is not None, name
    assert all(out["calibration"][k]["written"] for k in ("ft", "tcp", "scanner", "object"))
    rel = out["after_vs_calibrated"]["rel_diff"]
    assert rel is not None and rel <= 0.10, json.dumps(ev)
