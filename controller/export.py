"""``elastoprobe export DIR --format hdf5``: the whole session in one HDF5 file.

Everything the journal holds — raw and reference scans, profiles, forces, poses, each
step's plan and status, phases with their arrays and outputs, regions, model metadata
and weights, faults with their raw F/T data, transitions, events, runs, robot time and
provenance — in the layout documented in ``docs/hdf5.md`` (units in dataset attributes).
Arrays are copied with their journal dtype and shape (lossless gzip), so a read back
equals the journal bit for bit; :func:`read_back` does that for the round-trip test and
for users who prefer dictionaries.

The file is written to a temporary name beside the target, fsynced and renamed, so a
reader (or a kill) never leaves half an export under the real name. The journal is
opened read-only: exporting a running session never blocks it (each table is read as it
stands when the export reaches it).
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .core.atomic import ensure_dir, fsync_dir, readable_text
from .core.errors import DiskError
from .journal import STEP_ARRAYS_OPTIONAL, STEP_ARRAYS_REQUIRED, Journal, StepRecord, to_json
from .predict import read_manifest

FORMAT = "elastoprobe.session.hdf5/1"
STEP_CHUNK = 64                  # done steps loaded from the journal at a time (bounds memory)
COMPRESS_MIN_ELEMENTS = 1024     # smaller arrays are stored plainly (gzip would only add overhead)

# Units, frames and meaning of each step array (written as dataset attributes).
STEP_ARRAY_ATTRS: dict[str, dict[str, str]] = {
    "scans_xz_mm": {"units": "mm", "frame": "scanner", "shape": "(S, L, 2): x, z per sample; NaN = missing",
                    "description": "raw scans during the hold"},
    "scan_force_n": {"units": "N", "frame": "base", "shape": "(S, 3)",
                     "description": "mean contact force around each exposure"},
    "scan_pose": {"units": "mm, rad", "frame": "base <- tcp", "shape": "(S, 6): x, y, z, rotation vector",
                  "description": "TCP pose at each exposure"},
    "profile_depth_mm": {"units": "mm", "frame": "object; depth along -n", "shape": "(L,)",
                         "description": "averaged depth against the reference; NaN = missing"},
    "force_direction": {"units": "1", "frame": "base", "shape": "(3,)",
                        "description": "unit vector of the measured force the probe exerted"},
    "reference_xz_mm": {"units": "mm", "frame": "scanner", "shape": "(R, L, 2)",
                        "description": "zero-force reference scans of the same place"},
    "scan_t_s": {"units": "s", "frame": "robot clock of the run", "shape": "(S,)", "description": "exposure times"},
    "reference_pose": {"units": "mm, rad", "frame": "base <- tcp", "shape": "(R, 6)",
                       "description": "TCP pose at each reference scan"},
    "profile_x_mm": {"units": "mm", "frame": "along t", "shape": "(L,)", "description": "profile grid"},
}

# Known phase arrays (anything else is still exported, with units "see phase outputs").
PHASE_ARRAY_ATTRS: dict[str, dict[str, str]] = {
    "points_mm": {"units": "mm", "frame": "object"}, "normals": {"units": "1", "frame": "object"},
    "units": {"units": "mm", "frame": "object"}, "target_points_mm": {"units": "mm", "frame": "object"},
    "target_normals": {"units": "1", "frame": "object"}, "target_t": {"units": "1", "frame": "object"},
    "target_index": {"units": "index"}, "edge_flag": {"units": "bool (int8)"},
    "labelled_targets": {"units": "target index"}, "labels": {"units": "region id"},
    "features": {"units": "see outputs.feature_names"}, "cloud_labels": {"units": "region id per cloud point"},
    "far_field_mm": {"units": "mm", "description": "survey profile far from the contact: level, one sample's scatter"},
}


# ============================================================================ writing helpers
def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _str_dtype() -> Any:
    import h5py
    return h5py.string_dtype("utf-8")


def _put_array(group: Any, name: str, array: np.ndarray, attrs: dict[str, str] | None = None) -> Any:
    """A dataset holding ``array`` exactly (dtype, byte order, shape); gzip+shuffle if large."""
    a = np.asarray(array)
    kwargs: dict[str, Any] = {}
    if a.size >= COMPRESS_MIN_ELEMENTS and a.ndim >= 1:
        kwargs = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    ds = group.create_dataset(name, data=a, **kwargs)
    for k, v in (attrs or {}).items():
        ds.attrs[k] = v
    return ds


def _put_strings(group: Any, name: str, values: Sequence[str | None], attrs: dict[str, str] | None = None) -> Any:
    """A UTF-8 string column; None is stored as "" (documented per column as nullable)."""
    data = np.array(["" if v is None else str(v) for v in values], dtype=object)
    ds = group.create_dataset(name, data=data, dtype=_str_dtype(), shape=(len(values),))
    for k, v in (attrs or {}).items():
        ds.attrs[k] = v
    return ds


def _ints(values: Iterable[int | None]) -> np.ndarray:
    """An int64 column; None is stored as -1."""
    return np.array([-1 if v is None else int(v) for v in values], dtype=np.int64)


def _floats(values: Iterable[float | None]) -> np.ndarray:
    """A float64 column; None is stored as NaN."""
    return np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)


def _step_key(step_id: int) -> str:
    return f"{int(step_id):06d}"


# ============================================================================ sections
def _write_session(f: Any, j: Journal) -> None:
    g = f.create_group("session")
    for k, v in j.session().items():
        g.attrs[k] = "" if v is None else v
    p = f.create_group("provenance")
    p.attrs["encoding"] = "each attribute is the JSON text of one provenance entry"
    for k, v in j.provenance().items():
        p.attrs[k] = to_json(v)
    runs = j.summary()["runs"]
    r = f.create_group("runs")
    r.create_dataset("run_id", data=_ints(x["run_id"] for x in runs))
    r.create_dataset("pid", data=_ints(x["pid"] for x in runs))
    for col in ("mode", "started_utc", "host", "ended_utc", "end_status"):
        _put_strings(r, col, [x[col] for x in runs])
    rt = f.create_group("robot_time")
    rt.attrs["units"] = "s"
    for k, v in j.robot_time_s().items():
        rt.attrs[k] = float(v)


def _write_phases(f: Any, j: Journal) -> dict[tuple[str, int], Any]:
    g = f.create_group("phases")
    g.attrs["layout"] = "phases/<name>/<round>: attrs status, outputs (JSON), ...; step_ids; arrays/<name>"
    out = {}
    for order, p in enumerate(j.phases()):
        rec = j.phase(p["name"], p["round"])
        if rec is None:
            continue
        pg = g.require_group(rec.name).create_group(str(rec.round))
        pg.attrs.update({"status": rec.status, "outputs": to_json(rec.outputs), "outputs_hash": rec.outputs_hash,
                         "committed_utc": rec.committed_utc, "completed_utc": rec.completed_utc or "",
                         "commit_order": order})
        pg.create_dataset("step_ids", data=np.asarray(rec.step_ids, dtype=np.int64))
        ag = pg.create_group("arrays")
        for name, arr in sorted(rec.arrays.items()):
            _put_array(ag, name, arr, PHASE_ARRAY_ATTRS.get(name, {"units": "see phase outputs"}))
        out[(rec.name, rec.round)] = pg
    return out


def _write_steps(f: Any, j: Journal) -> None:
    steps = j.steps()
    g = f.create_group("steps")
    g.attrs["order"] = "execution order (order_index, then step_id)"
    g.create_dataset("step_id", data=_ints(s.step_id for s in steps))
    _put_strings(g, "phase", [s.phase for s in steps])
    g.create_dataset("round", data=_ints(s.round for s in steps))
    g.create_dataset("target_index", data=_ints(s.plan.target_index for s in steps))
    for name, unit in (("point_mm", "mm"), ("normal", "1"), ("t", "1")):
        ds = g.create_dataset(name, data=np.array([getattr(s.plan, name) for s in steps], dtype=np.float64)
                              .reshape(-1, 3))
        ds.attrs.update({"units": unit, "frame": "object"})
    g.create_dataset("angle_deg", data=_floats(s.plan.angle_deg for s in steps)).attrs["units"] = "deg"
    g.create_dataset("force_n", data=_floats(s.plan.force_n for s in steps)).attrs["units"] = "N"
    g.create_dataset("order_index", data=_ints(s.plan.order_index for s in steps))
    _put_strings(g, "status", [s.status for s in steps])
    g.create_dataset("attempts", data=_ints(s.attempts for s in steps))
    for col in ("started_utc", "finished_utc", "fail_reason"):
        _put_strings(g, col, [getattr(s, col) for s in steps], {"nullable": "empty string = none"})
    g.create_dataset("fault_id", data=_ints(s.fault_id for s in steps)).attrs["nullable"] = "-1 = none"
    _put_strings(g, "summary", [to_json(s.summary) if s.summary is not None else None for s in steps],
                 {"nullable": "empty string = not done", "encoding": "JSON"})
    data = g.create_group("data")
    data.attrs["layout"] = "data/<step_id, 6+ digits>/<array>; done steps only"
    done = [s for s in steps if s.status == "done"]
    for start in range(0, len(done), STEP_CHUNK):
        chunk = done[start:start + STEP_CHUNK]
        results = j.step_results([s.step_id for s in chunk])
        for s in chunk:
            _write_step_data(data, s, results[s.step_id])


def _write_step_data(data: Any, rec: StepRecord, result: Any) -> None:
    sg = data.create_group(_step_key(rec.step_id))
    sg.attrs.update({"step_id": rec.step_id, "robot_time_s": float(result.robot_time_s),
                     "summary": to_json(result.summary)})
    for name in STEP_ARRAYS_REQUIRED + STEP_ARRAYS_OPTIONAL:
        value = getattr(result, name)
        if value is not None:
            _put_array(sg, name, value, STEP_ARRAY_ATTRS[name])


def _write_regions(f: Any, j: Journal, phase_groups: dict[tuple[str, int], Any]) -> None:
    """Shortcuts (HDF5 hard links, no copies) to the latest region labels and the final map."""
    g = f.create_group("regions")
    rounds = sorted(r for (name, r) in phase_groups if name == "regions")
    g.attrs["regions_round"] = rounds[-1] if rounds else -1
    if rounds:
        arrays = phase_groups[("regions", rounds[-1])]["arrays"]
        for name in ("labelled_targets", "labels"):
            if name in arrays:
                g[name] = arrays[name]
        g.attrs["n_regions"] = int(json.loads(phase_groups[("regions", rounds[-1])].attrs["outputs"]).get("n_regions", -1))
    final = phase_groups.get(("final", 0))
    if final is not None and "cloud_labels" in final["arrays"]:
        g["cloud_labels"] = final["arrays"]["cloud_labels"]


MODEL_ARRAY_UNITS = {"w1": "normalised inputs -> hidden", "b1": "hidden", "w2": "hidden -> normalised depth",
                     "b2": "normalised depth", "x_mm": "mm",
                     "limits": "force range N (2), angle range deg (2), served depth bounds mm (2)",
                     "support_forces_n": "N", "support_angles_deg": "deg",
                     "support_codes": "0 measured, 1 mirrored, 2 tip, 3 inferred, 4 unsupported (angle, force, x)"}


def _write_models(f: Any, j: Journal) -> None:
    g = f.create_group("models")
    g.attrs["layout"] = ("models/region_<r>/member_<m>: attrs path, sha256, metrics, meta (JSON); w1, b1, w2, b2, "
                         "x_mm; with serving limits also limits, support_forces_n, support_angles_deg, support_codes")
    for m in j.models():
        mg = g.require_group(f"region_{int(m['region'])}").create_group(f"member_{int(m['member'])}")
        mg.attrs.update({"region": int(m["region"]), "member": int(m["member"]), "path": m["path"],
                         "sha256": m["sha256"], "metrics": to_json(m["metrics"])})
        path = Path(m["path"]) if Path(m["path"]).is_absolute() else j.session_dir / m["path"]
        _put_model_file(mg, path)
    manifest = read_manifest(j.session_dir)
    if manifest is None:
        return
    # What `elastoprobe train` refitted since (and predict now serves): not in the journal.
    rg = f.create_group("retrained_models")
    rg.attrs.update({"layout": "retrained_models/region_<r>: attrs path, model_hash, meta; the model's arrays",
                     "trained_utc": str(manifest.get("trained_utc", "")),
                     "session_models_round": int(manifest.get("session_models_round", -1))})
    for region, info in sorted(manifest["regions"].items()):
        if not isinstance(info, dict) or "path" not in info:
            continue
        mg = rg.create_group(f"region_{int(region)}")
        mg.attrs.update({"region": int(region), "path": str(info["path"]), "model_hash": str(info.get("model_hash", ""))})
        _put_model_file(mg, j.session_dir / info["path"])


def _put_model_file(mg: Any, path: Path) -> None:
    """A model's metadata text and arrays into the group ``mg`` (a problem attr if unreadable)."""
    base = path.with_suffix("")
    try:
        meta_text = base.with_suffix(".json").read_text(encoding="utf-8")
        with np.load(base.with_suffix(".npz"), allow_pickle=False) as z:
            weights = {k: z[k] for k in z.files}
    except Exception as exc:   # a missing or damaged model file is recorded, the export goes on
        mg.attrs["problem"] = f"{type(exc).__name__}: {exc}"
        return
    mg.attrs["meta"] = meta_text
    for name, arr in sorted(weights.items()):
        _put_array(mg, name, arr, {"units": MODEL_ARRAY_UNITS.get(name, "")})


