"""The "Done when" run: `elastoprobe run config/plans/loopback.yaml --cell config/cells/loopback.yaml`
with nothing else running — the cell starts the served world itself and the real drivers
connect to it. Real time (about a minute), so marked slow. The cell is copied onto its own
127.0.0.x so the test never collides with someone serving the shipped cell."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from elastoprobe.controller.cli import main
from test_loopback_rig import copy_loopback_configs


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(600)
def test_loopback_plan_runs_end_to_end_on_the_real_drivers(tmp_path: Path) -> None:
    plan, cell = copy_loopback_configs(tmp_path, "127.0.0.191")
    out = tmp_path / "session"
    code = main(["run", str(plan), "--cell", str(cell), "--seed", "1", "--out", str(out), "--quiet",
                 "--allow-stale-calibration"])
    assert code == 0
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    kinds = [e["event"] for e in events]
    assert "session_done" in kinds
    assert sum(k == "step_done" for k in kinds) >= 4
    assert (out / "report" / "index.html").exists()
