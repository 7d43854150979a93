"""Calibration file: round trip, corrections composed on the flange, age and presence checks,
and one routine end to end on the miscalibrated simulated cell."""
from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core.calfile import (Corrections, check_calibration, load_calibration, matrix_to_rpy_deg,
                                             pose_list, read_document, write_section)
from elastoprobe.controller.core.config import load_cell, rpy_deg_to_matrix
from elastoprobe.controller.core.errors import CalibrationError
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix

ROOT = Path(__file__).resolve().parent.parent
SIM = ROOT / "config" / "cells" / "sim.yaml"
MIS = ROOT / "config" / "cells" / "sim_miscalibrated.yaml"
T0 = dt.datetime(2026, 3, 1, 12, 0, tzinfo=dt.timezone.utc)


def write_all(path: Path, now: dt.datetime = T0) -> dict:
    f2t = Pose(np.array([0.5, -1.0, 161.2]), np.eye(3))
    f2s = Pose(np.array([151.0, 1.0, 40.0]), rotvec_to_matrix(np.radians([0.5, -51.0, 1.0])))
    sections = {
        "ft": {"payload_mass_kg": 0.7, "payload_com_sensor_mm": [10.0, 1.0, 42.0],
               "payload_com_tcp_mm": [10.0, 1.0, -118.0], "bias_force_n": [0.1, 0.2, 0.3],
               "bias_torque_nm": [0.0, 0.0, 0.01], "flange_to_sensor": pose_list(Pose.identity())},
        "tcp": {"tip_offset_mm": [0.5, -1.0, 1.2], "flange_to_tcp": pose_list(f2t), "fixed_point_base_mm": [0, 0, 0]},
        "scanner": {"flange_to_scanner": pose_list(f2s), "tcp_to_scanner": pose_list(f2s),
                    "flange_to_tcp_used": pose_list(Pose.identity())},
        "object": {"base_to_object": pose_list(Pose(np.array([402.0, 1.0, 0.0]), np.eye(3)))},
    }
    for kind, result in sections.items():
        write_section(path, "sim-cell", kind, result, {"rms": 0.01}, "ab" * 32, now=now)
    return {"f2t": f2t, "f2s": f2s}


def test_round_trip_and_versioned_format(tmp_path: Path) -> None:
    p = tmp_path / "cal.json"
    truth = write_all(p)
    doc = read_document(p)
    assert doc["format_version"] == 1 and doc["cell"] == "sim-cell"
    assert set(doc["sections"]) == {"ft", "tcp", "scanner", "object"}
    assert doc["sections"]["tcp"]["data_sha256"] == "ab" * 32
    corr = load_calibration(p)
    assert corr.flange_to_tcp.distance_to(truth["f2t"])[0] < 1e-9
    assert corr.flange_to_scanner.distance_to(truth["f2s"])[1] < 1e-9
    assert corr.payload_mass_kg == 0.7
    assert np.allclose(corr.base_to_object.position_mm, [402.0, 1.0, 0.0])
    assert corr.calibrated_utc["ft"] == T0
    # Rewriting one section keeps the others.
    write_section(p, "sim-cell", "ft", {**doc["sections"]["ft"]["result"], "payload_mass_kg": 0.71}, {}, "cd" * 32,
                  now=T0 + dt.timedelta(days=1))
    again = load_calibration(p)
    assert again.payload_mass_kg == 0.71 and again.flange_to_tcp.distance_to(truth["f2t"])[0] < 1e-9


def test_bad_files_refused(tmp_path: Path) -> None:
    p = tmp_path / "cal.json"
    p.write_text("{not json")
    with pytest.raises(CalibrationError, match="unreadable"):
        load_calibration(p)
    p.write_text(json.dumps({"format": "elastoprobe-calibration", "format_version": 99, "sections": {}}))
    with pytest.raises(CalibrationError, match="version 99"):
        load_calibration(p)
    with pytest.raises(CalibrationError, match="unreadable"):
        write_section(_corrupt(tmp_path), "sim-cell", "ft", {}, {}, "")
    write_all(tmp_path / "other.json")
    with pytest.raises(CalibrationError, match="belongs to cell"):
        write_section(tmp_path / "other.json", "another-cell", "ft", {}, {}, "")


def _corrupt(tmp_path: Path) -> Path:
    p = tmp_path / "corrupt.json"
    p.write_text("]")
    return p


def test_rpy_inverse() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        rpy = tuple(rng.uniform(-170, 170, 3) * np.array([1.0, 0.5, 1.0]))
        back = matrix_to_rpy_deg(rpy_deg_to_matrix(rpy))
        assert np.allclose(rpy_deg_to_matrix(back), rpy_deg_to_matrix(rpy), atol=1e-9)