def _write_faults(f: Any, j: Journal) -> None:
    faults = j.faults()
    g = f.create_group("faults")
    g.create_dataset("fault_id", data=_ints(x.fault_id for x in faults))
    _put_strings(g, "kind", [x.kind for x in faults])
    g.create_dataset("t_robot_s", data=_floats(x.t_robot_s for x in faults)).attrs.update(
        {"units": "s", "nullable": "NaN = none"})
    _put_strings(g, "t_wall_utc", [x.t_wall_utc for x in faults])
    g.create_dataset("step_id", data=_ints(x.step_id for x in faults)).attrs["nullable"] = "-1 = none"
    _put_strings(g, "message", [x.message for x in faults])
    _put_strings(g, "policy_action", [x.policy_action for x in faults], {"nullable": "empty string = none"})
    raw = g.create_group("raw")
    raw.attrs["layout"] = "raw/<fault_id, 6+ digits>: (N, 7) t_s, Fx, Fy, Fz (N), Tx, Ty, Tz (N m)"
    for x in faults:
        if x.raw is not None:
            _put_array(raw, _step_key(x.fault_id), x.raw,
                       {"units": "s, N, N, N, N m, N m, N m", "columns": "t_s, Fx, Fy, Fz, Tx, Ty, Tz",
                        "frame": "sensor"})


