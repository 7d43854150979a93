"""``elastoprobe calibrate {ft,tcp,scanner,object}``: build the cell, run one routine, write its section.

:func:`run_calibration` is what the CLI calls. The ``calibrate_*`` functions work on
any cell (they take a :class:`~.driver.Rig`, a toolhead on the cell) and return the
solver's fit and the section to store. :func:`calibration_cell` builds the cell for a
routine through the cell registry, whatever its kind (simulated, loopback over the real
protocols, a real ``ur`` arm): for ft, tcp and scanner the rigid reference sphere (an
acetal ball of certified radius) sits on the table where the object normally sits, for
object the cell's own object. A simulated cell's miscalibration is drawn from the seed
inside the simulator and never shown to the solvers: they see device data only.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from elastoprobe.controller.cellfactory import build_calibration_cell
from elastoprobe.controller.core.calfile import (calibration_path, load_calibration, pose_list, writable_document,
                                                 write_section)
from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.devices import Cell
from elastoprobe.controller.core.errors import CalibrationError, ElastoprobeError
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.toolhead import ProbeFault

from .driver import Rig, make_rig
from .ft_payload import PayloadFit, solve_payload
from .object_registration import ObjectFit, register_object
from .procedures import collect_ft, collect_sphere_scans, collect_touches, sweep_object
from .scanner_sphere import ScannerFit, solve_scanner_sphere
from .tcp_pivot import TipFit, solve_sphere_touches

KINDS = ("ft", "tcp", "scanner", "object")
SPHERE_RADIUS_MM = 25.0            # the reference sphere's certified radius
FT_HEIGHT_MM = 300.0               # TCP height for the F/T poses (free air above the table)


@dataclass(frozen=True)
class Section:
    """A routine's outcome: what goes into the calibration file, plus the raw fit object."""

    kind: str
    result: dict[str, Any]
    fit: dict[str, Any]
    data_sha256: str
    solved: object


def sphere_centre_nominal(cell_spec) -> np.ndarray:  # noqa: ANN001 — config.CellSpec
    """Where the reference sphere's centre roughly is: on the table at the object's placement."""
    b2o = cell_spec.object.base_to_object.pose()
    return b2o.apply(np.array([0.0, 0.0, SPHERE_RADIUS_MM]))


# ------------------------------------------------------------------------------ routines
def calibrate_ft(rig: Rig, cell_spec) -> Section:  # noqa: ANN001
    centre = np.array([*sphere_centre_nominal(cell_spec)[:2], FT_HEIGHT_MM])
    data = collect_ft(rig, centre)
    tcp_to_sensor = cell_spec.tool.tcp_to_sensor.pose()
    r_sensor = np.stack(data.r_base_tcp) @ tcp_to_sensor.rotation if data.r_base_tcp else np.zeros((0, 3, 3))
    fit: PayloadFit = solve_payload(r_sensor, np.asarray(data.force_n).reshape(-1, 3),
                                    np.asarray(data.torque_nm).reshape(-1, 3))
    f2t = cell_spec.tool.flange_to_tcp.pose()
    result = {"payload_mass_kg": fit.mass_kg, "payload_com_sensor_mm": fit.com_sensor_mm.tolist(),
              "payload_com_tcp_mm": fit.com_tcp_mm(tcp_to_sensor).tolist(),
              "bias_force_n": fit.bias_force_n.tolist(), "bias_torque_nm": fit.bias_torque_nm.tolist(),
              "flange_to_sensor": pose_list(f2t.compose(tcp_to_sensor))}
    return Section("ft", result, {"force": fit.force_report.to_dict(), "torque": fit.torque_report.to_dict(),
                                  "skipped": data.skipped, "robot_time_s": data.robot_time_s},
                   fit.data_sha256, fit)