def test_corrections_keep_the_scanner_fixed_on_the_flange(tmp_path: Path) -> None:
    p = tmp_path / "cal.json"
    truth = write_all(p)
    spec, _ = load_cell(SIM)
    out = load_calibration(p).apply_to(spec)
    f2t = out.tool.flange_to_tcp.pose()
    assert f2t.distance_to(truth["f2t"])[0] < 1e-9
    # The scanner and the tool shapes stay where they are on the flange.
    assert f2t.compose(out.tool.tcp_to_scanner.pose()).distance_to(truth["f2s"])[0] < 1e-6
    old = {s.name: spec.tool.flange_to_tcp.pose().compose(s.pose.pose()) for s in spec.tool.shapes}
    for s in out.tool.shapes:
        assert f2t.compose(s.pose.pose()).distance_to(old[s.name])[0] < 1e-6
    assert out.tool.payload_mass_kg == 0.7
    assert np.allclose(out.object.base_to_object.position_mm, [402.0, 1.0, 0.0])
    assert Corrections().apply_to(spec).tool.flange_to_tcp.pose().distance_to(spec.tool.flange_to_tcp.pose())[0] < 1e-9


def test_check_calibration_flags_missing_old_and_partial(tmp_path: Path) -> None:
    spec, _ = load_cell(MIS)
    cell_path = tmp_path / "cell.yaml"
    real = spec.model_copy(update={"kind": "ur", "name": "sim-cell", "calibration_file": "cal.json"})
    assert any("missing" in m for m in check_calibration(real, cell_path, now=T0))
    assert any("names no calibration_file" in m
               for m in check_calibration(real.model_copy(update={"calibration_file": None}), cell_path, now=T0))
    write_all(tmp_path / "cal.json")
    assert check_calibration(real, cell_path, now=T0 + dt.timedelta(days=10)) == []
    old = check_calibration(real, cell_path, now=T0 + dt.timedelta(days=31))
    assert len(old) == 3 and all("days old" in m for m in old)
    partial = tmp_path / "partial.json"
    write_section(partial, "sim-cell", "ft", {"payload_mass_kg": 1.0, "payload_com_sensor_mm": [0, 0, 0],
                                              "flange_to_sensor": [0, 0, 0, 0, 0, 0]}, {}, "", now=T0)
    probs = check_calibration(real.model_copy(update={"calibration_file": str(partial)}), cell_path, now=T0)
    assert any("no tcp calibration" in m for m in probs) and any("no scanner" in m for m in probs)


def test_run_calibration_tcp_on_the_miscalibrated_cell(tmp_path: Path) -> None:
    """End to end: the tip is found to 0.1 mm of the simulator's hidden truth, and written."""
    from elastoprobe.calibration.runner import run_calibration, calibration_cell

    out = tmp_path / "cal.json"
    summary = run_calibration("tcp", MIS, seed=5, out_path=out)
    assert summary["written"] == str(out)
    spec, _ = load_cell(MIS)
    cell, _ = calibration_cell(spec, MIS, 5, "tcp")
    true_tip = cell._true_geometry(cell.params)["tip_offset"]
    assert np.linalg.norm(true_tip) > 1.9                      # the cell really is off by 2 mm
    assert np.linalg.norm(np.array(summary["result"]["tip_offset_mm"]) - true_tip) < 0.1
    corr = load_calibration(out)
    assert np.allclose(corr.flange_to_tcp.position_mm, np.array([0.0, 0.0, 160.0]) + true_tip, atol=0.1)


def test_a_fault_mid_routine_parks_the_arm_and_writes_nothing(tmp_path: Path) -> None:
    """A force spike trips the guard during a touch-off: the routine ends in a CalibrationError
    naming the fault, the arm is lifted clear (as a session parks), nothing is written."""
    from elastoprobe.calibration.runner import calibration_cell, run_calibration, run_on_cell
    from elastoprobe.controller.core.errors import CalibrationError
    from elastoprobe.controller.toolhead import ProbeFault

    root = Path(__file__).resolve().parent.parent
    text = (root / "config" / "cells" / "sim.yaml").read_text()
    text = text.replace("file: ../objects/", f"file: {root / 'config' / 'objects'}/")
    cell_path = tmp_path / "cell.yaml"
    cell_path.write_text(text + "  faults:\n    - {kind: force_spike, step: 3}\n")
    out = tmp_path / "cal.json"
    with pytest.raises(CalibrationError, match="tcp: stopped by a force"):
        run_calibration("tcp", cell_path, seed=1, out_path=out)
    assert not out.exists()
    spec, _ = load_cell(cell_path)
    cell, mesh = calibration_cell(spec, cell_path, 1, "tcp")
    with pytest.raises(ProbeFault):
        run_on_cell("tcp", spec, cell, mesh, 1)
    top_z = float(cell.base_to_object.apply(mesh.vertices)[:, 2].max())
    assert cell.arm.status().tcp_pose.position_mm[2] >= top_z + 60.0 - 0.5      # lifted to travel height
