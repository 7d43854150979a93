"""Damaged journals, read-only and full disks, dead controllers and operator requests in
every phase (issue #15, cases 4, 5, 6 and 7).

Every session runs the real CLI in a child process on the tiny plan (tests/data/session/
tiny.yaml) with a private copy of the simulated cell. The contract checked: exit 2 with a
message naming what is damaged or which path cannot be written, never a traceback; a
finished session's status is never rewritten because of damage; read-only commands never
write to a journal; a pause or stop is honoured in the phase in progress and ``resume``
continues from there to the end.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest

from test_session_util import CLI, plan_for, run_cli, start_or_resume

from elastoprobe.controller.cli import main
from elastoprobe.controller.journal import Journal

REPO = Path(__file__).resolve().parent.parent
SIM_CELL = REPO / "config" / "cells" / "sim.yaml"
SEED = 2
READ_COMMANDS = (["status"], ["report"], ["export", "--format", "hdf5"], ["evaluate"], ["train"])


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _sql(session: Path, query: str, immutable: bool = False) -> list[tuple]:
    """Plain SQLite, read-only (no elastoprobe code between the test and the file);
    ``immutable`` for a finished session on a disk where SQLite cannot make its index file."""
    uri = f"file:{session / 'journal.sqlite'}?mode=ro" + ("&immutable=1" if immutable else "")
    con = sqlite3.connect(uri, uri=True, timeout=10.0)
    try:
        return con.execute(query).fetchall()
    finally:
        con.close()


def _status(session: Path, immutable: bool = False) -> tuple[str, str | None]:
    return _sql(session, "SELECT status, status_reason FROM session", immutable)[0]


def _phases(session: Path) -> set[tuple[str, int]]:
    return set(_sql(session, "SELECT name, round FROM phases"))


@pytest.fixture
def setup(tiny_session: dict) -> dict:
    return tiny_session


@pytest.fixture
def finished(tiny_session: dict) -> Path:
    """A finished tiny session (never modified: tests work on copies)."""
    return tiny_session["finished"]


def _copy(finished: Path, dst: Path) -> Path:
    shutil.copytree(finished, dst)
    return dst


# ----------------------------------------------------------------------------- case 4
def _blob_offset(journal: Path, step_id: int, name: str) -> int:
    """Where a done step's array bytes lie in the journal file."""
    con = sqlite3.connect(f"file:{journal}?mode=ro", uri=True)
    try:
        data = con.execute("SELECT data FROM step_arrays WHERE step_id=? AND name=?", (step_id, name)).fetchone()[0]
    finally:
        con.close()
    raw = journal.read_bytes()
    for start in range(len(data) // 2, len(data) - 64, 64):     # bytes found only there (not NaN runs)
        probe = bytes(data[start:start + 64])
        if raw.count(probe) == 1:
            return raw.find(probe)
    raise AssertionError("no unique stretch in the array")


def _table_page_offset(journal: Path, table: str) -> int:
    con = sqlite3.connect(f"file:{journal}?mode=ro", uri=True)
    try:
        page_size = con.execute("PRAGMA page_size").fetchone()[0]
        root = con.execute("SELECT rootpage FROM sqlite_master WHERE name=?", (table,)).fetchone()[0]
    finally:
        con.close()
    return (root - 1) * page_size


def _damage(journal: Path, offset: int, n: int, seed: int) -> None:
    rng = __import__("random").Random(seed)
    with open(journal, "r+b") as f:
        f.seek(offset)
        f.write(bytes(rng.randrange(256) for _ in range(n)))


DAMAGE = {
    # label: (where, bytes)
    "20 bytes in a step's scans": ("blob", 20),
    "300 bytes over the steps table's root page": ("steps", 300),
    "300 bytes over the session table's page": ("session", 300),
    "300 bytes over the phase arrays": ("phase_arrays", 300),
}


def _damaged_copy(finished: Path, dst: Path, label: str) -> Path:
    session = _copy(finished, dst)
    journal = session / "journal.sqlite"
    where, n = DAMAGE[label]
    offset = _blob_offset(journal, 1, "scans_xz_mm") if where == "blob" else _table_page_offset(journal, where) + 8
    _damage(journal, offset, n, seed=len(label))
    return session


@pytest.mark.parametrize("label", sorted(DAMAGE))
def test_case4_a_damaged_journal_is_named_never_rewritten(label: str, finished: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    session = _damaged_copy(finished, tmp_path / "s", label)
    journal = session / "journal.sqlite"
    before = _sha(journal)
    for args in READ_COMMANDS + (["resume", "--quiet"],):
        code = main([args[0], str(session), *args[1:]])       # in-process: a traceback fails the test
        captured = capsys.readouterr()
        assert code == 2, (args, code, captured.err[-2000:], captured.out[-2000:])
        text = captured.err + captured.out
        assert "damaged" in text and "elastoprobe salvage" in text, (args, text[-2000:])
        # Never written to: not by a read-only command, not by a refused resume.
        assert _sha(journal) == before, args


def test_case4_salvage_keeps_every_intact_step_and_resume_finishes(finished: Path, setup: dict,
                                                                   tmp_path: Path) -> None:
    session = _damaged_copy(finished, tmp_path / "s", "20 bytes in a step's scans")
    new = tmp_path / "salvaged"
    child = run_cli(["salvage", str(session), "--out", str(new)], setup["env"])
    assert child.returncode == 0, child.stderr[-3000:]
    assert "step 1" in child.stdout
    done_before = {r[0] for r in _sql(finished, "SELECT step_id FROM steps WHERE status='done'")}
    with Journal.open_readonly(new) as j:              # sound: a full check passes
        assert j.verify() == []
        done_now = {r.step_id for r in j.steps(statuses=["done"])}
        status, reason = j.session()["status"], j.session()["status_reason"]
    assert done_now == done_before - {1}
    assert status == "paused" and "salvage" in reason
    resumed = run_cli(["resume", str(new), "--quiet"], setup["env"])
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    with Journal.open_readonly(new) as j:
        assert {r.step_id for r in j.steps(statuses=["done"])} == done_before
        assert j.session()["status"] == "done"


def test_a_damaged_model_file_is_not_served(finished: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    session = _copy(finished, tmp_path / "s")
    model = sorted((session / "models").rglob("region*.npz"))[0]
    region = model.stem.removeprefix("region")
    model.write_bytes(os.urandom(300))
    assert main(["predict", str(session), "--region", region, "--force", "5", "--angle", "90"]) == 2
    err = capsys.readouterr().err
    assert f"{model}: " in err and "Traceback" not in err, err


# ----------------------------------------------------------------------------- case 5
@pytest.fixture()
def read_only_dir(tmp_path: Path) -> Iterator[tuple[Path, callable]]:
    """A directory to fill, then made read-only: a read-only tmpfs when this process may
    mount (root), else permissions (EACCES instead of EROFS: the same path through the code)."""
    d = tmp_path / "ro"
    d.mkdir()
    mounted = False
    if os.geteuid() == 0 and shutil.which("mount"):
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(d)],
                                 capture_output=True).returncode == 0

    def seal() -> None:
        if mounted:
            subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        else:
            for root, dirs, files in os.walk(d):
                for name in dirs + files:
                    os.chmod(os.path.join(root, name), 0o555)
            os.chmod(d, 0o555)

    yield d, seal
    if mounted:
        subprocess.run(["umount", str(d)], check=False)
    else:
        for root, dirs, _ in os.walk(d):
            os.chmod(root, 0o755)


def test_case5_read_only_disk_is_bad_input_naming_the_path(finished: Path, setup: dict,
                                                           read_only_dir: tuple[Path, callable]) -> None:
    d, seal = read_only_dir
    if os.geteuid() == 0 and not Path("/proc/mounts").read_text().count(str(d)):
        pytest.skip("running as root without mount: permissions do not stop root")
    session = _copy(finished, d / "s")
    seal()
    before = _sha(session / "journal.sqlite")
    runs = {
        "run": ["run", str(setup["plan"]), "--out", str(d / "new"), "--quiet"],
        "resume": ["resume", str(session), "--quiet"],
        "report": ["report", str(session)],
        "export": ["export", str(session), "--format", "hdf5"],
        "train": ["train", str(session)],
    }
    for what, args in runs.items():
        child = run_cli(args, setup["env"])
        assert "Traceback" not in child.stderr, (what, child.stderr[-3000:])
        assert child.returncode == 2, (what, child.returncode, child.stderr[-2000:])
        assert str(d) in child.stderr, (what, child.stderr[-2000:])
    # Reading still works on a read-only disk.
    for args in (["status", str(session)], ["evaluate", str(session), "--json"]):
        child = run_cli(args, setup["env"])
        assert child.returncode == 0, (args, child.stderr[-2000:])
    assert _sha(session / "journal.sqlite") == before


def test_case5_out_pointing_at_a_file_is_bad_input(setup: dict, tmp_path: Path) -> None:
    target = tmp_path / "a_file"
    target.write_text("not a directory\n")
    child = run_cli(["run", str(setup["plan"]), "--out", str(target), "--quiet"], setup["env"])
    assert child.returncode == 2, child.stderr[-2000:]
    assert "Traceback" not in child.stderr and f"{target}: " in child.stderr
    assert target.read_text() == "not a directory\n"


def test_case5_a_full_disk_is_a_message_naming_the_path(finished: Path, setup: dict, tmp_path: Path) -> None:
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("needs a small tmpfs (root)")
    d = tmp_path / "full"
    d.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(d)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        session = _copy(finished, d / "s")
        (d / "filler").write_bytes(b"\0" * (os.statvfs(d).f_bavail * os.statvfs(d).f_frsize - 4096))
        for args in (["report", str(session)], ["export", str(session), "--format", "hdf5"]):
            child = run_cli(args, setup["env"])
            assert "Traceback" not in child.stderr, (args, child.stderr[-3000:])
            assert child.returncode == 2 and str(session) in child.stderr, (args, child.stderr[-2000:])
            assert "full" in child.stderr, (args, child.stderr[-2000:])
        assert _status(session, immutable=True)[0] == "done"
    finally:
        subprocess.run(["umount", str(d)], check=False)


# ----------------------------------------------------------------------------- case 6
def _wait_for_state(session: Path, proc: subprocess.Popen, states: set[str], timeout_s: float = 300.0) -> str:
    """Poll the journal (read-only) until the controller's last transition enters one of ``states``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the controller ended ({proc.returncode}) before reaching {states}"
        if (session / "journal.sqlite").exists():
            try:
                last = _sql(session, "SELECT to_state FROM transitions ORDER BY id DESC LIMIT 1")
            except sqlite3.Error:   # being created: poll again
                last = []
            if last and last[0][0] in states:
                return last[0][0]
        time.sleep(0.05)
    raise AssertionError(f"never reached {states}")


def _start(setup: dict, out: Path, plan: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["run", str(plan or setup["plan"]), "--out", str(out), "--seed", str(SEED),
                                   "--quiet"], env=setup["env"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def test_case6_status_after_kill9_says_the_controller_is_gone(setup: dict, tmp_path: Path) -> None:
    out = tmp_path / "s"
    proc = _start(setup, out)
    _wait_for_state(out, proc, {"probing", "contact", "loading", "scanning", "at_standoff", "moving"})
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    child = run_cli(["status", str(out)], setup["env"])
    assert child.returncode == 0, child.stderr
    assert f"running as pid {proc.pid}" not in child.stdout
    assert str(proc.pid) in child.stdout and "not running" in child.stdout
    assert f"elastoprobe resume {out}" in child.stdout
    snap = json.loads(run_cli(["status", str(out), "--json"], setup["env"]).stdout)
    assert snap["running_pid"] is None and snap["controller"]["alive"] is False
    # A lock record naming a live process that does not hold the lock (pid reused) is not "running".
    (out / "session.lock").write_text(json.dumps({"pid": os.getpid(), "host": os.uname().nodename,
                                                  "started_utc": "2000-01-01T00:00:00+00:00"}))
    snap = json.loads(run_cli(["status", str(out), "--json"], setup["env"]).stdout)
    assert snap["running_pid"] is None
    # status --follow of a dead controller ends at once instead of waiting for ever.
    follow = run_cli(["status", str(out), "--follow"], setup["env"])
    assert follow.returncode == 0
    # pause/stop name the dead controller instead of signalling whatever has its pid now.
    refused = run_cli(["pause", str(out)], setup["env"])
    assert refused.returncode == 2 and "not running" in refused.stderr, refused.stderr


# ----------------------------------------------------------------------------- case 7
# About ten seconds of learning per models phase (a few seconds for the tiny plan's own):
# time for a request to land while the learning phase runs. Only the learning cases need it.
LONG_LEARNING = {"ensemble: 2": "ensemble: 3", "max_epochs: 100": "max_epochs: 2000"}
# Every case resumes to the end; the densify round (a survey and a models phase more) adds
# nothing to what a request in these phases checks.
NO_DENSIFY = {"    rounds: 1\n": "    rounds: 0\n"}
PHASE_STATES = {
    "sweeping": {"sweeping"},
    "planning": {"planning"},
    "probing": {"contact", "loading", "scanning"},
    "learning": {"learning"},
}
REQUESTS = {
    "SIGINT": lambda pid, out: os.kill(pid, signal.SIGINT),
    "SIGTERM": lambda pid, out: os.kill(pid, signal.SIGTERM),
    "SIGINT twice": lambda pid, out: (os.kill(pid, signal.SIGINT), time.sleep(0.3), os.kill(pid, signal.SIGINT)),
    "elastoprobe stop": lambda pid, out: subprocess.run(CLI + ["stop", str(out)], check=True, capture_output=True),
    "elastoprobe pause": lambda pid, out: subprocess.run(CLI + ["pause", str(out)], check=True, capture_output=True),
}
STOPS = {"SIGINT twice", "elastoprobe stop"}


# By default: the cases in the learning phase, and a pause while sweeping; every
# request in every phase with -m slow (each case is a session of about a minute).
DEFAULT_CASES = {("learning", "SIGINT twice"), ("sweeping", "SIGINT")}
CASES = [(p, r) for p in PHASE_STATES for r in REQUESTS]


@pytest.mark.parametrize("phase,request_", [c if c in DEFAULT_CASES else pytest.param(*c, marks=pytest.mark.slow)
                                            for c in CASES])
@pytest.mark.timeout(900)
def test_case7_pause_and_stop_are_honoured_in_every_phase(phase: str, request_: str, setup: dict,
                                                          tmp_path: Path) -> None:
    edits = {**NO_DENSIFY, **(LONG_LEARNING if phase == "learning" else {})}
    plan = plan_for(setup["cell"], tmp_path, edits=edits)
    out = tmp_path / "s"
    proc = _start(setup, out, plan)
    # The learning phase after the survey's regions: the models are planned there.
    _wait_for_state(out, proc, PHASE_STATES[phase])
    phases_before = _phases(out)
    REQUESTS[request_](proc.pid, out)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 3, (proc.returncode, stderr[-3000:])
    assert "Traceback" not in stderr
    status, reason = _status(out)
    assert status == "paused"
    assert ("stop" in reason) if request_ in STOPS else ("pause" in reason), reason
    phases_after = _phases(out)
    if phase == "learning":
        # Interrupted in the learning phase itself: its models were not committed.
        assert ("models", 0) not in phases_after
    if phase == "sweeping":
        assert phases_after == phases_before          # the sweep was left; its cloud is not committed
    if phase in ("sweeping", "planning"):
        assert _sql(out, "SELECT count(*) FROM steps WHERE status='done'")[0][0] == 0
    resumed = start_or_resume(plan, out, SEED, setup["env"])
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert _status(out)[0] == "done"


# ----------------------------------------------------------------------------- a second sweep
# Cases a later hostile sweep found (journals from another schema version, outputs aimed at a
# session's own files, sessions made inside another session's directory).
def _set_schema_version(session: Path, version: object) -> None:
    con = sqlite3.connect(session / "journal.sqlite")
    try:
        con.execute("UPDATE schema_version SET version=?", (version,))
        con.commit()
    finally:
        con.close()


@pytest.mark.parametrize("version,text", [(99, "newer than this elastoprobe"), (0, "not one any elastoprobe wrote"),
                                          ("one", "not one any elastoprobe wrote")])
def test_a_journal_of_another_schema_version_is_bad_input_and_left_alone(
        version: object, text: str, finished: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Version 99 was exit 1 (a fault) and salvage copied it into this release's schema;
    version 0 was read and resumed as if current; 'one' was a ValueError traceback. A version
    no release wrote is damage (salvage recovers the rest); a newer one is not salvaged here."""
    session = _copy(finished, tmp_path / "s")
    _set_schema_version(session, version)
    before = _sha(session / "journal.sqlite")
    newer = version == 99
    for args in READ_COMMANDS + (["resume", "--quiet"],) + ((["salvage", "--out", str(tmp_path / "new")],) if newer else ()):
        code = main([args[0], str(session), *args[1:]])
        err = capsys.readouterr().err
        assert code == 2, (args, code, err[-2000:])
        assert text in err and "Traceback" not in err, (args, err[-2000:])
        assert ("elastoprobe salvage" in err) is not newer, err
    assert _sha(session / "journal.sqlite") == before
    if newer:
        assert not (tmp_path / "new" / "journal.sqlite").exists()
    else:
        assert main(["salvage", str(session), "--out", str(tmp_path / "new")]) == 0
        with Journal.open_readonly(tmp_path / "new") as j:
            assert j.verify() == []


@pytest.mark.parametrize("command", ["export", "diagram", "calibrate"])
@pytest.mark.parametrize("target", ["journal.sqlite", "log.jsonl", "models/round0/region0.npz", "a copy of the journal"])
def test_an_output_never_replaces_a_sessions_stored_data(command: str, target: str, finished: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """``export --out DIR/journal.sqlite`` replaced the session's journal with an HDF5 file (exit 0),
    and ``diagram --out`` did the same with Markdown."""
    session = _copy(finished, tmp_path / "s")
    if target == "a copy of the journal":
        path = tmp_path / "backup.db"
        shutil.copyfile(session / "journal.sqlite", path)
    else:
        path = session / target
    before = _sha(path)
    argv = {"export": ["export", str(session), "--format", "hdf5", "--out", str(path)],
            "diagram": ["diagram", "--out", str(path)],
            "calibrate": ["calibrate", "ft", "--out", str(path)]}[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{path}: " in err and "stored data" in err and "Traceback" not in err, err
    assert _sha(path) == before


def test_export_still_writes_beside_the_session_and_over_its_own_file(finished: Path, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    session = _copy(finished, tmp_path / "s")
    assert main(["export", str(session), "--format", "hdf5"]) == 0
    assert (session / "export.h5").is_file()
    out = tmp_path / "x.h5"
    for _ in range(2):
        assert main(["export", str(session), "--format", "hdf5", "--out", str(out)]) == 0
    assert out.is_file()


@pytest.mark.parametrize("inside", ["models", "a/b"])
def test_no_session_is_made_inside_another_sessions_directory(inside: str, finished: Path, setup: dict,
                                                              tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``run --out DIR/models`` ran a whole session inside a finished one's model folder."""
    session = _copy(finished, tmp_path / "s")
    before = _sha(session / "journal.sqlite")
    listing = sorted(p.relative_to(session) for p in session.rglob("*"))
    for argv in (["run", str(setup["plan"]), "--out", str(session / inside), "--quiet"],
                 ["salvage", str(session), "--out", str(session / inside)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"{session / inside}: lies inside the session directory {session}" in err, err
    assert _sha(session / "journal.sqlite") == before
    assert sorted(p.relative_to(session) for p in session.rglob("*")) == listing


def test_a_session_in_a_folder_whose_name_is_not_utf8(finished: Path, setup: dict, tmp_path: Path) -> None:
    """``run --out $'out\\xff'`` measured the whole session, then its report's read-only open
    (a SQLite URI quoted as text) raised UnicodeEncodeError: the finished session was recorded
    as a fault, and ``status`` and ``report`` on it were tracebacks. The name prints as its bytes."""
    raw = os.path.join(os.fsencode(tmp_path), b"out\xff")
    session = Path(os.fsdecode(raw))
    _copy(finished, session)
    before = _sha(session / "journal.sqlite")
    for args in READ_COMMANDS:
        child = subprocess.run(CLI + [args[0], raw, *args[1:]], env=setup["env"], capture_output=True, timeout=600)
        assert child.returncode == 0, (args, child.returncode, child.stderr[-2000:])
        assert b"Traceback" not in child.stderr
    assert raw in subprocess.run(CLI + ["status", raw], env=setup["env"], capture_output=True, timeout=600).stdout
    new = tmp_path / "new"
    assert subprocess.run(CLI + ["salvage", raw, "--out", str(new)], env=setup["env"], capture_output=True,
                          timeout=600).returncode == 0
    assert _status(new) == _status(finished)
    assert _sha(session / "journal.sqlite") == before


def test_a_resume_refused_for_an_edited_plan_writes_nothing(setup: dict, tmp_path: Path) -> None:
    """The refusal came after the session had opened the journal to write: a run record was
    added and the write-ahead log checkpointed into the file by a resume that did nothing."""
    plan = plan_for(setup["cell"], tmp_path)
    out = tmp_path / "s"
    proc = _start(setup, out, plan)
    _wait_for_state(out, proc, {"sweeping", "planning", "probing", "contact", "loading", "scanning", "moving"})
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    plan.write_text(plan.read_text().replace("scans_per_step: 5", "scans_per_step: 6"))
    stored = ("journal.sqlite", "journal.sqlite-wal")      # (readers share the -shm index)
    files = {name: _sha(out / name) for name in stored if (out / name).exists()}
    child = run_cli(["resume", str(out), "--quiet"], setup["env"])
    assert child.returncode == 2, child.stderr[-2000:]
    assert "the plan file changed since this session started" in child.stderr and "Traceback" not in child.stderr
    assert {name: _sha(out / name) for name in stored if (out / name).exists()} == files
