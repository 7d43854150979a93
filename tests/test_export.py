"""HDF5 export: a round trip equal to the journal bit for bit, units on the datasets,
atomic replacement, partial sessions and damaged model files."""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from elastoprobe.controller import export as X
from elastoprobe.controller.journal import STEP_ARRAYS_OPTIONAL, STEP_ARRAYS_REQUIRED, Journal

from report_fixture import build_session


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_session(tmp_path_factory.mktemp("exp") / "session", "final")


@pytest.fixture(scope="module")
def exported(session: Path) -> tuple[Path, X.ExportedSession]:
    path = X.export_hdf5(session, session.parent / "out" / "session.h5")
    return path, X.read_back(path)


def test_step_arrays_round_trip_bit_for_bit(session: Path, exported: tuple[Path, X.ExportedSession]) -> None:
    _, e = exported
    with Journal.open_readonly(session) as j:
        results = j.step_results()
        records = j.steps()
    assert results and set(e.step_arrays) == set(results)
    for sid, res in results.items():
        got = e.step_arrays[sid]
        for name in STEP_ARRAYS_REQUIRED + STEP_ARRAYS_OPTIONAL:
            want = getattr(res, name)
            if want is None:
                assert name not in got
            else:
                assert _same_bits(got[name], want), (sid, name)
        assert e.step_attrs[sid]["robot_time_s"] == res.robot_time_s
        assert e.step_attrs[sid]["summary"] == res.summary
    # NaNs (missing samples) survive as NaNs in the same places.
    assert any(np.isnan(a["scans_xz_mm"]).any() for a in e.step_arrays.values())
    assert [r["step_id"] for r in e.steps] == [r.step_id for r in records]
    for row, rec in zip(e.steps, records):
        assert (row["phase"], row["round"], row["status"], row["attempts"], row["fault_id"]) == \
            (rec.phase, rec.round, rec.status, rec.attempts, rec.fault_id)
        assert (row["started_utc"], row["finished_utc"], row["fail_reason"], row["summary"]) == \
            (rec.started_utc, rec.finished_utc, rec.fail_reason, rec.summary)
        assert (row["target_index"], row["angle_deg"], row["force_n"], row["order_index"]) == \
            (rec.plan.target_index, rec.plan.angle_deg, rec.plan.force_n, rec.plan.order_index)
        for name in ("point_mm", "normal", "t"):
            assert _same_bits(row[name], np.asarray(getattr(rec.plan, name), dtype=np.float64))


def test_phases_regions_and_models_round_trip(session: Path, exported: tuple[Path, X.ExportedSession]) -> None:
    _, e = exported
    with Journal.open_readonly(session) as j:
        phases = {(p["name"], p["round"]): j.phase(p["name"], p["round"]) for p in j.phases()}
        models = j.models()
    assert set(e.phases) == set(phases)
    for key, rec in phases.items():
        got = e.phases[key]
        assert got["outputs"] == rec.outputs and got["outputs_hash"] == rec.outputs_hash
        assert got["status"] == rec.status and got["step_ids"] == rec.step_ids
        assert got["completed_utc"] == rec.completed_utc and got["committed_utc"] == rec.committed_utc
        assert set(got["arrays"]) == set(rec.arrays)
        for name, arr in rec.arrays.items():
            assert _same_bits(got["arrays"][name], arr), (key, name)
    latest = phases[("regions", 1)]
    assert _same_bits(e.regions["labels"], latest.arrays["labels"])
    assert _same_bits(e.regions["labelled_targets"], latest.arrays["labelled_targets"])
    assert _same_bits(e.regions["cloud_labels"], phases[("final", 0)].arrays["cloud_labels"])
    assert e.regions["regions_round"] == 1 and e.regions["n_regions"] == 2
    assert set(e.models) == {(m["region"], m["member"]) for m in models}
    for m in models:
        got = e.models[(m["region"], m["member"])]
        assert got["sha256"] == m["sha256"] and got["metrics"] == m["metrics"] and got["problem"] is None
        base = (session / m["path"]).with_suffix("")
        assert got["meta"] == json.loads(base.with_suffix(".json").read_text())
        with np.load(base.with_suffix(".npz")) as z:
            assert set(got["weights"]) == set(z.files)
            for name in z.files:
                assert _same_bits(got["weights"][name], z[name])


