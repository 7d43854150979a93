"""What the controller believes vs what the simulated world is.

A calibration file's corrections reach the controller's geometry (session inputs, the
cell's mounts and placement, the arm's TCP) and leave the simulated truth alone; the
miscalibration is the cell's, whatever the run seed; a missing or stale calibration is
said in the build warnings and the provenance. A "perfect" calibration file (written
from the simulator's truth) must make the believed and the true geometry agree.
"""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
from ruamel.yaml import YAML

from elastoprobe.controller.cellfactory import build_cell
from elastoprobe.controller.core.calfile import pose_list, utc_now, write_section
from elastoprobe.controller.core.config import load_cell, load_session_inputs
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.provenance import calibration_entry, sha256_file
from elastoprobe.sim.cell import SimCell, params_from_cell

ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "config" / "plans" / "demo.yaml"
SIM = ROOT / "config" / "cells" / "sim.yaml"
MIS = ROOT / "config" / "cells" / "sim_miscalibrated.yaml"
SEED = 1


def copy_cell(src: Path, dest_dir: Path, **miscalibration: object) -> Path:
    """The cell file in ``dest_dir`` (object path made absolute; its calibration file lives there)."""
    yaml = YAML()
    doc = yaml.load(src.read_text(encoding="utf-8"))
    doc["object"]["file"] = str((src.parent / doc["object"]["file"]).resolve())
    for key, value in miscalibration.items():
        doc["simulation"]["miscalibration"][key] = value
    dest = dest_dir / src.name
    with dest.open("w", encoding="utf-8") as f:
        yaml.dump(doc, f)
    return dest


def write_truth_as_calibration(cell: SimCell, path: Path, name: str, now: dt.datetime) -> dict[str, Pose]:
    """A calibration file holding the simulator's truth (a perfect calibration), against the flange."""
    p = cell.params
    t = cell.truth
    f2t_file = p.flange_to_tcp
    f2t = f2t_file.compose(Pose(t.tip_offset_mm, np.eye(3)))
    f2s = f2t_file.compose(t.tcp_to_scanner)
    f2sensor = f2t_file.compose(t.tcp_to_sensor)
    com_sensor = t.tcp_to_sensor.inverse().apply(t.payload_com_mm)
    sections = {
        "ft": {"payload_mass_kg": t.payload_mass_kg, "payload_com_sensor_mm": com_sensor.tolist(),
               "flange_to_sensor": pose_list(f2sensor)},
        "tcp": {"tip_offset_mm": t.tip_offset_mm.tolist(), "flange_to_tcp": pose_list(f2t)},
        "scanner": {"flange_to_scanner": pose_list(f2s)},
        "object": {"base_to_object": pose_list(t.base_to_object)},
    }
    for kind, result in sections.items():
        write_section(path, name, kind, result, {}, "00" * 32, now=now)
    return {"f2t": f2t, "f2s": f2s, "b2o": t.base_to_object}


def tip_and_scanner_in_base(cell: SimCell) -> tuple[np.ndarray, Pose]:
    """Where the TRUE tip centre and scanner are in the base frame, at the arm's current joints."""
    tcp = cell.arm.status().tcp_pose
    return tcp.apply(cell.world.tip_offset_tcp_mm), tcp.compose(cell.scanner._tcp_to_scanner)


