"""The cell's calibration file: versioned JSON, one section per routine, written atomically.

Layout (``format_version`` 1; poses are ``[x, y, z, rx, ry, rz]``: mm and a rotation
vector in rad, parent <- child)::

    {"format": "elastoprobe-calibration", "format_version": 1, "cell": "<cell name>",
     "written_utc": "2026-01-02T03:04:05+00:00",
     "sections": {
       "ft":      {"calibrated_utc", "data_sha256", "fit": {...}, "result":
                   {"payload_mass_kg", "payload_com_sensor_mm", "payload_com_tcp_mm",
                    "bias_force_n", "bias_torque_nm", "flange_to_sensor"}},
       "tcp":     {..., "result": {"tip_offset_mm", "flange_to_tcp", "fixed_point_base_mm"}},
       "scanner": {..., "result": {"flange_to_scanner", "tcp_to_scanner", "flange_to_tcp_used"}},
       "object":  {..., "result": {"base_to_object"}}}}

``fit`` holds the solver's residuals and conditioning. Mounts are stored against the
flange, which calibration never moves, so a tip calibrated after the scanner (or
before) composes correctly: :class:`Corrections` re-expresses them in the calibrated
TCP frame. Each routine rewrites only its own section (read, replace, atomic write).
"""
from __future__ import annotations

import datetime as dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_json
from .errors import CalibrationError, CalibrationFileError
from .geometry import Pose
from .inputfiles import read_input_bytes, read_input_text

FORMAT = "elastoprobe-calibration"
FORMAT_VERSION = 1
KINDS = ("ft", "tcp", "scanner", "object")
REQUIRED_FOR_RUN = ("ft", "tcp", "scanner")


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def pose_list(pose: Pose) -> list[float]:
    return [float(v) for v in pose.to_list()]


