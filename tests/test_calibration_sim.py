"""All four routines on the miscalibrated simulated cell, judged against the simulator's hidden truth;
a touch-off's two speeds."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.calibration.driver import (SLOW_TOUCH_SPEED_MM_S, TOUCH_SLOW_ZONE_MM, TOUCH_SPEED_MM_S, make_rig,
                                            touch)
from elastoprobe.calibration.runner import SPHERE_RADIUS_MM, calibration_cell, run_on_cell, sphere_centre_nominal
from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.geometry import Pose

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


SIM = Path(__file__).resolve().parent.parent / "config" / "cells" / "sim.yaml"


@pytest.mark.parametrize("standoff_mm", [8.0, 1.5])
def test_a_touch_meets_the_rigid_sphere_at_the_slow_speed_unless_it_is_nearer_than_expected(standoff_mm: float) -> None:
    """The stop after a contact lands late on a loaded machine and a rigid sphere's force climbs
    to the limit within 0.03 mm: the touch crosses free air fast and the expected surface
    slowly. A surface within the slow zone is met at the free-air speed."""
    spec, _ = load_cell(SIM)
    cell, mesh = calibration_cell(spec, SIM, 0, "tcp")
    rig = make_rig(spec, cell, mesh, 0)
    speeds: list[float] = []
    seek = cell.arm.seek_contact

    def recorded(direction, speed_mm_s, contact_force_n, max_distance_mm):  # noqa: ANN001, ANN202
        speeds.append(speed_mm_s)
        return seek(direction, speed_mm_s, contact_force_n, max_distance_mm)

    cell.arm.seek_contact = recorded
    centre = sphere_centre_nominal(spec)
    rho = SPHERE_RADIUS_MM + spec.tool.tip_radius_mm
    down = np.array([0.0, 0.0, -1.0])
    rig.head.travel_to(Pose(centre - down * (rho + standoff_mm), np.diag([1.0, -1.0, -1.0])))
    hit = touch(rig.head, down, standoff_mm + 8.0, expected_mm=8.0)
    assert hit is not None and abs(np.linalg.norm(hit.position_mm - centre) - rho) < 0.1
    assert speeds[0] == TOUCH_SPEED_MM_S
    if standoff_mm > TOUCH_SLOW_ZONE_MM:
        assert speeds == [TOUCH_SPEED_MM_S, SLOW_TOUCH_SPEED_MM_S]
    else:
        assert speeds == [TOUCH_SPEED_MM_S]       # met in the free-air leg, no slow leg after it
    peak_n = float(np.abs(rig.head.recorder.wrench().force_n).max())
    assert peak_n < spec.limits.max_force_n / 2
