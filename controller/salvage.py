"""``elastoprobe salvage DIR --out NEW``: every intact part of a damaged journal, in a new one.

A damaged journal is never written to (controller/journal.py refuses to resume it). The
salvage reads it row by row, around whatever SQLite or a checksum finds damaged, and
builds a new journal in ``NEW`` from which ``resume`` continues:

- phases, in commit order, as long as each one verifies (its outputs, arrays and planned
  steps match its hash); from the first damaged one on, phases are dropped together with
  the steps they planned — resume computes them again from the intact ones before;
- the steps of the kept phases: a done step whose arrays and summary verify stays done
  with its data; a done step with damaged data is planned again (resume measures it
  anew); the others keep their state;
- faults (a raw F/T blob that fails its checksum is left out, the fault kept), runs,
  transitions, events, robot time, provenance, models and artifacts whose files are
  intact (their files are copied).

The new session is ``paused`` (reason: what was lost) when anything must be measured or
computed again, else it keeps the old status.
"""
from __future__ import annotations

import json
import os
import shutil
import sqlite3
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from .core.atomic import ensure_dir
from .core.errors import InputError
from .journal import (JOURNAL_NAME, SCHEMA_VERSION, STEP_ARRAYS_REQUIRED, Journal, JournalVersionError, SessionMeta,
                      _array_digest, _phase_digest, refuse_nested_session,
                      _plan_from_row, _STEP_PLAN_COLS)
from .locking import SessionLock, session_lock_holder
from .provenance import sha256_file

Row = tuple[Any, ...]


@dataclass
class SalvageReport:
    """What a salvage kept and what resume will redo."""

    phases_kept: list[str] = field(default_factory=list)
    phases_dropped: list[str] = field(default_factory=list)     # "name[round]: why"
    steps_done: int = 0
    steps_remeasure: list[str] = field(default_factory=list)    # "step k: why"
    steps_dropped: int = 0
    lost: list[str] = field(default_factory=list)               # other records left out
    files_copied: int = 0
    status: str = ""
    status_reason: str | None = None

    def lines(self, new_dir: Path) -> list[str]:
        out = [f"phases kept: {', '.join(self.phases_kept) or 'none'}"]
        out += [f"phase dropped (resume computes it again): {p}" for p in self.phases_dropped]
        out.append(f"steps kept done: {self.steps_done}")
        out += [f"to measure again: {s}" for s in self.steps_remeasure]
        if self.steps_dropped:
            out.append(f"steps dropped with their phases: {self.steps_dropped}")
        out += [f"left out: {what}" for what in self.lost]
        out.append(f"model and artifact files copied: {self.files_copied}")
        out.append(f"new session {new_dir}: {self.status}" + (f" ({self.status_reason})" if self.status_reason else ""))
        if self.status != "done":
            out.append(f"continue with: elastoprobe resume {new_dir}")
        return out


# ----------------------------------------------------------------------------- robust reads
def _connect(path: Path) -> sqlite3.Connection:
    uri = "file:" + urllib.parse.quote(os.fsencode(path)) + "?mode=ro&immutable=1"
    return sqlite3.connect(uri, uri=True, isolation_level=None)


def read_rows(con: sqlite3.Connection, table: str, columns: str, lost: list[str]) -> list[Row]:
    """Every readable row of ``table`` (``columns``, rowid first), in rowid order.

    The whole table in one read when it can; else rowid ranges, halved around the
    damage down to single rows, so one damaged page loses only the rows on it."""
    missing = _missing_from_schema(con, table, columns)
    if missing is not None:             # not damage: nothing of it to read, row by row or at once
        raise sqlite3.OperationalError(missing)
    sql = f"SELECT rowid, {columns} FROM {table}"
    try:
        return con.execute(sql + " ORDER BY rowid").fetchall()
    except sqlite3.DatabaseError:
        pass
    try:
        top = int(con.execute(f"SELECT max(rowid) FROM {table}").fetchone()[0] or 0)
    except sqlite3.DatabaseError:
        top = int(con.execute("PRAGMA page_count").fetchone()[0]) * 100   # more rows than pages can hold
    out: list[Row] = []
    bad = 0
    pending = [(1, top)]
    while pending:
        lo, hi = pending.pop()
        if lo > hi:
            continue
        try:
            out.extend(con.execute(sql + " WHERE rowid BETWEEN ? AND ?", (lo, hi)).fetchall())
        except sqlite3.DatabaseError:
            if lo == hi:
                bad += 1
            else:
                mid = (lo + hi) // 2
                pending += [(mid + 1, hi), (lo, mid)]
    if bad:
        lost.append(f"{bad} unreadable {table} rows")
    return sorted(out, key=lambda r: r[0])