def test_a_calibration_reaches_the_believed_geometry_and_leaves_the_truth(tmp_path: Path) -> None:
    cell_path = copy_cell(MIS, tmp_path)
    before = load_session_inputs(PLAN, cell_path)
    assert before.cell == before.cell_file                     # no calibration yet: the nominal drawing
    uncal = build_cell(before, SEED)
    assert any("missing" in w for w in uncal.warnings)
    assert np.linalg.norm(uncal.cell.truth.tip_offset_mm) > 1.9       # the cell really is off

    truth = write_truth_as_calibration(uncal.cell, tmp_path / "sim_miscalibrated.calibration.json",
                                       before.cell.name, utc_now())
    after = load_session_inputs(PLAN, cell_path)
    # The session's cell (validator kinematics, collision shapes) is the calibrated one ...
    assert after.cell.tool.flange_to_tcp.pose().distance_to(truth["f2t"])[0] < 1e-6
    assert after.cell_file == before.cell_file
    cal = build_cell(after, SEED)
    assert cal.warnings == []
    c = cal.cell
    # ... and so is what the cell hands the controller to map readings with.
    assert c.base_to_object.distance_to(truth["b2o"])[0] < 1e-6
    f2t_believed = after.cell.tool.flange_to_tcp.pose()
    assert f2t_believed.compose(c.tcp_to_scanner).distance_to(truth["f2s"])[0] < 1e-6
    assert c.arm.status().tcp_pose.distance_to(uncal.cell.arm.status().tcp_pose)[0] > 1.9   # the arm's TCP moved
    # A perfect calibration: believed == true in the frame of the TCP the arm reports.
    assert np.linalg.norm(c.world.tip_offset_tcp_mm) < 1e-6
    d_mm, d_deg = c.scanner._tcp_to_scanner.distance_to(c.tcp_to_scanner)
    assert d_mm < 1e-6 and d_deg < 1e-6
    assert c.world.base_to_object.distance_to(c.base_to_object)[0] < 1e-6
    # The truth is the same physical cell: same tool, same placement, same tip and scanner in the base.
    t0, t1 = uncal.cell.true_geometry(), c.true_geometry()
    assert np.allclose(t0["tip_offset"], t1["tip_offset"]) and t0["mass"] == t1["mass"]
    assert t0["tcp_to_scanner"].distance_to(t1["tcp_to_scanner"])[0] < 1e-12
    assert uncal.cell.world.base_to_object.distance_to(c.world.base_to_object)[0] < 1e-12
    tip0, scan0 = tip_and_scanner_in_base(uncal.cell)
    tip1, scan1 = tip_and_scanner_in_base(c)
    assert np.linalg.norm(tip0 - tip1) < 1e-6 and scan0.distance_to(scan1)[0] < 1e-6
    # The session hashes the file it used, and which sections were applied.
    entry = calibration_entry(cell_path, tmp_path / "sim_miscalibrated.calibration.json")
    assert entry["sha256"] == sha256_file(tmp_path / "sim_miscalibrated.calibration.json")
    assert entry["applied_sections"] == ["ft", "tcp", "scanner", "object"] and entry["problems"] == []


def test_a_stale_calibration_is_applied_and_said(tmp_path: Path) -> None:
    cell_path = copy_cell(MIS, tmp_path)
    inputs = load_session_inputs(PLAN, cell_path)
    uncal = build_cell(inputs, SEED)
    old = utc_now() - dt.timedelta(days=45)            # the cell allows 30
    truth = write_truth_as_calibration(uncal.cell, tmp_path / "sim_miscalibrated.calibration.json",
                                       inputs.cell.name, old)
    stale = load_session_inputs(PLAN, cell_path)
    assert stale.cell.tool.flange_to_tcp.pose().distance_to(truth["f2t"])[0] < 1e-6
    warnings = build_cell(stale, SEED).warnings
    assert len(warnings) == 3 and all("days old" in w for w in warnings)
    entry = calibration_entry(cell_path, tmp_path / "sim_miscalibrated.calibration.json")
    assert entry["applied_sections"] == ["ft", "tcp", "scanner", "object"] and len(entry["problems"]) == 3


def test_the_miscalibration_is_the_cells_not_the_runs(tmp_path: Path) -> None:
    spec, _ = load_cell(MIS)
    obj = ROOT / "config" / "objects" / "rubber_ball.yaml"
    a = SimCell(params_from_cell(spec, obj, seed=1)).true_geometry()
    b = SimCell(params_from_cell(spec, obj, seed=7)).true_geometry()
    assert np.array_equal(a["tip_offset"], b["tip_offset"]) and a["mass"] == b["mass"]
    assert a["tcp_to_scanner"].distance_to(b["tcp_to_scanner"])[0] == 0.0
    assert a["base_to_object"].distance_to(b["base_to_object"])[0] == 0.0
    other = load_cell(copy_cell(MIS, tmp_path, seed=3))[0]
    c = SimCell(params_from_cell(other, obj, seed=1)).true_geometry()
    assert np.linalg.norm(a["tip_offset"] - c["tip_offset"]) > 0.1
    # Every term has the magnitude the cell file gives (directions drawn from the cell's seed).
    nominal_b2o = spec.object.base_to_object.pose()
    assert a["base_to_object"].distance_to(nominal_b2o)[0] == pytest.approx(4.0)
    assert a["base_to_object"].position_mm[2] == nominal_b2o.position_mm[2]      # still on the table
    assert np.linalg.norm(a["tip_offset"]) == pytest.approx(2.0)


def test_the_calibrated_sim_cell_is_untouched() -> None:
    inputs = load_session_inputs(PLAN, SIM)
    assert inputs.cell == inputs.cell_file
    built = build_cell(inputs, SEED)
    c = built.cell
    assert built.warnings == []
    assert not c.world.tip_offset_tcp_mm.any()
    assert c.scanner._tcp_to_scanner is c.tcp_to_scanner or \
        np.array_equal(c.scanner._tcp_to_scanner.matrix(), c.tcp_to_scanner.matrix())
    assert np.array_equal(c.world.base_to_object.matrix(), inputs.cell.object.base_to_object.pose().matrix())
    assert calibration_entry(SIM, None) is None