def matrix_to_rpy_deg(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of ``config.rpy_deg_to_matrix`` (R = Rz @ Ry @ Rx): (roll, pitch, yaw) in degrees."""
    r = np.asarray(rotation, dtype=float)
    pitch = -np.arcsin(np.clip(r[2, 0], -1.0, 1.0))
    if abs(np.cos(pitch)) > 1e-9:
        roll = np.arctan2(r[2, 1], r[2, 2])
        yaw = np.arctan2(r[1, 0], r[0, 0])
    else:   # gimbal lock: put the whole turn in yaw
        roll = 0.0
        yaw = np.arctan2(-r[0, 1], r[1, 1])
    return tuple(float(v) for v in np.degrees([roll, pitch, yaw]))   # type: ignore[return-value]


def empty_document(cell_name: str) -> dict[str, Any]:
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "cell": cell_name, "written_utc": None,
            "sections": {}}


def read_document(path: str | Path) -> dict[str, Any]:
    """The parsed file, checked for format and version; CalibrationError otherwise."""
    p = Path(path)
    try:
        doc = json.loads(read_input_text(p))
    except FileNotFoundError:
        raise CalibrationFileError(f"{p}: calibration file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationFileError(f"{p}: unreadable calibration file: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CalibrationFileError(f"{p}: not an Elastoprobe calibration file (format {doc.get('format')!r})"
                               if isinstance(doc, dict) else f"{p}: not an Elastoprobe calibration file")
    if doc.get("format_version") != FORMAT_VERSION:
        raise CalibrationFileError(f"{p}: calibration format version {doc.get('format_version')!r} is not supported "
                               f"(this version reads {FORMAT_VERSION})")
    if not isinstance(doc.get("sections"), dict):
        raise CalibrationFileError(f"{p}: calibration file has no sections")
    for kind, sec in doc["sections"].items():
        if kind not in KINDS:
            raise CalibrationFileError(f"{p}: unknown calibration section {kind!r}")
        if not isinstance(sec, dict) or "result" not in sec or "calibrated_utc" not in sec:
            raise CalibrationFileError(f"{p}: section {kind!r} lacks result or calibrated_utc")
        _parse_time(sec["calibrated_utc"], p, kind)
    return doc


def _parse_time(value: Any, path: Path, kind: str) -> dt.datetime:
    try:
        t = dt.datetime.fromisoformat(str(value))
    except ValueError:
        raise CalibrationFileError(f"{path}: section {kind!r} has a bad calibrated_utc {value!r}") from None
    return t if t.tzinfo else t.replace(tzinfo=dt.timezone.utc)


def writable_document(path: str | Path, cell_name: str) -> dict[str, Any]:
    """The document a new section of ``cell_name`` goes into: the file's, or an empty one when
    there is none. Refused (CalibrationFileError) when the file is unreadable, damaged or
    another cell's, or its folder cannot be written: what a calibration checks before the
    arm moves, so that an hour of poses is never measured for a file it cannot write."""
    p = Path(path)
    if p.exists():
        doc = read_document(p)
        if doc.get("cell") != cell_name:
            raise CalibrationFileError(f"{p}: the calibration file belongs to cell {doc.get('cell')!r}, not {cell_name!r}")
        return doc
    folder = p.parent if str(p.parent) else Path(".")
    if folder.exists() and not os.access(folder, os.W_OK | os.X_OK):
        raise CalibrationFileError(f"{p}: cannot write into {folder} (permission denied)")
    return empty_document(cell_name)


def write_section(path: str | Path, cell_name: str, kind: str, result: dict[str, Any], fit: dict[str, Any],
                  data_sha256: str, now: dt.datetime | None = None) -> Path:
    """Replace one section of the cell's calibration file (created if missing), atomically.

    An existing file that is unreadable or belongs to another cell is never overwritten:
    that is refused with the reason (move it away first).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown calibration kind {kind!r}")
    p = Path(path)
    doc = writable_document(p, cell_name)
    stamp = (now or utc_now()).astimezone(dt.timezone.utc).isoformat(timespec="seconds")
    doc["sections"][kind] = {"calibrated_utc": stamp, "data_sha256": data_sha256, "fit": fit, "result": result}
    doc["written_utc"] = stamp
    p.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_json(p, doc)


@dataclass(frozen=True)
class Corrections:
    """What a calibration file corrects; None where that routine has not been run.

    Mounts are against the flange. ``apply_to`` gives the cell spec with them in place.
    """

    flange_to_tcp: Pose | None = None
    flange_to_scanner: Pose | None = None
    flange_to_sensor: Pose | None = None
    payload_mass_kg: float | None = None
    payload_com_sensor_mm: np.ndarray | None = None
    base_to_object: Pose | None = None
    calibrated_utc: dict[str, dt.datetime] = field(default_factory=dict)

    def tool_frames(self, flange_to_tcp: Pose, tcp_to_scanner: Pose, tcp_to_sensor: Pose) -> dict[str, Any]:
        """Calibrated tool frames given the nominal ones (all in the CALIBRATED TCP frame):
        flange_to_tcp, tcp_to_scanner, tcp_to_sensor, payload_com_tcp_mm (or None), payload_mass_kg (or None)."""
        f2t = self.flange_to_tcp or flange_to_tcp
        f2s = self.flange_to_scanner or flange_to_tcp.compose(tcp_to_scanner)
        f2sensor = self.flange_to_sensor or flange_to_tcp.compose(tcp_to_sensor)
        tcp_from_flange = f2t.inverse()
        tcp_to_sensor_cal = tcp_from_flange.compose(f2sensor)
        com = None
        if self.payload_com_sensor_mm is not None:
            com = tcp_to_sensor_cal.apply(np.asarray(self.payload_com_sensor_mm, dtype=float))
        return {"flange_to_tcp": f2t, "tcp_to_scanner": tcp_from_flange.compose(f2s),
                "tcp_to_sensor": tcp_to_sensor_cal, "payload_com_tcp_mm": com,
                "payload_mass_kg": self.payload_mass_kg}

    def apply_to(self, cell_spec):  # noqa: ANN001, ANN201 — controller.config.CellSpec in and out
        """A copy of the cell spec with the calibration in place (tool frames, tool shapes kept
        fixed on the flange, payload, object placement)."""
        tool = cell_spec.tool
        pose_spec = type(tool.flange_to_tcp)    # config.PoseSpec, taken from the spec given
        old_f2t = tool.flange_to_tcp.pose()
        frames = self.tool_frames(old_f2t, tool.tcp_to_scanner.pose(), tool.tcp_to_sensor.pose())
        new_from_old = frames["flange_to_tcp"].inverse().compose(old_f2t)   # new tcp <- old tcp

        def spec(pose: Pose) -> Any:
            return pose_spec(position_mm=tuple(float(v) for v in pose.position_mm),
                            rpy_deg=matrix_to_rpy_deg(pose.rotation))

        shapes = [s.model_copy(update={"pose": spec(new_from_old.compose(s.pose.pose()))}) for s in tool.shapes]
        update: dict[str, Any] = {"flange_to_tcp": spec(frames["flange_to_tcp"]),
                                  "tcp_to_scanner": spec(frames["tcp_to_scanner"]),
                                  "tcp_to_sensor": spec(frames["tcp_to_sensor"]), "shapes": shapes}
        if frames["payload_mass_kg"] is not None:
            update["payload_mass_kg"] = float(frames["payload_mass_kg"])
        if frames["payload_com_tcp_mm"] is not None:
            update["payload_com_mm"] = tuple(float(v) for v in frames["payload_com_tcp_mm"])
        else:
            update["payload_com_mm"] = tuple(float(v) for v in new_from_old.apply(np.array(tool.payload_com_mm)))
        cell_update: dict[str, Any] = {"tool": tool.model_copy(update=update)}
        if self.base_to_object is not None:
            cell_update["object"] = cell_spec.object.model_copy(update={"base_to_object": spec(self.base_to_object)})
        return cell_spec.model_copy(update=cell_update)


def _pose(values: Any, path: Path, where: str) -> Pose:
    v = np.asarray(values, dtype=float)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise CalibrationFileError(f"{path}: {where} must be six finite numbers [x, y, z, rx, ry, rz]")
    return Pose.from_list(v)


def load_calibration(path: str | Path) -> Corrections:
    """The corrections of a calibration file (CalibrationError if it is missing or invalid)."""
    p = Path(path)
    doc = read_document(p)
    secs = doc["sections"]
    kw: dict[str, Any] = {"calibrated_utc": {k: _parse_time(s["calibrated_utc"], p, k) for k, s in secs.items()}}
    try:
        if "ft" in secs:
            r = secs["ft"]["result"]
            kw["payload_mass_kg"] = float(r["payload_mass_kg"])
            kw["payload_com_sensor_mm"] = np.asarray(r["payload_com_sensor_mm"], dtype=float).reshape(3)
            kw["flange_to_sensor"] = _pose(r["flange_to_sensor"], p, "ft.flange_to_sensor")
        if "tcp" in secs:
            kw["flange_to_tcp"] = _pose(secs["tcp"]["result"]["flange_to_tcp"], p, "tcp.flange_to_tcp")
        if "scanner" in secs:
            kw["flange_to_scanner"] = _pose(secs["scanner"]["result"]["flange_to_scanner"], p,
                                            "scanner.flange_to_scanner")
        if "object" in secs:
            kw["base_to_object"] = _pose(secs["object"]["result"]["base_to_object"], p, "object.base_to_object")
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{p}: incomplete calibration result ({exc})") from None
    return Corrections(**kw)


def calibration_path(cell_spec, cell_path: str | Path) -> Path | None:  # noqa: ANN001 — config.CellSpec
    """The cell's calibration file, relative paths against the cell file's folder (None if not named)."""
    if cell_spec.calibration_file is None:
        return None
    p = Path(cell_spec.calibration_file)
    return p if p.is_absolute() else Path(cell_path).parent / p


def check_calibration(cell_spec, cell_path: str | Path, now: dt.datetime | None = None,  # noqa: ANN001
                      required: tuple[str, ...] = REQUIRED_FOR_RUN) -> list[str]:
    """Problems that should stop a real cell from running a plan (empty list: fine).

    Missing or unnamed file (simulated cells without one are calibrated by construction),
    an unreadable or foreign file, a missing required section, a section older than
    the cell's ``calibration_max_age_days`` or stamped in the future.
    """
    path = calibration_path(cell_spec, cell_path)
    if path is None:
        if cell_spec.kind == "simulated":
            return []
        return [f"cell {cell_spec.name!r} names no calibration_file; run elastoprobe calibrate"]
    if not path.exists():
        return [f"calibration file {path} is missing; run elastoprobe calibrate"]
    try:
        doc = read_document(path)
    except CalibrationError as exc:
        return [str(exc)]
    problems = []
    if doc.get("cell") != cell_spec.name:
        problems.append(f"{path}: calibrated for cell {doc.get('cell')!r}, not {cell_spec.name!r}")
    now = now or utc_now()
    max_age = float(cell_spec.calibration_max_age_days)
    for kind in required:
        sec = doc["sections"].get(kind)
        if sec is None:
            problems.append(f"{path}: no {kind} calibration; run elastoprobe calibrate {kind}")
            continue
        t = _parse_time(sec["calibrated_utc"], path, kind)
        age_days = (now - t).total_seconds() / 86400.0
        if age_days > max_age:
            problems.append(f"{path}: the {kind} calibration is {age_days:.1f} days old (the cell allows "
                            f"{max_age:g}); recalibrate")
        elif age_days < -1.0 / 24.0:
            problems.append(f"{path}: the {kind} calibration is stamped {t.isoformat()}, in the future")
    return problems


@dataclass(frozen=True)
class CalibrationState:
    """What a cell's controller believes and why: the calibration file used and its problems.

    ``applied``: the sections whose corrections are in the believed cell (empty: the cell
    file's nominal values). ``problems``: why the calibration is missing, partial, stale or
    unusable (empty: current). ``sha256``: of the file's bytes when it was read.
    """

    path: Path | None
    applied: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()
    sha256: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"path": None if self.path is None else str(self.path.resolve()), "sha256": self.sha256,
                "applied_sections": list(self.applied), "problems": list(self.problems)}