def _missing_from_schema(con: sqlite3.Connection, table: str, columns: str) -> str | None:
    """What the schema lacks of ``table`` and its ``columns`` (plain names, comma-separated),
    said as SQLite says it; None when all are there, or when the schema itself cannot be read
    (then the rows are read as damaged ones are)."""
    try:
        have = {row[1] for row in con.execute(f"PRAGMA table_info({table})").fetchall()}
    except sqlite3.DatabaseError:
        return None
    if not have:
        return f"no such table: {table}"
    missing = [c.strip() for c in columns.split(",") if c.strip() not in have]
    return f"no such column: {', '.join(missing)}" if missing else None


_BAD = object()     # a JSON column that does not parse


def _loads(text: Any) -> Any:
    try:
        return json.loads(text)
    except (TypeError, ValueError):
        return _BAD


def _blob_ok(dtype: Any, shape: Any, sha: Any, data: Any) -> bool:
    try:
        return data is not None and _array_digest(dtype, shape, bytes(data)) == sha
    except (TypeError, UnicodeEncodeError):
        return False


# ----------------------------------------------------------------------------- the salvage
def salvage(src_dir: Path, out_dir: Path) -> SalvageReport:
    """Copy every intact part of ``src_dir``'s journal into a new session in ``out_dir``."""
    src = Path(src_dir) / JOURNAL_NAME
    if not src.exists():
        raise InputError("no session journal here (expected journal.sqlite)", path=str(src_dir))
    holder = session_lock_holder(src_dir)
    if holder and holder.get("alive"):
        raise InputError(f"the session is running (pid {holder.get('pid')}); stop it first "
                         f"(elastoprobe stop {src_dir})", path=str(src_dir))
    refuse_nested_session(out_dir)
    out = ensure_dir(out_dir)
    if (out / JOURNAL_NAME).exists():
        raise InputError("already holds a session journal; choose an empty --out", path=str(out))
    try:
        con = _connect(src)
        con.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"nothing can be salvaged: SQLite cannot read the file at all ({exc})",
                         path=str(src)) from None
    report = SalvageReport()
    try:
        _refuse_newer_schema(con, src)
        tables = _read_all(con, report.lost)
    finally:
        con.close()
    prov = {r[0]: _loads(r[1]) for r in tables["provenance"]}
    if not isinstance(prov.get("plan"), dict) or not isinstance(prov.get("cell"), dict):
        raise InputError("nothing can be salvaged to resume from: the journal's plan and cell provenance "
                         "are damaged", path=str(src))
    fill = _Filler(tables, report, Path(src_dir), out)
    with SessionLock(out):
        session = fill.session_row()
        Journal._build(out, SessionMeta(plan_name=session[2], seed=int(session[3])), fill)
    return report


def _refuse_newer_schema(con: sqlite3.Connection, src: Path) -> None:
    """A journal a newer elastoprobe wrote is not damaged: its rows mean what that release says,
    so it is not copied into this release's schema (an unreadable version is salvaged as damage)."""
    try:
        version = con.execute("SELECT max(version) FROM schema_version").fetchone()[0]
    except sqlite3.DatabaseError:
        return
    if isinstance(version, int) and version > SCHEMA_VERSION:
        raise JournalVersionError(f"{src}: journal schema version {version} is newer than this elastoprobe "
                                  f"understands ({SCHEMA_VERSION}); salvage it with the release that wrote it")


