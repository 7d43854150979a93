"""Calibration through the same door as a session: the cell registry builds the cell by kind,
the routines drive it through the public toolhead, on the loopback cell over the real
protocols (ur_rtde against the UR emulator, Net F/T UDP, the serial scanner).

Default run: a real cell without a current calibration is refused by ``run``; a ``ur`` cell's
calibration set-up goes to the same real-driver builder as loopback's; one touch-off on the
served reference sphere over the real protocols. Slow: ``elastoprobe calibrate ft|tcp|scanner|object``
on a copy of the shipped loopback cell, each section checked against the served world, and
then the loopback plan runs on the calibrated cell without ``--allow-stale-calibration``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from elastoprobe.calibration.driver import back_off, make_rig, touch
from elastoprobe.calibration.runner import SPHERE_RADIUS_MM, calibration_cell, sphere_centre_nominal
from elastoprobe.controller import cellfactory
from elastoprobe.controller.cli import main
from elastoprobe.controller.core.calfile import check_calibration, load_calibration
from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.drivers import real_cell
from elastoprobe.controller.drivers.real_cell import RealCell
from test_loopback_rig import copy_loopback_configs

HOST = "127.0.0.193"


def test_run_refuses_a_loopback_cell_that_is_not_calibrated(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    plan, cell = copy_loopback_configs(tmp_path, HOST)
    code = main(["run", str(plan), "--cell", str(cell), "--seed", "1", "--out", str(tmp_path / "s"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "calibration is not current" in err and "loopback.calibration.json is missing" in err
    assert not (tmp_path / "s").exists()                 # nothing started, nothing written


def test_a_ur_cell_is_calibrated_on_the_same_real_drivers_as_loopback(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The registry hands a ``ur`` cell's calibration set-up to the same builder as a loopback
    cell's (no robot here: the builder is recorded, not run)."""
    _, cell_path = copy_loopback_configs(tmp_path, HOST)
    text = cell_path.read_text().replace("kind: loopback", "kind: ur")
    cell_path.write_text(text)
    spec, doc = load_cell(cell_path)
    calls: list[dict[str, Any]] = []

    def recorded(cell: Any, limits: Any, **kwargs: Any) -> str:
        calls.append({"cell": cell, "limits": limits, **kwargs})
        return "the real cell"

    monkeypatch.setattr(real_cell, "build_real_cell", recorded)
    built = cellfactory.build_calibration_cell(spec, doc, cell_path, 0, SPHERE_RADIUS_MM)
    assert built.cell == "the real cell" and calls[0]["cell"] is spec and "addresses" not in calls[0]
    lo, hi = built.object_mesh.bounds
    assert np.allclose(hi - lo, 2 * SPHERE_RADIUS_MM, atol=0.5) and abs(lo[2]) < 1e-6   # the sphere, on the table
    built = cellfactory.build_calibration_cell(spec, doc, cell_path, 0, None)
    assert np.isclose(built.object_mesh.bounds[1][2], 130.0, atol=0.5)                  # the ball, from its file


@pytest.mark.loopback
@pytest.mark.timeout(300)
def test_a_touch_off_on_the_served_reference_sphere_over_the_real_protocols(tmp_path: Path) -> None:
    _, cell_path = copy_loopback_configs(tmp_path, HOST)
    spec, _ = load_cell(cell_path)
    cell, mesh = calibration_cell(spec, cell_path, 0, "tcp")
    try:
        assert isinstance(cell, RealCell)
        rig = make_rig(spec, cell, mesh, 0)
        centre = sphere_centre_nominal(spec)
        rho = SPHERE_RADIUS_MM + spec.tool.tip_radius_mm
        down = np.array([0.0, 0.0, -1.0])
        rig.head.travel_to(Pose(centre - down * (rho + 8.0), np.diag([1.0, -1.0, -1.0])))
        hit = touch(rig.head, down, 16.0, expected_mm=8.0)
        assert hit is not None
        # The tip centre rests on the sphere grown by the tip radius (the cell is not miscalibrated).
        assert abs(np.linalg.norm(hit.position_mm - centre) - rho) < 0.1
        back_off(rig.head, down, 8.0)
        assert rig.head.pose().position_mm[2] > hit.position_mm[2] + 7.9
    finally:
        cell.close()


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(1800)
def test_calibrate_every_section_on_loopback_then_the_plan_runs_without_override(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    plan, cell_path = copy_loopback_configs(tmp_path, HOST)
    spec, _ = load_cell(cell_path)
    cal = tmp_path / "loopback.calibration.json"
    summaries = {}
    for kind in ("ft", "tcp", "scanner", "object"):
        capsys.readouterr()
        assert main(["calibrate", kind, "--cell", str(cell_path), "--json"]) == 0, capsys.readouterr().err
        summaries[kind] = json.loads(capsys.readouterr().out)
        assert summaries[kind]["written"] == str(cal)
    # The served world is the cell file exactly (no miscalibration): each routine finds it.
    tool = spec.tool
    ft = summaries["ft"]["result"]
    assert abs(ft["payload_mass_kg"] - tool.payload_mass_kg) / tool.payload_mass_kg < 0.02
    assert np.linalg.norm(np.array(ft["payload_com_tcp_mm"]) - tool.payload_com_mm) < 2.0
    assert np.linalg.norm(summaries["tcp"]["result"]["tip_offset_mm"]) < 0.5
    corr = load_calibration(cal)
    d_mm, d_deg = corr.flange_to_scanner.distance_to(tool.flange_to_tcp.pose().compose(tool.tcp_to_scanner.pose()))
    assert d_mm < 1.0 and d_deg < 0.5
    assert summaries["object"]["scanner_mount_from"] == str(cal)
    # A ball's turn about its centre is not observable: its centre is what registration finds.
    centre = np.array([0.0, 0.0, 65.0])
    assert np.linalg.norm(corr.base_to_object.apply(centre) - spec.object.base_to_object.pose().apply(centre)) < 1.0
    assert check_calibration(spec, cell_path) == []
    out = tmp_path / "session"
    assert main(["run", str(plan), "--cell", str(cell_path), "--seed", "1", "--out", str(out), "--quiet"]) == 0
    events = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert "session_done" in [e["event"] for e in events]
    assert sum(e["event"] == "step_done" for e in events) >= 4