def _write_log(f: Any, j: Journal) -> None:
    tr = j.transitions()
    g = f.create_group("transitions")
    g.create_dataset("id", data=_ints(t["id"] for t in tr))
    g.create_dataset("run_id", data=_ints(t["run_id"] for t in tr)).attrs["nullable"] = "-1 = none"
    g.create_dataset("t_robot_s", data=_floats(t["t_robot_s"] for t in tr)).attrs.update(
        {"units": "s (robot clock of the run)", "nullable": "NaN = none"})
    for col in ("t_wall_utc", "from_state", "to_state", "trigger"):
        _put_strings(g, col, [t[col] for t in tr])
    g.create_dataset("step_id", data=_ints(t["step_id"] for t in tr)).attrs["nullable"] = "-1 = none"
    ev = j.events()
    e = f.create_group("events")
    e.create_dataset("id", data=_ints(x["id"] for x in ev))
    e.create_dataset("run_id", data=_ints(x["run_id"] for x in ev)).attrs["nullable"] = "-1 = none"
    _put_strings(e, "t_wall_utc", [x["t_wall_utc"] for x in ev])
    e.create_dataset("t_robot_s", data=_floats(x["t_robot_s"] for x in ev)).attrs.update(
        {"units": "s", "nullable": "NaN = none"})
    _put_strings(e, "kind", [x["kind"] for x in ev])
    _put_strings(e, "record", [to_json(x["record"]) for x in ev], {"encoding": "JSON"})
    arts = j.artifacts()
    a = f.create_group("artifacts")
    for col in ("name", "path", "sha256"):
        _put_strings(a, col, [x[col] for x in arts])