TABLES = {
    "session": "id, created_utc, plan_name, seed, status, status_utc, status_reason",
    "provenance": "key, value, recorded_utc",
    "runs": "run_id, mode, started_utc, pid, host, ended_utc, end_status",
    "phases": "phase_id, name, round, status, outputs, outputs_hash, n_steps, committed_utc, completed_utc, run_id",
    "phase_arrays": "phase_id, name, dtype, shape, sha256, data",
    "steps": (f"{_STEP_PLAN_COLS}, phase_id, phase, round, status, attempts, started_utc, finished_utc, run_id, "
              f"summary, fail_reason, fault_id"),
    "step_arrays": "step_id, name, dtype, shape, sha256, data",
    "transitions": "id, run_id, t_robot_s, t_wall_utc, from_state, to_state, trigger, step_id",
    "faults": ("fault_id, run_id, kind, t_robot_s, t_wall_utc, step_id, message, policy_action, raw_dtype, "
               "raw_shape, raw_sha256, raw"),
    "events": "id, run_id, t_wall_utc, t_robot_s, kind, record",
    "robot_time": "category, seconds",
    "models": "region, member, path, sha256, metrics, recorded_utc",
    "artifacts": "name, path, sha256, recorded_utc",
}


def _read_all(con: sqlite3.Connection, lost: list[str]) -> dict[str, list[Row]]:
    out: dict[str, list[Row]] = {}
    for table, columns in TABLES.items():
        try:
            out[table] = [r[1:] for r in read_rows(con, table, columns, lost)]
        except sqlite3.DatabaseError as exc:       # the table itself is gone from the schema
            lost.append(f"table {table} ({exc})")
            out[table] = []
    return out