def believed_cell(cell_spec, cell_path: str | Path,  # noqa: ANN001, ANN201 — config.CellSpec in and out
                  now: dt.datetime | None = None) -> tuple[Any, CalibrationState]:
    """The cell as the controller believes it: the cell file with its calibration file's corrections.

    A readable calibration file of this cell is applied section by section (whatever it
    holds), even when some section is older than the cell allows: a stale calibration
    is still nearer the truth than the nominal drawing, and real cells refuse to run on
    one anyway unless the operator overrides that (``check_calibration``). Never raises:
    a missing, unreadable or foreign file leaves the nominal values and says why in
    ``problems``. A simulated cell that enables a miscalibration but names no
    calibration file is reported too (its controller believes the nominal values).
    """
    import hashlib

    path = calibration_path(cell_spec, cell_path)
    problems = list(check_calibration(cell_spec, cell_path, now=now))
    sim = getattr(cell_spec, "simulation", None)
    if path is None:
        if cell_spec.kind == "simulated" and sim is not None and sim.miscalibration.enabled:
            problems.append(f"simulated cell {cell_spec.name!r} is miscalibrated but names no calibration_file: "
                            f"the controller believes the cell file's nominal geometry")
        return cell_spec, CalibrationState(None, (), tuple(problems), None)
    if not path.exists():          # check_calibration said so already
        problems.append("the controller believes the cell file's nominal geometry")
        return cell_spec, CalibrationState(path, (), tuple(problems), None)
    try:
        data = read_input_bytes(path)
        doc = read_document(path)
        if doc.get("cell") != cell_spec.name:
            raise CalibrationFileError(f"{path}: calibrated for cell {doc.get('cell')!r}, not {cell_spec.name!r}")
        corrections = load_calibration(path)
    except (OSError, CalibrationError) as exc:
        msg = str(exc) if isinstance(exc, CalibrationError) else f"{path}: {exc.strerror or exc}"
        if msg not in problems:
            problems.append(msg)
        problems.append("the controller believes the cell file's nominal geometry")
        return cell_spec, CalibrationState(path, (), tuple(problems), None)
    applied = tuple(k for k in KINDS if k in doc["sections"])
    return corrections.apply_to(cell_spec), CalibrationState(path, applied, tuple(problems),
                                                             hashlib.sha256(data).hexdigest())