def test_faults_log_and_provenance_round_trip(session: Path, exported: tuple[Path, X.ExportedSession]) -> None:
    _, e = exported
    with Journal.open_readonly(session) as j:
        faults, transitions, events = j.faults(), j.transitions(), j.events()
        prov, sess, robot, runs = j.provenance(), j.session(), j.robot_time_s(), j.summary()["runs"]
    assert len(e.faults) == len(faults) == 2
    for got, f in zip(e.faults, faults):
        assert (got["fault_id"], got["kind"], got["t_robot_s"], got["t_wall_utc"], got["step_id"], got["message"],
                got["policy_action"]) == (f.fault_id, f.kind, f.t_robot_s, f.t_wall_utc, f.step_id, f.message,
                                          f.policy_action)
        if f.raw is None:
            assert got["raw"] is None
        else:
            assert _same_bits(got["raw"], f.raw)
    assert any(f.raw is None for f in faults) and any(f.raw is not None for f in faults)
    assert e.transitions == transitions and e.events == events
    assert e.provenance == prov and e.session == sess and e.robot_time_s == robot and e.runs == runs


def test_units_are_on_the_datasets(exported: tuple[Path, X.ExportedSession]) -> None:
    path, e = exported
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == X.FORMAT
        step = f["steps/data"][next(iter(f["steps/data"]))]
        for name, ds in step.items():
            assert ds.attrs["units"] == X.STEP_ARRAY_ATTRS[name]["units"] and "frame" in ds.attrs
        assert f["steps/force_n"].attrs["units"] == "N" and f["steps/angle_deg"].attrs["units"] == "deg"
        assert f["phases/cloud/0/arrays/points_mm"].attrs["units"] == "mm"
        raw = f["faults/raw"]
        assert all(ds.attrs["columns"] == "t_s, Fx, Fy, Fz, Tx, Ty, Tz" for ds in raw.values())
        # Region shortcuts are hard links, not copies.
        assert f["regions/labels"].id == f["phases/regions/1/arrays/labels"].id


def test_failed_export_leaves_the_previous_file_and_no_temporary(session: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "s.h5"
    X.export_hdf5(session, out)
    before = out.read_bytes()

    def boom(*_args: object) -> None:
        raise RuntimeError("disk error in the middle of the export")

    monkeypatch.setattr(X, "_write_faults", boom)
    with pytest.raises(RuntimeError, match="middle of the export"):
        X.export_hdf5(session, out)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


def test_partial_session_and_damaged_model(tmp_path: Path) -> None:
    created = build_session(tmp_path / "created", "created")
    e = X.read_back(X.export_hdf5(created))
    assert (created / "export.h5").exists()
    assert e.steps == [] and e.step_arrays == {} and e.faults == [] and e.phases == {}
    assert e.regions == {"regions_round": -1} and e.session["status"] == "running"
    surveyed = build_session(tmp_path / "surveyed", "survey")
    e = X.read_back(X.export_hdf5(surveyed))
    assert len(e.step_arrays) == 24 and e.faults[0]["kind"] == "force_spike"
    assert e.steps[1]["attempts"] == 2                          # failed once, then done


def test_damaged_model_file_is_recorded_not_fatal(session: Path, tmp_path: Path) -> None:
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(session, copy, ignore=shutil.ignore_patterns("session.lock", "out"))
    (copy / "models" / "round0" / "region0.npz").unlink()
    e = X.read_back(X.export_hdf5(copy, tmp_path / "c.h5"))
    assert e.models[(0, 0)]["problem"] and e.models[(0, 0)]["weights"] == {}
    assert e.models[(1, 0)]["problem"] is None and e.models[(1, 0)]["weights"]