class _Filler:
    """Decides what is intact and writes it into the new journal (inside its build transaction)."""

    N_PLAN = len(_STEP_PLAN_COLS.split(","))

    def __init__(self, tables: dict[str, list[Row]], report: SalvageReport, src_dir: Path, out_dir: Path) -> None:
        self.t = tables
        self.report = report
        self.src_dir = src_dir
        self.out_dir = out_dir

    def session_row(self) -> Row:
        rows = [r for r in self.t["session"] if r[0] == 1]
        if rows and isinstance(rows[0][1], str) and isinstance(rows[0][2], str) and isinstance(rows[0][3], int):
            return rows[0]
        prov = {r[0]: _loads(r[1]) for r in self.t["provenance"]}
        seed = prov.get("seed")
        if not isinstance(seed, int):
            raise InputError("nothing can be salvaged to resume from: the session record and the seed in its "
                             "provenance are damaged", path=str(self.src_dir / JOURNAL_NAME))
        self.report.lost.append("the session record (rebuilt from the provenance)")
        name = str((prov.get("plan") or {}).get("name") or "salvaged")
        return (1, None, name, seed, "paused", None, None)

    def __call__(self, c: sqlite3.Connection) -> None:
        self._provenance(c)
        run_ids = self._runs(c)
        kept_phases = self._phases(c, run_ids)
        kept_steps, remeasure = self._steps(c, kept_phases, run_ids)
        self._faults(c, kept_steps, run_ids)
        self._rest(c, kept_steps, run_ids)
        self._files(c)
        self._status(c, remeasure)

    def _provenance(self, c: sqlite3.Connection) -> None:
        c.execute("DELETE FROM provenance")
        for key, value, recorded in self.t["provenance"]:
            if _loads(value) is _BAD:
                self.report.lost.append(f"provenance {key!r}")
                continue
            c.execute("INSERT INTO provenance VALUES (?,?,?)", (key, value, recorded))

    def _runs(self, c: sqlite3.Connection) -> set[int]:
        ids = set()
        for r in self.t["runs"]:
            if r[1] in ("create", "resume") and isinstance(r[0], int) and isinstance(r[3], int):
                c.execute("INSERT INTO runs VALUES (?,?,?,?,?,?,?)", r)
                ids.add(r[0])
        return ids

    def _phases(self, c: sqlite3.Connection, run_ids: set[int]) -> set[int]:
        arrays: dict[int, list[Row]] = {}
        for a in self.t["phase_arrays"]:
            arrays.setdefault(a[0], []).append(a)
        steps_by_phase: dict[int, list[Row]] = {}
        for s in self.t["steps"]:
            steps_by_phase.setdefault(s[self.N_PLAN], []).append(s)
        kept: set[int] = set()
        broken = None
        for p in sorted(self.t["phases"], key=lambda r: r[0]):
            label = f"{p[1]}[{p[2]}]"
            if broken is None:
                broken = self._phase_problem(p, arrays.get(p[0], []), steps_by_phase.get(p[0], []))
                if broken is None:
                    c.execute("INSERT INTO phases VALUES (?,?,?,?,?,?,?,?,?,?)",
                              (*p[:9], p[9] if p[9] in run_ids else None))
                    c.executemany("INSERT INTO phase_arrays VALUES (?,?,?,?,?,?)", arrays.get(p[0], []))
                    kept.add(p[0])
                    self.report.phases_kept.append(label)
                    continue
                self.report.phases_dropped.append(f"{label}: {broken}")
            else:
                self.report.phases_dropped.append(f"{label}: after the damaged one")
        return kept

    def _phase_problem(self, p: Row, arrays: list[Row], steps: list[Row]) -> str | None:
        sums = {}
        for a in arrays:
            if not _blob_ok(*a[2:6]):
                return f"array {a[1]!r} fails its checksum"
            sums[a[1]] = a[4]
        try:
            planned = [_plan_from_row(s[:self.N_PLAN]).canonical() for s in steps]
        except (TypeError, ValueError):
            return "a planned step is damaged"
        if len(planned) != p[6] or _phase_digest(p[4], sums, planned) != p[5]:
            return "outputs or planned steps do not match the phase's hash"
        return None

    def _steps(self, c: sqlite3.Connection, kept_phases: set[int],
               run_ids: set[int]) -> tuple[set[int], list[int]]:
        arrays: dict[int, list[Row]] = {}
        for a in self.t["step_arrays"]:
            arrays.setdefault(a[0], []).append(a)
        n = self.N_PLAN
        kept, remeasure = set(), []
        cols = ("step_id, target_index, px, py, pz, nx, ny, nz, tx, ty, tz, angle_deg, force_n, order_index, "
                "phase_id, phase, round, status, attempts, started_utc, finished_utc, run_id, summary, fail_reason, "
                "fault_id")
        for s in self.t["steps"]:
            if s[n] not in kept_phases:
                self.report.steps_dropped += 1
                continue
            row = list(s)
            row[n + 7] = s[n + 7] if s[n + 7] in run_ids else None
            row[n + 10] = None                 # fault ids are linked again below, once the faults are in
            status = s[n + 3]
            why = self._done_problem(s, arrays.get(s[0], [])) if status == "done" else None
            if status == "done" and why is None:
                row[n + 3], row[n + 8] = "in_progress", None
                c.execute(f"INSERT INTO steps ({cols}) VALUES ({','.join('?' * len(row))})", row)
                c.executemany("INSERT INTO step_arrays VALUES (?,?,?,?,?,?)", arrays[s[0]])
                c.execute("UPDATE steps SET status='done', summary=? WHERE step_id=?", (s[n + 8], s[0]))
                self.report.steps_done += 1
            else:
                if why is not None:
                    row[n + 3], row[n + 5], row[n + 6], row[n + 8] = "planned", None, None, None
                    row[n + 9] = f"salvaged: {why}"
                    remeasure.append(s[0])
                    self.report.steps_remeasure.append(f"step {s[0]}: {why}")
                elif status not in ("planned", "in_progress", "failed", "skipped"):
                    row[n + 3], row[n + 8] = "planned", None
                c.execute(f"INSERT INTO steps ({cols}) VALUES ({','.join('?' * len(row))})", row)
            kept.add(s[0])
        return kept, remeasure

    @staticmethod
    def _done_problem(s: Row, arrays: list[Row]) -> str | None:
        summary = _loads(s[len(_STEP_PLAN_COLS.split(",")) + 8])
        if not isinstance(summary, dict):
            return "its summary is damaged"
        listed = summary.get("arrays") or {}
        have = {a[1]: a for a in arrays}
        for name in set(listed) | set(STEP_ARRAYS_REQUIRED):
            a = have.get(name)
            if a is None:
                return f"array {name!r} is missing"
            if listed.get(name) != a[4] or not _blob_ok(*a[2:6]):
                return f"array {name!r} fails its checksum"
        return None

    def _faults(self, c: sqlite3.Connection, steps: set[int], run_ids: set[int]) -> None:
        raw_lost = 0
        for f in self.t["faults"]:
            f = list(f)
            if f[11] is not None and not _blob_ok(*f[8:12]):
                f[8:12] = [None] * 4
                raw_lost += 1
            if f[5] is not None and f[5] not in steps:
                f[5] = None
            f[1] = f[1] if f[1] in run_ids else None
            c.execute("INSERT INTO faults VALUES (?,?,?,?,?,?,?,?,?,?,?,?)", f)
        if raw_lost:
            self.report.lost.append(f"the raw F/T data of {raw_lost} faults (the faults are kept)")
        for s in self.t["steps"]:
            fault_id = s[self.N_PLAN + 10]
            if s[0] in steps and fault_id is not None:
                c.execute("UPDATE steps SET fault_id=? WHERE step_id=? AND EXISTS "
                          "(SELECT 1 FROM faults WHERE fault_id=?)", (fault_id, s[0], fault_id))

    def _rest(self, c: sqlite3.Connection, steps: set[int], run_ids: set[int]) -> None:
        for t in self.t["transitions"]:
            t = list(t)
            t[1] = t[1] if t[1] in run_ids else None
            t[7] = t[7] if t[7] in steps else None
            c.execute("INSERT INTO transitions VALUES (?,?,?,?,?,?,?,?)", t)
        bad = 0
        for e in self.t["events"]:
            if _loads(e[5]) is _BAD:
                bad += 1
                continue
            c.execute("INSERT INTO events VALUES (?,?,?,?,?,?)", (e[0], e[1] if e[1] in run_ids else None, *e[2:]))
        if bad:
            self.report.lost.append(f"{bad} events whose record is damaged")
        c.executemany("INSERT INTO robot_time VALUES (?,?)",
                      [r for r in self.t["robot_time"] if isinstance(r[1], (int, float))])

    def _files(self, c: sqlite3.Connection) -> None:
        """The models directory whole (a model is several files, its journal row names one),
        then the rows of the recorded files that are intact."""

        models = self.src_dir / "models"
        if models.is_dir():
            shutil.copytree(models, self.out_dir / "models", dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns(".*.tmp"))
        for table, width, path_col, sha_col in (("models", 6, 2, 3), ("artifacts", 4, 1, 2)):
            for r in self.t[table]:
                rel = Path(str(r[path_col]))
                if rel.is_absolute():
                    continue          # outside the session: not ours to copy
                src = self.src_dir / rel
                if not src.is_file() or sha256_file(src) != r[sha_col]:
                    self.report.lost.append(f"{table[:-1]} file {rel} (missing or changed)")
                    continue
                dst = self.out_dir / rel
                if not dst.exists():
                    ensure_dir(dst.parent)
                    shutil.copy2(src, dst)
                self.report.files_copied += 1
                c.execute(f"INSERT INTO {table} VALUES ({','.join('?' * width)})", r)

    def _status(self, c: sqlite3.Connection, remeasure: Sequence[int]) -> None:
        r = self.session_row()
        status, reason = r[4], r[6]
        redo = bool(remeasure or self.report.phases_dropped)
        if redo or status not in ("created", "running", "paused", "done", "aborted", "fault"):
            status = "paused"
            reason = (f"salvaged from {self.src_dir}: {len(remeasure)} steps to measure again, "
                      f"{len(self.report.phases_dropped)} phases to compute again")
        c.execute("UPDATE session SET created_utc=coalesce(?, created_utc), status=?, status_reason=? WHERE id=1",
                  (r[1], status, reason))
        c.execute("INSERT INTO events (run_id, t_wall_utc, kind, record) VALUES (NULL, datetime('now'), 'salvaged', ?)",
                  (json.dumps({"from": str(self.src_dir), "phases_dropped": self.report.phases_dropped,
                               "steps_remeasure": self.report.steps_remeasure, "lost": self.report.lost}),))
        self.report.status, self.report.status_reason = status, reason