def calibrate_tcp(rig: Rig, cell_spec, seed: int = 0) -> Section:  # noqa: ANN001
    rho = SPHERE_RADIUS_MM + cell_spec.tool.tip_radius_mm
    data = collect_touches(rig, sphere_centre_nominal(cell_spec), rho, seed=seed)
    if len(data.rotations) < 3:
        raise CalibrationError(f"tcp: only {len(data.rotations)} touches succeeded ({'; '.join(data.skipped[:3])})")
    fit: TipFit = solve_sphere_touches(np.stack(data.rotations), np.stack(data.positions_mm),
                                       np.stack(data.approach_dirs), rho)
    f2t = cell_spec.tool.flange_to_tcp.pose()
    result = {"tip_offset_mm": fit.tip_mm.tolist(),
              "flange_to_tcp": pose_list(Pose(f2t.apply(fit.tip_mm), f2t.rotation)),
              "fixed_point_base_mm": fit.fixed_point_base_mm.tolist()}
    return Section("tcp", result, {"touch": fit.report.to_dict(), "skipped": data.skipped,
                                   "robot_time_s": data.robot_time_s}, fit.data_sha256, fit)


def calibrate_scanner(rig: Rig, cell_spec, seed: int = 0) -> Section:  # noqa: ANN001
    data = collect_sphere_scans(rig, sphere_centre_nominal(cell_spec), SPHERE_RADIUS_MM,
                                cell_spec.tool.tip_radius_mm, seed=seed)
    nominal = cell_spec.tool.tcp_to_scanner.pose()
    fit: ScannerFit = solve_scanner_sphere(data.profiles, SPHERE_RADIUS_MM, nominal)
    f2t = cell_spec.tool.flange_to_tcp.pose()
    result = {"tcp_to_scanner": pose_list(fit.tcp_to_scanner), "flange_to_tcp_used": pose_list(f2t),
              "flange_to_scanner": pose_list(f2t.compose(fit.tcp_to_scanner)),
              "sphere_centre_base_mm": fit.sphere_centre_base_mm.tolist()}
    return Section("scanner", result, {"sphere": fit.report.to_dict(), "skipped": data.skipped,
                                       "robot_time_s": data.robot_time_s}, fit.data_sha256, fit)


def calibrate_object(rig: Rig, cell_spec, mesh, tcp_to_scanner: Pose,  # noqa: ANN001
                     spacing_mm: float = 3.0, height_above_mm: float = 40.0) -> Section:
    """Sweep the object with the scanner in both raster directions (mapped through
    ``tcp_to_scanner``, in the frame of the TCP the arm reports) and register ``mesh``
    (object frame) onto the cloud."""
    nominal = rig.cell.base_to_object
    mesh_base = mesh.copy()
    mesh_base.apply_transform(nominal.matrix())
    lo, hi = mesh_base.bounds
    data = sweep_object(rig, lo, hi, tcp_to_scanner, spacing_mm, height_above_mm)
    fit: ObjectFit = register_object(mesh, data.points_base_mm, nominal)
    result = {"base_to_object": pose_list(fit.base_to_object), "correction": pose_list(fit.correction)}
    return Section("object", result, {"icp": fit.report.to_dict(), "skipped": data.skipped,
                                      "robot_time_s": data.robot_time_s}, fit.data_sha256, fit)


# ------------------------------------------------------------------------------ set-up
def calibration_cell(cell_spec, cell_path: str | Path, seed: int, kind: str, cell_doc=None):  # noqa: ANN001, ANN201
    """(cell, what is on its table: mesh in the object frame) for a routine, from the cell
    registry: the reference sphere for ft/tcp/scanner, the cell's object for object. The
    caller closes the cell. ``cell_doc``: the cell's YAML (where an error in its object file is
    reported), read from ``cell_path`` if not given."""
    if cell_doc is None:
        _, cell_doc = load_cell(cell_path)
    built = build_calibration_cell(cell_spec, cell_doc, cell_path, seed,
                                   None if kind == "object" else SPHERE_RADIUS_MM)
    return built.cell, built.object_mesh


