"""All four routines on the miscalibrated simulated cell, judged against the simulator's hidden truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.calibration.runner import calibration_cell, run_on_cell
from elastoprobe.controller.core.config import load_cell

MIS = Path(__file__).resolve().parent.parent / "config" / "cells" / "sim_miscalibrated.yaml"


@pytest.mark.slow
def test_all_routines_recover_the_hidden_miscalibration() -> None:
    seed = 7
    spec, _ = load_cell(MIS)
    cell, mesh = calibration_cell(spec, MIS, seed, "ft")
    truth = cell._true_geometry(cell.params)
    ft = run_on_cell("ft", spec, cell, mesh, seed).solved
    assert abs(ft.mass_kg - truth["mass"]) / truth["mass"] < 0.02
    assert abs(spec.tool.payload_mass_kg - truth["mass"]) / truth["mass"] > 0.09      # it was off
    assert np.linalg.norm(ft.com_tcp_mm(spec.tool.tcp_to_sensor.pose()) - truth["com"]) < 2.0
    cell, mesh = calibration_cell(spec, MIS, seed, "tcp")
    tip = run_on_cell("tcp", spec, cell, mesh, seed).solved
    assert np.linalg.norm(tip.tip_mm - truth["tip_offset"]) < 0.5
    cell, mesh = calibration_cell(spec, MIS, seed, "scanner")
    sc = run_on_cell("scanner", spec, cell, mesh, seed).solved
    d_mm, d_deg = sc.tcp_to_scanner.distance_to(truth["tcp_to_scanner"])
    assert d_mm < 1.0 and d_deg < 0.5
    cell, mesh = calibration_cell(spec, MIS, seed, "object")
    cell.world.move_object(np.array([3.0, -2.5, 0.0]))
    true_place = cell.world.base_to_object
    obj = run_on_cell("object", spec, cell, mesh, seed, tcp_to_scanner=sc.tcp_to_scanner).solved
    v = np.asarray(mesh.vertices)
    assert np.max(np.linalg.norm(obj.base_to_object.apply(v) - true_place.apply(v), axis=1)) < 1.0