# ============================================================================ the export
def export_hdf5(session_dir: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None) -> Path:
    """Export the session in ``session_dir`` to ``out_path`` (default ``DIR/export.h5``, as the CLI).

    Written to ``.<name>.*.tmp`` beside the target, fsynced, then renamed; returns the path.
    """
    import h5py

    d = Path(session_dir)
    out = Path(out_path) if out_path is not None else d / "export.h5"
    j = Journal.open_readonly(d)
    try:
        ensure_dir(out.parent)
        # The export holds about what the journal holds: refuse before h5py meets a full disk.
        need, free = (d / "journal.sqlite").stat().st_size, shutil.disk_usage(out.parent).free
        if free < need:
            raise DiskError(f"cannot write: about {need / 2**20:.0f} MiB needed, {free / 2**20:.0f} MiB free "
                            f"(the disk is full)", path=str(out))
        fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
        os.close(fd)
    except OSError as exc:
        j.close()
        raise DiskError.from_os_error(exc, str(out)) from None
    except BaseException:
        j.close()
        raise
    # h5py reports a failed write again from its objects' destructors ("Exception ignored
    # in ..."); the error that matters is raised below, so those echoes are not printed.
    hook, sys.unraisablehook = sys.unraisablehook, lambda unraisable: None
    try:
        with h5py.File(tmp_name, "w") as f:
            f.attrs.update({"format": FORMAT, "exported_utc": _utc_now(), "session_dir": readable_text(str(d.resolve())),
                            "layout": "docs/hdf5.md"})
            _write_session(f, j)
            phase_groups = _write_phases(f, j)
            _write_steps(f, j)
            _write_regions(f, j, phase_groups)
            _write_models(f, j)
            _write_faults(f, j)
            _write_log(f, j)
        with open(tmp_name, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_name, out)
    except BaseException as exc:
        Path(tmp_name).unlink(missing_ok=True)
        if isinstance(exc, OSError):       # h5py and the file system say "full" or "read-only" so
            raise DiskError.from_os_error(exc, str(out)) from None
        raise
    finally:
        j.close()
        sys.unraisablehook = hook
    fsync_dir(out.parent)
    return out


