"""The journal's contracts one by one: states, checksums, provenance, file systems, readers."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core.errors import InputError
from elastoprobe.controller.documents import Publisher, TransitionDoc
from elastoprobe.controller.journal import (
    InputsChanged, Journal, JournalCorruption, JournalError, SessionMeta, StepPlan, StepResult,
    StepStateError, check_local_filesystem, decode_array, encode_array, filesystem_type,
)
from elastoprobe.controller.locking import LockHeld
from elastoprobe.controller.machine import SessionMachine
from elastoprobe.controller.provenance import collect_provenance, sha256_text
from elastoprobe.controller.salvage import read_rows

PLAN = "name: demo\nseed: 7\ntargets: []\n"
CELL = "name: sim\nkind: sim\n"


def _meta(tmp_path: Path) -> SessionMeta:
    (tmp_path / "plan.yaml").write_text(PLAN)
    (tmp_path / "cell.yaml").write_text(CELL)
    prov = collect_provenance(tmp_path / "plan.yaml", tmp_path / "cell.yaml", None)
    return SessionMeta("demo", 7, prov)


def _plans(first: int, n: int) -> list[StepPlan]:
    return [StepPlan(step_id=first + k, target_index=k // 2, point_mm=np.array([k, 2.0, 3.0]),
                     normal=np.array([0, 0, 1.0]), t=np.array([1.0, 0, 0]), angle_deg=45.0,
                     force_n=1.0 + k % 2, order_index=first + k) for k in range(n)]


def _result(seed: int, n_scans: int = 4, n_samples: int = 32) -> StepResult:
    rng = np.random.default_rng(seed)
    return StepResult(scans_xz_mm=rng.normal(size=(n_scans, n_samples, 2)), scan_force_n=rng.normal(size=(n_scans, 3)),
                      scan_pose=rng.normal(size=(n_scans, 6)), profile_depth_mm=rng.normal(size=n_samples),
                      force_direction=np.array([0.0, 0.6, -0.8]),
                      reference_xz_mm=rng.normal(size=(2, n_samples, 2)), robot_time_s=1.5,
                      summary={"force_measured_n": 2.0})


@pytest.fixture
def journal(tmp_path: Path):
    j = Journal.create(tmp_path / "session", _meta(tmp_path), min_free_bytes=0)
    yield j
    j.close()


def test_pragmas_schema_and_provenance(journal: Journal) -> None:
    c = journal._conn
    assert c.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert c.execute("PRAGMA synchronous").fetchone()[0] == 2          # FULL
    assert c.execute("PRAGMA foreign_keys").fetchone()[0] == 1
    prov = journal.provenance()
    assert prov["plan"]["text"] == PLAN and prov["plan"]["sha256"] == sha256_text(PLAN)
    assert prov["packages"]["numpy"] == np.__version__
    assert journal.session()["seed"] == 7 and journal.session()["status"] == "created"
    journal.set_provenance("devices", {"arm": {"serial": "20235500001"}})
    assert journal.provenance()["devices"]["arm"]["serial"] == "20235500001"
    with pytest.raises(JournalError):
        journal.set_provenance("plan", {"text": "other"})


def test_step_lifecycle_and_no_double_commit(journal: Journal) -> None:
    journal.commit_phase("survey", 0, {"n": 3}, {"units": np.zeros((3, 3))}, _plans(0, 3))
    assert [s.step_id for s in journal.pending_steps()] == [0, 1, 2]
    a = journal.begin_step(0)
    assert a == 1 and journal.step(0).status == "in_progress"
    journal.commit_step(0, a, _result(0))
    with pytest.raises(StepStateError, match="already done"):
        journal.commit_step(0, a, _result(0))
    with pytest.raises(StepStateError):
        journal.begin_step(0)
    # Stale attempt: begun twice (crash and resume), the first attempt may not commit.
    a1 = journal.begin_step(1)
    a2 = journal.begin_step(1)
    assert a2 == a1 + 1
    with pytest.raises(StepStateError, match="not the one in progress"):
        journal.commit_step(1, a1, _result(1))
    fid = journal.record_fault("force", "spike", 3.0, 1, "retry", np.ones((5, 7)))
    journal.fail_step(1, a2, "spike", fid)
    assert journal.step(1).status == "failed" and journal.step(1).fault_id == fid
    assert [s.step_id for s in journal.pending_steps()] == [1, 2]
    assert [s.step_id for s in journal.pending_steps(max_attempts=2)] == [2]
    assert [s.step_id for s in journal.pending_steps(include_failed=False)] == [2]
    journal.skip_step(2, "budget")
    assert journal.status_counts() == {"planned": 0, "in_progress": 0, "done": 1, "failed": 1, "skipped": 1}
    # Nothing duplicated: one array set, robot time counted once.
    assert journal._conn.execute("SELECT count(*) FROM step_arrays").fetchone()[0] == 6
    assert journal.robot_time_s()["probing"] == pytest.approx(1.5)
    with pytest.raises(StepStateError, match="never planned"):
        journal.begin_step(99)


def test_database_triggers_guard_done_steps(journal: Journal) -> None:
    """Even SQL that bypasses the API cannot reopen a done step or alter its data."""
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 1))
    journal.commit_step(0, journal.begin_step(0), _result(0))
    with pytest.raises(sqlite3.IntegrityError):
        journal._conn.execute("UPDATE steps SET status='planned' WHERE step_id=0")
    with pytest.raises(sqlite3.IntegrityError):
        journal._conn.execute("UPDATE step_arrays SET data=x'00' WHERE step_id=0")


def test_step_result_roundtrip(journal: Journal) -> None:
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 1))
    r = _result(5)
    r.scans_xz_mm[0, 3, 1] = np.nan
    journal.commit_step(0, journal.begin_step(0), r)
    back = journal.step_result(0)
    assert back.scans_xz_mm.dtype == np.float32 and back.scans_xz_mm.shape == (4, 32, 2)
    np.testing.assert_array_equal(back.scans_xz_mm, r.scans_xz_mm.astype(np.float32))
    np.testing.assert_array_equal(back.scan_pose, r.scan_pose)
    np.testing.assert_array_equal(back.force_direction, r.force_direction)
    assert back.summary["force_measured_n"] == 2.0 and back.robot_time_s == 1.5
    assert back.scan_t_s is None


def test_result_shapes_are_checked(journal: Journal) -> None:
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 1))
    a = journal.begin_step(0)
    bad = _result(0)
    bad.scan_pose = np.zeros((3, 6))
    with pytest.raises(ValueError, match="scan_pose"):
        journal.commit_step(0, a, bad)
    assert journal.step(0).status == "in_progress"


def test_phase_all_or_nothing_and_hash(journal: Journal) -> None:
    h = journal.commit_phase("survey", 0, {"cloud_sha256": "ab", "units": 2}, {"units": np.eye(3)}, _plans(0, 2))
    rec = journal.phase("survey", 0)
    assert rec is not None and rec.outputs_hash == h and rec.step_ids == [0, 1]
    np.testing.assert_array_equal(rec.arrays["units"], np.eye(3))
    with pytest.raises(JournalError, match="already committed"):
        journal.commit_phase("survey", 0, {}, {}, [])
    # Step ids that collide roll the whole phase back: no phase row, no arrays, no steps.
    with pytest.raises(JournalError, match="collide"):
        journal.commit_phase("densify", 1, {"x": 1}, {"u": np.ones(2)}, _plans(5, 2) + _plans(1, 1))
    assert journal.phase("densify", 1) is None
    assert journal._conn.execute("SELECT count(*) FROM steps").fetchone()[0] == 2
    assert journal._conn.execute("SELECT count(*) FROM phase_arrays").fetchone()[0] == 1
    assert journal.next_step_id() == 2
    # Tampered outputs or planned steps are detected.
    journal._conn.execute("UPDATE phases SET outputs='{\"units\":3}' WHERE name='survey'")
    with pytest.raises(JournalCorruption):
        journal.phase("survey", 0)
    with pytest.raises(ValueError):
        journal.commit_phase("bad", 0, {"x": float("nan")})
    with pytest.raises(StepStateError, match="open steps"):
        journal.complete_phase("survey", 0)


def _flip_byte_in_file(path: Path, needle: bytes) -> None:
    data = bytearray(path.read_bytes())
    pos = data.find(needle)
    assert pos >= 0, "blob bytes not found in the database file"
    assert data.find(needle, pos + 1) < 0
    data[pos + 5] ^= 0x10
    path.write_bytes(bytes(data))


def test_checksums_detect_a_flipped_byte_on_disk(tmp_path: Path) -> None:
    d = tmp_path / "s"
    j = Journal.create(d, _meta(tmp_path), min_free_bytes=0)
    j.commit_phase("survey", 0, {}, {"units": np.arange(64.0) * np.pi}, _plans(0, 2))
    r0, r1 = _result(10, n_scans=20, n_samples=128), _result(11)
    j.commit_step(0, j.begin_step(0), r0)
    j.commit_step(1, j.begin_step(1), r1)
    raw = np.random.default_rng(3).normal(size=(50, 7))
    j.record_fault("force", "spike", 1.0, 1, "retry", raw)
    j.close()                                   # checkpoints the WAL into the main file
    assert not (d / "journal.sqlite-wal").exists() or (d / "journal.sqlite-wal").stat().st_size == 0
    db = d / "journal.sqlite"
    scans = r0.scans_xz_mm.astype("<f4").tobytes()
    _flip_byte_in_file(db, scans[2000:2064])
    _flip_byte_in_file(db, (np.arange(64.0) * np.pi).astype("<f8").tobytes()[100:164])
    _flip_byte_in_file(db, raw.astype("<f8").tobytes()[:64])
    before = db.read_bytes()
    # Opening for writing (resume) checks everything first, names every damaged part and
    # writes nothing; so does a reader that asks for the full check (the default).
    for opening in (lambda: Journal.open(d, min_free_bytes=0), lambda: Journal.open_readonly(d)):
        with pytest.raises(JournalCorruption, match=r"damaged: .*phase 'survey' .*step 0 array 'scans_xz_mm'.*fault 1"):
            opening()
    assert db.read_bytes() == before
    with Journal.open_readonly(d, check="none") as j:
        # SQLite itself does not notice damage inside a blob; our checksums do.
        assert j._conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        with pytest.raises(JournalCorruption, match="step 0 array 'scans_xz_mm'"):
            j.step_result(0)
        assert j.step_result(1).scans_xz_mm.shape == (4, 32, 2)      # the sound step still reads
        with pytest.raises(JournalCorruption, match="phase 'survey'"):
            j.phase("survey", 0)
        with pytest.raises(JournalCorruption, match="fault"):
            j.faults()
        problems = j.verify()
        assert len(problems) == 3


def test_array_codec() -> None:
    for a in (np.arange(6, dtype=np.int16).reshape(2, 3), np.array([True, False]), np.zeros((0, 7)),
              np.arange(4, dtype=">f8")):
        back = decode_array(*encode_array(a), what="x")
        np.testing.assert_array_equal(back, a)
    dtype, shape, sha, data = encode_array(np.ones((2, 2), dtype=np.float32))
    with pytest.raises(JournalCorruption):
        decode_array(dtype, "[4]", sha, data, "x")      # a damaged header is caught too
    with pytest.raises(TypeError):
        encode_array(np.array(["a"]))


def test_verify_inputs(journal: Journal) -> None:
    journal.verify_inputs(PLAN, CELL.encode())
    with pytest.raises(InputsChanged, match=r"plan file changed.*line 2: 'seed: 7' -> 'seed: 8'") as exc:
        journal.verify_inputs(PLAN.replace("seed: 7", "seed: 8"), CELL)
    assert exc.value.exit_code == 2
    with pytest.raises(InputsChanged, match="cell file changed"):
        journal.verify_inputs(PLAN, CELL + "# comment\n")


def test_transitions_events_robot_time_models(journal: Journal, tmp_path: Path) -> None:
    # The journal as the engine wires it: a subscriber to the documents the machine's moves become.
    t = [0.0]
    docs = Publisher(journal.receive)
    machine = SessionMachine(lambda a, b, trig: docs.emit(TransitionDoc(a, b, trig, t[0], None)))
    machine.fire("start")
    t[0] = 2.5
    machine.fire("plan")
    machine.fire("go_to_target")
    machine.fire("fault")
    tr = journal.transitions()
    assert [(x["from_state"], x["to_state"], x["trigger"], x["t_robot_s"], x["step_id"]) for x in tr] == \
           [("idle", "preflight", "start", 0.0, None), ("preflight", "planning", "plan", 2.5, None),
            ("planning", "moving_to_standoff", "go_to_target", 2.5, None),
            ("moving_to_standoff", "fault", "fault", 2.5, None)]
    e1 = journal.log_event("note", {"msg": "hello", "value": np.float32(1.5)})
    journal.log_event("warn", {"msg": "x"}, t_robot_s=3.0)
    assert [e["kind"] for e in journal.events(after_id=e1)] == ["warn"]
    assert journal.events("note")[0]["record"] == {"msg": "hello", "value": 1.5}
    journal.add_robot_time("travel", 4.0)
    journal.add_robot_time("travel", 1.0)
    assert journal.robot_time_s() == {"travel": 5.0, "total": 5.0}
    with pytest.raises(ValueError):
        journal.add_robot_time("travel", float("nan"))
    model = journal.session_dir / "models" / "r0_m1.pt"
    model.parent.mkdir()
    model.write_bytes(b"weights")
    sha = journal.record_model(0, 1, model, {"rmse_mm": 0.1})
    assert journal.models() == [{"region": 0, "member": 1, "path": "models/r0_m1.pt", "sha256": sha,
                                 "metrics": {"rmse_mm": 0.1}}]
    journal.record_artifact("report", model)
    assert journal.verify_files() == []
    model.write_bytes(b"other weights")
    assert len(journal.verify_files()) == 2


def test_reader_never_blocks_the_writer(journal: Journal) -> None:
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 3))
    reader = Journal.open_readonly(journal.session_dir)
    try:
        reader._conn.execute("BEGIN")
        assert reader.status_counts()["planned"] == 3          # snapshot taken
        journal.commit_step(0, journal.begin_step(0), _result(0))   # no SQLITE_BUSY
        assert reader.status_counts()["done"] == 0             # a consistent snapshot
        reader._conn.execute("COMMIT")
        assert reader.status_counts()["done"] == 1
        with pytest.raises(JournalError, match="read-only"):
            reader.log_event("x")
        assert reader.summary()["steps"]["done"] == 1
    finally:
        reader.close()


def test_one_writer_per_session(tmp_path: Path, journal: Journal) -> None:
    with pytest.raises(LockHeld, match="in use by pid"):
        Journal.open(journal.session_dir, min_free_bytes=0)
    with pytest.raises(InputError, match="already holds a session journal"):
        Journal.create(journal.session_dir, _meta(tmp_path), min_free_bytes=0, lock=False)


def test_newer_schema_refused(tmp_path: Path) -> None:
    d = tmp_path / "s"
    Journal.create(d, _meta(tmp_path), min_free_bytes=0).close()
    with sqlite3.connect(d / "journal.sqlite") as c:
        c.execute("INSERT INTO schema_version VALUES (2, 'now', 'future')")
    with pytest.raises(JournalError, match="schema version 2 is newer"):
        Journal.open(d, min_free_bytes=0)
    with pytest.raises(JournalError, match="newer"):
        Journal.open_readonly(d)
    # A foreign SQLite file is not mistaken for a journal.
    other = tmp_path / "o"
    other.mkdir()
    sqlite3.connect(other / "journal.sqlite").execute("CREATE TABLE t (x)").connection.close()
    with pytest.raises(JournalCorruption, match="not an elastoprobe"):
        Journal.open(other, min_free_bytes=0)


MOUNTS = (
    "/dev/vda / ext4 rw,relatime 0 0\n"
    "server:/export {nfs} nfs4 rw,vers=4.2 0 0\n"
    "//nas/share {smb} cifs rw 0 0\n"
    "me@host:/data {sshfs} fuse.sshfs rw 0 0\n"
    "tmpfs {local} tmpfs rw 0 0\n"
)


def test_network_file_systems_refused(tmp_path: Path) -> None:
    dirs = {k: tmp_path / k for k in ("nfs", "smb", "sshfs", "local")}
    dirs["smb"] = tmp_path / "my share"                    # /proc/mounts escapes the space
    for p in dirs.values():
        p.mkdir()
    mounts = MOUNTS.format(**{k: str(v).replace(" ", "\\040") for k, v in dirs.items()})
    assert filesystem_type(dirs["nfs"] / "session", mounts) == ("nfs4", str(dirs["nfs"]))
    assert filesystem_type(dirs["smb"], mounts)[0] == "cifs"
    assert filesystem_type(dirs["local"], mounts)[0] == "tmpfs"
    # Component-wise prefix: /x/nfs-other is not inside /x/nfs.
    assert filesystem_type(tmp_path / "nfs-other", mounts)[0] == "ext4"
    for kind in ("nfs", "smb", "sshfs"):
        with pytest.raises(InputError, match="network file system"):
            check_local_filesystem(dirs[kind], mounts)
        with pytest.raises(InputError, match="network file system"):
            Journal.create(dirs[kind] / "session", _meta(tmp_path), min_free_bytes=0, mounts_text=mounts)
        assert not (dirs[kind] / "session" / "journal.sqlite").exists()
    check_local_filesystem(dirs["local"], mounts)
    Journal.create(dirs["local"] / "session", _meta(tmp_path), min_free_bytes=0, mounts_text=mounts).close()


def test_free_disk_checked(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="MiB free"):
        Journal.create(tmp_path / "s", _meta(tmp_path), min_free_bytes=2**62)
    assert not (tmp_path / "s" / "journal.sqlite").exists()


def test_from_probe_step_data(journal: Journal) -> None:
    """The probe executor's StepData goes into the journal as is, plus the averaged profile."""
    from elastoprobe.controller.probe import StepData

    rng = np.random.default_rng(2)
    forces = np.tile([0.0, 0.0, 3.0], (5, 1)) + rng.normal(0, 0.01, (5, 3))   # on the tool: push along -z
    data = StepData(step_id=0, force_target_n=3.0, angle_deg=90.0,
                    scans_xz_mm=rng.normal(size=(5, 16, 2)).astype(np.float32), scan_t_s=np.arange(5) * 0.02,
                    scan_pose=rng.normal(size=(5, 6)), scan_force_n=forces,
                    reference_xz_mm=rng.normal(size=(3, 16, 2)).astype(np.float32),
                    reference_pose=rng.normal(size=(3, 6)), robot_time_s=0.8)
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 1))
    profile = np.linspace(0, 1, 16)
    journal.commit_step(0, journal.begin_step(0), StepResult.from_step_data(data, profile, np.arange(16.0)))
    back = journal.step_result(0)
    np.testing.assert_allclose(back.force_direction, [0, 0, -1], atol=0.01)
    assert back.summary["force_measured_n"] == pytest.approx(3.0, abs=0.02)
    np.testing.assert_array_equal(back.reference_pose, data.reference_pose)
    np.testing.assert_array_equal(back.profile_depth_mm, profile)
    assert journal.robot_time_s()["probing"] == pytest.approx(0.8)