def scanner_mount_for_object(cell_spec, cal_file: Path | None) -> tuple[Pose, str]:  # noqa: ANN001
    """The scanner mount (in the cell file's TCP frame) to map the object sweep with, and where it came from."""
    nominal_f2t = cell_spec.tool.flange_to_tcp.pose()
    if cal_file is not None and cal_file.exists():
        corr = load_calibration(cal_file)
        if corr.flange_to_scanner is not None:
            return nominal_f2t.inverse().compose(corr.flange_to_scanner), str(cal_file)
    return cell_spec.tool.tcp_to_scanner.pose(), "cell file (nominal: run calibrate scanner first)"


def run_on_cell(kind: str, cell_spec, cell: Cell, mesh, seed: int,  # noqa: ANN001
                tcp_to_scanner: Pose | None = None) -> Section:
    """Run one routine on a built cell (``mesh``: the object's or the reference sphere's, object frame).

    A fault (ProbeFault: a trip, a protective stop, a lost link) stops the routine; the arm is
    then unloaded and lifted to travel height as a session parks after one (not if an
    operator, an emergency stop or a lost link has it), and the fault is raised."""
    rig = make_rig(cell_spec, cell, mesh, seed)
    try:
        return _run_routine(kind, rig, cell_spec, mesh, seed, tcp_to_scanner)
    except ProbeFault:
        rig.head.acknowledged_trip = cell.arm.trip()
        try:
            rig.head.safe_retract()
        except (ProbeFault, ElastoprobeError):
            pass                    # best effort: the fault raised below is what the operator must see
        raise


def _run_routine(kind: str, rig: Rig, cell_spec, mesh, seed: int,  # noqa: ANN001
                 tcp_to_scanner: Pose | None) -> Section:
    if kind == "ft":
        return calibrate_ft(rig, cell_spec)
    if kind == "tcp":
        return calibrate_tcp(rig, cell_spec, seed)
    if kind == "scanner":
        return calibrate_scanner(rig, cell_spec, seed)
    if kind == "object":
        return calibrate_object(rig, cell_spec, mesh, tcp_to_scanner or cell_spec.tool.tcp_to_scanner.pose())
    raise CalibrationError(f"unknown calibration {kind!r} (one of {', '.join(KINDS)})")


def run_calibration(kind: str, cell_path: Path, seed: int = 0, out_path: Path | None = None) -> dict:
    """Calibrate one part of a cell and write its section of the calibration file.

    Writes ``out_path`` if given, else the cell's ``calibration_file``; if neither, nothing
    is written (the summary says so). Returns a JSON-ready summary: kind, cell, seed,
    written path, result, fit (residuals, conditioning, skipped poses, robot time).
    Raises CalibrationError for a refused fit or a fault on the cell, InputError for a bad cell file.
    """
    if kind not in KINDS:
        raise CalibrationError(f"unknown calibration {kind!r} (one of {', '.join(KINDS)})")
    cell_path = Path(cell_path)
    cell_spec, cell_doc = load_cell(cell_path)
    target = Path(out_path) if out_path is not None else calibration_path(cell_spec, cell_path)
    if target is not None:
        writable_document(target, cell_spec.name)     # refused now, not after the poses
    mount, mount_source = (None, None)
    if kind == "object":
        mount, mount_source = scanner_mount_for_object(cell_spec, target)
    cell, mesh = calibration_cell(cell_spec, cell_path, seed, kind, cell_doc)
    try:
        section = run_on_cell(kind, cell_spec, cell, mesh, seed, mount)
    except ProbeFault as exc:    # the arm is stopped; closing the cell stops its devices
        raise CalibrationError(f"{kind}: stopped by a {exc.kind} fault: {exc.message}; nothing was written") from exc
    finally:
        cell.close()
    written = None
    if target is not None:
        written = str(write_section(target, cell_spec.name, kind, section.result, section.fit, section.data_sha256))
    summary = {"kind": kind, "cell": cell_spec.name, "seed": seed, "written": written,
               "result": section.result, "fit": section.fit}
    if written is None:
        summary["note"] = "the cell names no calibration_file and no output path was given: nothing written"
    if mount_source is not None:
        summary["scanner_mount_from"] = mount_source
    return summary