# ============================================================================ reading back
@dataclass
class ExportedSession:
    """An export read back into plain Python (arrays as numpy, JSON decoded, sentinels undone)."""

    format: str
    session: dict[str, Any]
    provenance: dict[str, Any]
    runs: list[dict[str, Any]]
    robot_time_s: dict[str, float]
    phases: dict[tuple[str, int], dict[str, Any]]
    steps: list[dict[str, Any]]
    step_arrays: dict[int, dict[str, np.ndarray]]
    step_attrs: dict[int, dict[str, Any]]
    regions: dict[str, Any]
    models: dict[tuple[int, int], dict[str, Any]]
    faults: list[dict[str, Any]]
    transitions: list[dict[str, Any]]
    events: list[dict[str, Any]]
    artifacts: list[dict[str, Any]] = field(default_factory=list)
    retrained_models: dict[int, dict[str, Any]] = field(default_factory=dict)


def _col(g: Any, name: str) -> list[Any]:
    ds = g[name]
    if ds.dtype.kind == "O":
        return list(ds.asstr()[()])
    return ds[()].tolist()


def _none_str(v: str) -> str | None:
    return None if v == "" else v


def _none_int(v: int) -> int | None:
    return None if v == -1 else int(v)


def _none_float(v: float) -> float | None:
    return None if np.isnan(v) else float(v)


def _table(g: Any, columns: dict[str, Any]) -> list[dict[str, Any]]:
    cols = {name: [conv(v) for v in _col(g, name)] for name, conv in columns.items()}
    n = len(next(iter(cols.values()))) if cols else 0
    return [{name: cols[name][k] for name in cols} for k in range(n)]


def _attr_str(v: Any) -> Any:
    return v.decode("utf-8") if isinstance(v, bytes) else v