def test_fault_and_transition_queries(journal: Journal) -> None:
    journal.commit_phase("survey", 0, {}, {}, _plans(0, 2))
    block = type("Block", (), {"t_s": np.arange(3.0), "force_n": np.ones((3, 3)), "torque_nm": np.zeros((3, 3))})()
    journal.record_fault("force", "a", 1.0, 0, "retry", block)
    journal.record_fault("slip", "b", 2.0, 1, "skip_target")
    journal.record_fault("stale", "c", 3.0, 0, "retry", np.zeros((4, 7)))
    assert [f.message for f in journal.faults(step_id=0)] == ["a", "c"]
    assert all(f.raw is None for f in journal.faults(with_raw=False))
    np.testing.assert_array_equal(journal.faults()[0].raw[:, 1:4], np.ones((3, 3)))
    assert journal.faults()[0].raw[:, 0].tolist() == [0.0, 1.0, 2.0]
    for k in range(5):
        journal.record_transition("a", "b", f"t{k}", float(k))
    assert [t["trigger"] for t in journal.transitions(last=2)] == ["t3", "t4"]
    assert len(journal.transitions()) == 5


def test_salvage_tells_a_table_missing_from_the_schema_by_the_schema_not_by_the_message(tmp_path: Path) -> None:
    """A table or column the schema lacks is not damage: read_rows says so (as SQLite would) at
    once, without reading row ranges; what the schema has is read whole."""
    con = sqlite3.connect(tmp_path / "j.sqlite")
    con.execute("CREATE TABLE steps (step_id INTEGER, phase TEXT)")
    con.executemany("INSERT INTO steps VALUES (?, ?)", [(0, "sampling"), (1, "regions")])
    con.commit()
    lost: list[str] = []
    assert [r[1:] for r in read_rows(con, "steps", "step_id, phase", lost)] == [(0, "sampling"), (1, "regions")]
    with pytest.raises(sqlite3.OperationalError, match="no such column: status"):
        read_rows(con, "steps", "step_id, status", lost)
    with pytest.raises(sqlite3.OperationalError, match="no such table: faults"):
        read_rows(con, "faults", "fault_id", lost)
    assert lost == []
    con.close()