def read_back(path: str | os.PathLike[str]) -> ExportedSession:
    """Read an export written by :func:`export_hdf5` (for checks and round trips)."""
    import h5py

    with h5py.File(path, "r") as f:
        session = {k: _attr_str(v) for k, v in f["session"].attrs.items()}
        session = {k: (None if v == "" and k == "status_reason" else v) for k, v in session.items()}
        session["seed"] = int(session["seed"])
        prov = {k: json.loads(_attr_str(v)) for k, v in f["provenance"].attrs.items() if k != "encoding"}
        runs = _table(f["runs"], {"run_id": int, "mode": str, "started_utc": str, "pid": int, "host": str,
                                  "ended_utc": _none_str, "end_status": _none_str})
        robot = {k: float(v) for k, v in f["robot_time"].attrs.items() if k != "units"}
        phases: dict[tuple[str, int], dict[str, Any]] = {}
        for name, g in f["phases"].items():
            for rnd, pg in g.items():
                phases[(name, int(rnd))] = {
                    "status": _attr_str(pg.attrs["status"]), "outputs": json.loads(_attr_str(pg.attrs["outputs"])),
                    "outputs_hash": _attr_str(pg.attrs["outputs_hash"]),
                    "committed_utc": _attr_str(pg.attrs["committed_utc"]),
                    "completed_utc": _none_str(_attr_str(pg.attrs["completed_utc"])),
                    "step_ids": pg["step_ids"][()].tolist(),
                    "arrays": {k: ds[()] for k, ds in pg["arrays"].items()}}
        sg = f["steps"]
        steps = _table(sg, {"step_id": int, "phase": str, "round": int, "target_index": int, "angle_deg": float,
                            "force_n": float, "order_index": int, "status": str, "attempts": int,
                            "started_utc": _none_str, "finished_utc": _none_str, "fail_reason": _none_str,
                            "fault_id": _none_int, "summary": lambda v: json.loads(v) if v else None})
        for name in ("point_mm", "normal", "t"):
            for row, v in zip(steps, sg[name][()]):
                row[name] = v
        step_arrays, step_attrs = {}, {}
        for key, g in sg["data"].items():
            sid = int(g.attrs["step_id"])
            step_arrays[sid] = {k: ds[()] for k, ds in g.items()}
            step_attrs[sid] = {"robot_time_s": float(g.attrs["robot_time_s"]),
                               "summary": json.loads(_attr_str(g.attrs["summary"]))}
        regions = {k: ds[()] for k, ds in f["regions"].items()}
        regions.update({k: int(v) for k, v in f["regions"].attrs.items()})
        models: dict[tuple[int, int], dict[str, Any]] = {}
        for rg in f["models"].values():
            for mg in rg.values():
                attrs = {k: _attr_str(v) for k, v in mg.attrs.items()}
                models[(int(attrs["region"]), int(attrs["member"]))] = {
                    "path": attrs["path"], "sha256": attrs["sha256"], "metrics": json.loads(attrs["metrics"]),
                    "meta": json.loads(attrs["meta"]) if "meta" in attrs else None, "problem": attrs.get("problem"),
                    "weights": {k: ds[()] for k, ds in mg.items()}}
        retrained: dict[int, dict[str, Any]] = {}
        for mg in (f["retrained_models"].values() if "retrained_models" in f else []):
            attrs = {k: _attr_str(v) for k, v in mg.attrs.items()}
            retrained[int(attrs["region"])] = {
                "path": attrs["path"], "model_hash": attrs.get("model_hash"), "problem": attrs.get("problem"),
                "meta": json.loads(attrs["meta"]) if "meta" in attrs else None,
                "weights": {k: ds[()] for k, ds in mg.items()}}
        fg = f["faults"]
        faults = _table(fg, {"fault_id": int, "kind": str, "t_robot_s": _none_float, "t_wall_utc": str,
                             "step_id": _none_int, "message": str, "policy_action": _none_str})
        for row in faults:
            key = _step_key(row["fault_id"])
            row["raw"] = fg["raw"][key][()] if key in fg["raw"] else None
        transitions = _table(f["transitions"], {"id": int, "run_id": _none_int, "t_robot_s": _none_float,
                                                "t_wall_utc": str, "from_state": str, "to_state": str,
                                                "trigger": str, "step_id": _none_int})
        events = _table(f["events"], {"id": int, "run_id": _none_int, "t_wall_utc": str, "t_robot_s": _none_float,
                                      "kind": str, "record": json.loads})
        artifacts = _table(f["artifacts"], {"name": str, "path": str, "sha256": str})
        return ExportedSession(format=_attr_str(f.attrs["format"]), session=session, provenance=prov, runs=runs,
                               robot_time_s=robot, phases=phases, steps=steps, step_arrays=step_arrays,
                               step_attrs=step_attrs, regions=regions, models=models, faults=faults,
                               transitions=transitions, events=events, artifacts=artifacts,
                               retrained_models=retrained)
