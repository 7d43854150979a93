"""The session journal (docs/design.md §6): one SQLite file, nothing lost, resumable, reproducible.

``DIR/journal.sqlite`` holds everything a session did: provenance, the outputs of each
phase together with the force steps it planned, every step's raw data, state machine
transitions, faults with their raw F/T data, free-form events, robot time, models and
artifacts. The layout and the guarantees are documented in docs/journal.md.

Durability: WAL with ``synchronous=FULL`` (a commit is on disk when it returns) and
every write path is one ``BEGIN IMMEDIATE`` transaction. A kill -9 at any moment loses
at most the transaction in flight — in practice the step being measured — and a step
can become ``done`` only once (checked in the committing transaction and enforced by
triggers). Arrays are stored as blobs with dtype, shape and a sha256 that every read
verifies. Readers in other processes (``elastoprobe status``) use
:meth:`Journal.open_readonly`; under WAL they never block the writer.

Units: positions mm (object frame for plans; base frame for TCP poses: mm + rotation
vector rad), forces N, angles degrees, robot times s (``t_robot_s`` is the controller
clock of the current run; ``runs`` tells runs apart), wall times ISO 8601 UTC.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
import socket
import sqlite3
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from .core.atomic import ensure_dir, json_default
from .core.errors import DiskError, ElastoprobeError, InputError
from .documents import Document
from .locking import SESSION_LOCK_NAME, SessionLock
from .provenance import sha256_file
from .signals import deferred_interrupts
from .testing import crash_point

SCHEMA_VERSION = 1
JOURNAL_NAME = "journal.sqlite"
APPLICATION_ID = 0x45505242          # "EPRB": tells a journal from any other SQLite file
DEFAULT_MIN_FREE_BYTES = 200 * 2**20  # ~2000 steps of 50 scans x 256 samples

STEP_STATUSES = ("planned", "in_progress", "done", "failed", "skipped")
SESSION_STATUSES = ("created", "running", "paused", "done", "aborted", "fault")

# File systems on which SQLite's locking and fsync cannot be trusted (or are slow and
# can vanish mid-session): the journal refuses them.
NETWORK_FS_TYPES = frozenset({
    "nfs", "nfs4", "cifs", "smb", "smb2", "smb3", "smbfs", "ncpfs", "afs", "9p", "ceph",
    "glusterfs", "lustre", "gpfs", "ocfs2", "gfs2", "davfs", "sshfs", "fuse.sshfs",
    "fuse.glusterfs", "fuse.cephfs", "fuse.s3fs", "fuse.rclone", "fuse.gcsfuse", "fuse.davfs",
    "fuse.juicefs", "fuse.goofys", "fuse.smbnetfs", "fuse.curlftpfs",
})

# The arrays of a done step: required ones first, then the optional ones.
STEP_ARRAYS_REQUIRED = ("scans_xz_mm", "scan_force_n", "scan_pose", "profile_depth_mm",
                        "force_direction", "reference_xz_mm")
STEP_ARRAYS_OPTIONAL = ("scan_t_s", "reference_pose", "profile_x_mm")

_ALLOWED_KINDS = {"f", "i", "u", "b"}


# ============================================================================ errors
class JournalError(ElastoprobeError):
    """A journal operation that cannot be done (wrong state, unknown step, missing journal)."""


class JournalCorruption(JournalError):
    """Stored data fails its checksum, or SQLite finds the file damaged: the journal cannot be
    trusted there (exit 2: the journal is the input of ``resume``; ``elastoprobe salvage``
    copies what is intact into a new one)."""

    exit_code = 2


class JournalVersionError(JournalError):
    """The journal was written by a newer elastoprobe, under a schema this one cannot read: exit 2,
    it is the input of every session command. (A version no release wrote is damage.)"""

    exit_code = 2


class StepStateError(JournalError):
    """A step is not in the state the operation needs (e.g. committing a done step twice)."""


class InputsChanged(InputError):
    """The plan or cell file differs from the one the session started with (resume refuses)."""


def _is_damage(exc: sqlite3.DatabaseError) -> bool:
    """Whether SQLite's error means the file's content is damaged (not busy, locked or a failing disk)."""
    if not isinstance(exc, sqlite3.OperationalError):
        return True              # "database disk image is malformed", "file is not a database", ...
    if _sqlite_error(exc, "SQLITE_CORRUPT", "SQLITE_NOTADB"):
        return True
    # A table or column missing from the schema is SQLite's generic SQLITE_ERROR: only the
    # message tells it from a mistake in our own SQL.
    text = str(exc).lower()
    return any(w in text for w in ("malformed", "no such table", "no such column", "could not decode",
                                   "not a database", "corrupt"))


def _sqlite_error(exc: sqlite3.Error, *names: str) -> bool:
    """Whether SQLite's own result code (extended codes included, e.g. SQLITE_IOERR_READ)
    is one of ``names``: the code, not the wording of the message, which varies by version."""
    name = getattr(exc, "sqlite_errorname", None) or ""
    return any(name == n or name.startswith(n + "_") for n in names)


def _damage_error(exc: sqlite3.DatabaseError, path: Path) -> JournalError:
    if _is_damage(exc):
        return JournalCorruption(f"{path}: SQLite finds the file damaged ({exc})")
    return JournalError(f"{path}: {exc}")


def _json(text: Any, what: str) -> Any:
    """A JSON column, or JournalCorruption naming it."""
    try:
        return json.loads(text)
    except (TypeError, ValueError) as exc:
        raise JournalCorruption(f"journal: {what} is not valid JSON (stored data is damaged: {exc})") from None


# ============================================================================ helpers
def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")


def to_json(obj: Any) -> str:
    """Canonical JSON (sorted keys, no NaN/Infinity: use None) — hashes depend on it."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False, default=json_default)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def encode_array(array: np.ndarray) -> tuple[str, str, str, bytes]:
    """``(dtype, shape_json, sha256, data)`` of a numeric array, little-endian C order.

    The checksum covers dtype and shape as well as the bytes, so a damaged header is
    caught too.
    """
    a = np.asarray(array)
    if a.dtype.kind not in _ALLOWED_KINDS:
        raise TypeError(f"journal arrays must be float, int, uint or bool, not {a.dtype}")
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
    dtype = a.dtype.str
    shape = json.dumps(list(a.shape))
    data = a.tobytes(order="C")
    return dtype, shape, _array_digest(dtype, shape, data), data


def _array_digest(dtype: str, shape: str, data: bytes) -> str:
    h = hashlib.sha256(f"{dtype}|{shape}|".encode("ascii"))
    h.update(data)
    return h.hexdigest()


def decode_array(dtype: str, shape: str, sha256: str, data: bytes, what: str) -> np.ndarray:
    """Inverse of :func:`encode_array`; raises :class:`JournalCorruption` on a bad checksum."""
    try:
        intact = data is not None and _array_digest(dtype, shape, bytes(data)) == sha256
    except (TypeError, UnicodeEncodeError):
        intact = False
    if not intact:
        raise JournalCorruption(f"journal: checksum mismatch in {what} (stored data is damaged)")
    return np.frombuffer(bytes(data), dtype=np.dtype(dtype)).reshape(json.loads(shape)).copy()


# ============================================================================ records
@dataclass(frozen=True)
class StepPlan:
    """One planned force step: press ``target`` at ``angle_deg`` to ``force_n``.

    ``point_mm``, ``normal``, ``t``: object frame (mm; unit vectors). ``order_index``:
    execution order within the session (steps of one probe are consecutive, increasing
    force). ``step_id`` is unique in the session (see :meth:`Journal.next_step_id`).
    """

    step_id: int
    target_index: int
    point_mm: np.ndarray
    normal: np.ndarray
    t: np.ndarray
    angle_deg: float
    force_n: float
    order_index: int

    def canonical(self) -> dict[str, Any]:
        """The fields as plain numbers (what the phase hash covers)."""
        return {"step_id": int(self.step_id), "target_index": int(self.target_index),
                "point_mm": [float(v) for v in np.asarray(self.point_mm).reshape(3)],
                "normal": [float(v) for v in np.asarray(self.normal).reshape(3)],
                "t": [float(v) for v in np.asarray(self.t).reshape(3)],
                "angle_deg": float(self.angle_deg), "force_n": float(self.force_n),
                "order_index": int(self.order_index)}


@dataclass
class StepResult:
    """What one force step measured (stored in one transaction by :meth:`Journal.commit_step`).

    ``scans_xz_mm`` (S, L, 2) scanner-frame x, z in mm (stored float32, NaN = missing);
    ``scan_force_n`` (S, 3) mean contact force around each exposure, base frame;
    ``scan_pose`` (S, 6) TCP pose at each exposure (mm + rotation vector rad, base <- tcp);
    ``profile_depth_mm`` (L,) averaged depth along -n against the reference (NaN = missing);
    ``force_direction`` (3,) unit vector of the measured force the probe exerted (base frame);
    ``reference_xz_mm`` (R, L, 2) the zero-force reference scans of the same place.
    Optional: ``scan_t_s`` (S,), ``reference_pose`` (R, 6), ``profile_x_mm`` (L,) grid.
    ``summary``: small JSON-able facts (measured |F|, robot time, ...).
    """

    scans_xz_mm: np.ndarray
    scan_force_n: np.ndarray
    scan_pose: np.ndarray
    profile_depth_mm: np.ndarray
    force_direction: np.ndarray
    reference_xz_mm: np.ndarray
    scan_t_s: np.ndarray | None = None
    reference_pose: np.ndarray | None = None
    profile_x_mm: np.ndarray | None = None
    robot_time_s: float = 0.0
    summary: dict[str, Any] = field(default_factory=dict)

    def arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {
            "scans_xz_mm": np.asarray(self.scans_xz_mm, dtype=np.float32),
            "scan_force_n": np.asarray(self.scan_force_n, dtype=np.float64),
            "scan_pose": np.asarray(self.scan_pose, dtype=np.float64),
            "profile_depth_mm": np.asarray(self.profile_depth_mm, dtype=np.float64),
            "force_direction": np.asarray(self.force_direction, dtype=np.float64),
            "reference_xz_mm": np.asarray(self.reference_xz_mm, dtype=np.float32),
        }
        for name in STEP_ARRAYS_OPTIONAL:
            value = getattr(self, name)
            if value is not None:
                out[name] = np.asarray(value, dtype=np.float64)
        return out

    def validate(self) -> None:
        """Shapes must agree: S scans of L samples, S forces and poses."""
        s = np.asarray(self.scans_xz_mm)
        if s.ndim != 3 or s.shape[2] != 2 or s.shape[0] < 1:
            raise ValueError(f"scans_xz_mm must be (S, L, 2) with S >= 1, got {s.shape}")
        n_scans = s.shape[0]
        for name, shape in (("scan_force_n", (n_scans, 3)), ("scan_pose", (n_scans, 6)),
                            ("force_direction", (3,))):
            got = np.asarray(getattr(self, name)).shape
            if got != shape:
                raise ValueError(f"{name} must have shape {shape}, got {got}")
        r = np.asarray(self.reference_xz_mm)
        if r.ndim != 3 or r.shape[2] != 2:
            raise ValueError(f"reference_xz_mm must be (R, L, 2), got {r.shape}")
        if np.asarray(self.profile_depth_mm).ndim != 1:
            raise ValueError("profile_depth_mm must be 1-D (L,)")
        if self.scan_t_s is not None and np.asarray(self.scan_t_s).shape != (n_scans,):
            raise ValueError(f"scan_t_s must have shape ({n_scans},)")

    @staticmethod
    def from_step_data(data: Any, profile_depth_mm: np.ndarray, profile_x_mm: np.ndarray | None = None,
                       summary: Mapping[str, Any] | None = None) -> "StepResult":
        """Build from the probe executor's ``StepData`` plus the averaged profile."""
        facts = {"force_target_n": float(data.force_target_n), "angle_deg": float(data.angle_deg),
                 "force_measured_n": float(data.force_magnitude_n()),
                 "n_scans": int(np.asarray(data.scans_xz_mm).shape[0])}
        facts.update(summary or {})
        return StepResult(scans_xz_mm=data.scans_xz_mm, scan_force_n=data.scan_force_n,
                          scan_pose=data.scan_pose, profile_depth_mm=profile_depth_mm,
                          force_direction=data.measured_direction(), reference_xz_mm=data.reference_xz_mm,
                          scan_t_s=data.scan_t_s, reference_pose=data.reference_pose,
                          profile_x_mm=profile_x_mm, robot_time_s=float(data.robot_time_s), summary=facts)


@dataclass(frozen=True)
class StepRecord:
    """A row of ``steps``: the plan plus where it stands."""

    plan: StepPlan
    phase: str
    round: int
    status: str
    attempts: int
    started_utc: str | None
    finished_utc: str | None
    fail_reason: str | None
    fault_id: int | None
    summary: dict[str, Any] | None

    @property
    def step_id(self) -> int:
        return self.plan.step_id


@dataclass(frozen=True)
class PhaseRecord:
    """A committed phase: its outputs (JSON), arrays (verified) and planned step ids."""

    name: str
    round: int
    status: str
    outputs: dict[str, Any]
    outputs_hash: str
    arrays: dict[str, np.ndarray]
    step_ids: list[int]
    committed_utc: str
    completed_utc: str | None


@dataclass(frozen=True)
class FaultRecord:
    fault_id: int
    kind: str
    t_robot_s: float | None
    t_wall_utc: str
    step_id: int | None
    message: str
    policy_action: str | None
    raw: np.ndarray | None     # (N, 7): t_s, Fx, Fy, Fz (N), Tx, Ty, Tz (N m)
    run_id: int | None = None  # the run (controller process) that journaled it


@dataclass
class SessionMeta:
    """What :meth:`Journal.create` needs: the plan's name, the session seed, and provenance
    (``collect_provenance`` output plus anything else: device identities, seeds)."""

    plan_name: str
    seed: int
    provenance: dict[str, Any] = field(default_factory=dict)


# ============================================================================ file system checks
def _unescape_mount(field_text: str) -> str:
    # /proc/mounts escapes space, tab, newline and backslash as octal (\040 ...).
    out, i = [], 0
    while i < len(field_text):
        if field_text[i] == "\\" and field_text[i + 1:i + 4].isdigit() and len(field_text[i + 1:i + 4]) == 3:
            out.append(chr(int(field_text[i + 1:i + 4], 8)))
            i += 4
        else:
            out.append(field_text[i])
            i += 1
    return "".join(out)


def filesystem_type(path: str | os.PathLike[str], mounts_text: str | None = None) -> tuple[str, str]:
    """``(fs_type, mount_point)`` of the file system holding ``path`` (from /proc/mounts).

    The longest mount point that contains the real path wins; for repeated mount points
    the last (topmost) entry wins. ``("unknown", "")`` when the table is unreadable.
    """
    if mounts_text is None:
        try:
            mounts_text = Path("/proc/mounts").read_text()
        except OSError:
            return "unknown", ""
    real = os.path.realpath(os.fspath(path))
    best: tuple[int, str, str] = (-1, "unknown", "")
    for line in mounts_text.splitlines():
        parts = line.split()
        if len(parts) < 3:
            continue
        mount_point, fs_type = _unescape_mount(parts[1]), parts[2]
        mp = mount_point.rstrip("/") or "/"
        inside = mp == "/" or real == mp or real.startswith(mp + "/")
        if inside and len(mp) >= best[0]:
            best = (len(mp), fs_type, mount_point)
    return best[1], best[2]


def check_local_filesystem(path: str | os.PathLike[str], mounts_text: str | None = None) -> None:
    """Raise InputError if ``path`` lies on a network file system (SQLite cannot lock it safely)."""
    fs_type, mount_point = filesystem_type(path, mounts_text)
    if fs_type in NETWORK_FS_TYPES or fs_type.startswith(("nfs", "fuse.sshfs")):
        raise InputError(f"the session directory is on a network file system ({fs_type} mounted at "
                         f"{mount_point}); the journal needs a local disk (SQLite locking and fsync "
                         f"are not reliable over the network) — choose --out on a local disk",
                         path=os.fspath(path))


def _writable(directory: Path) -> bool:
    """Whether files can be created in ``directory`` (not a read-only mount, write permission)."""
    try:
        if os.statvfs(directory).f_flag & os.ST_RDONLY:
            return False
    except OSError:
        return False
    return os.access(directory, os.W_OK)


# A session directory's own stored data (docs/journal.md): an output file never replaces one
# of these (nor anything under models/), and no session is made inside another's directory.
LOG_NAME = "log.jsonl"
SESSION_FILES = frozenset({JOURNAL_NAME, JOURNAL_NAME + "-wal", JOURNAL_NAME + "-shm", LOG_NAME,
                           SESSION_LOCK_NAME, "models"})
_SQLITE_MAGIC = b"SQLite format 3\x00"


def is_journal_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a regular file whose SQLite header carries the journal's application id
    (a session journal wherever it lies and whatever it is called)."""
    if not os.path.isfile(path):         # never open a pipe or a device to look
        return False
    try:
        with open(path, "rb") as f:
            header = f.read(72)
    except OSError:
        return False
    return header.startswith(_SQLITE_MAGIC) and int.from_bytes(header[68:72], "big") == APPLICATION_ID


def enclosing_session(path: str | os.PathLike[str]) -> Path | None:
    """The session directory (one holding a journal) that ``path`` lies inside, or None."""
    for parent in Path(os.path.abspath(path)).parents:
        if (parent / JOURNAL_NAME).exists():
            return parent
    return None


def refuse_session_file(path: str | os.PathLike[str], what: str) -> None:
    """InputError when writing ``path`` (an output a command was asked for) would replace a
    session's stored data: a journal anywhere, or a session directory's journal, log, lock or
    model files. Other new files inside a session directory (``export.h5``) are fine."""
    p = Path(os.path.abspath(path))
    session = enclosing_session(p)
    owned = session is not None and p.relative_to(session).parts[0] in SESSION_FILES
    if is_journal_file(p) or owned:
        raise InputError(f"{what} would replace stored data of the session in {session or p.parent}; "
                         f"choose another file", path=os.fspath(path))


def refuse_nested_session(session_dir: str | os.PathLike[str]) -> None:
    """InputError when a new session directory would lie inside another session's directory
    (its journal, models and report would be mixed up with that session's files)."""
    outer = enclosing_session(session_dir)
    if outer is not None:
        raise InputError(f"lies inside the session directory {outer}; choose a folder outside it",
                         path=os.fspath(session_dir))


def check_free_disk(path: str | os.PathLike[str], min_free_bytes: int) -> int:
    """Free bytes at ``path``; InputError when below ``min_free_bytes``."""
    free = shutil.disk_usage(os.fspath(path)).free
    if free < min_free_bytes:
        raise InputError(f"only {free / 2**20:.0f} MiB free on the session's disk; the journal needs "
                         f"at least {min_free_bytes / 2**20:.0f} MiB", path=os.fspath(path))
    return free


# ============================================================================ schema
_SCHEMA = """
CREATE TABLE schema_version (
    version      INTEGER NOT NULL,
    applied_utc  TEXT NOT NULL,
    software     TEXT
);
CREATE TABLE session (
    id           INTEGER PRIMARY KEY CHECK (id = 1),
    created_utc  TEXT NOT NULL,
    plan_name    TEXT NOT NULL,
    seed         INTEGER NOT NULL,
    status       TEXT NOT NULL CHECK (status IN ('created','running','paused','done','aborted','fault')),
    status_utc   TEXT NOT NULL,
    status_reason TEXT
);
CREATE TABLE provenance (
    key          TEXT PRIMARY KEY,
    value        TEXT NOT NULL,             -- JSON
    recorded_utc TEXT NOT NULL
);
CREATE TABLE runs (
    run_id       INTEGER PRIMARY KEY,
    mode         TEXT NOT NULL CHECK (mode IN ('create','resume')),
    started_utc  TEXT NOT NULL,
    pid          INTEGER NOT NULL,
    host         TEXT NOT NULL,
    ended_utc    TEXT,
    end_status   TEXT
);
CREATE TABLE phases (
    phase_id     INTEGER PRIMARY KEY,
    name         TEXT NOT NULL,
    round        INTEGER NOT NULL,
    status       TEXT NOT NULL CHECK (status IN ('committed','complete')),
    outputs      TEXT NOT NULL,             -- JSON
    outputs_hash TEXT NOT NULL,             -- sha256 over outputs, array checksums, planned steps
    n_steps      INTEGER NOT NULL,
    committed_utc TEXT NOT NULL,
    completed_utc TEXT,
    run_id       INTEGER REFERENCES runs(run_id),
    UNIQUE (name, round)
);
CREATE TABLE phase_arrays (
    phase_id     INTEGER NOT NULL REFERENCES phases(phase_id),
    name         TEXT NOT NULL,
    dtype        TEXT NOT NULL,
    shape        TEXT NOT NULL,
    sha256       TEXT NOT NULL,
    data         BLOB NOT NULL,
    PRIMARY KEY (phase_id, name)
);
CREATE TABLE steps (
    step_id      INTEGER PRIMARY KEY,
    phase_id     INTEGER NOT NULL REFERENCES phases(phase_id),
    phase        TEXT NOT NULL,
    round        INTEGER NOT NULL,
    target_index INTEGER NOT NULL,
    px REAL NOT NULL, py REAL NOT NULL, pz REAL NOT NULL,
    nx REAL NOT NULL, ny REAL NOT NULL, nz REAL NOT NULL,
    tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
    angle_deg    REAL NOT NULL,
    force_n      REAL NOT NULL,
    order_index  INTEGER NOT NULL,
    status       TEXT NOT NULL DEFAULT 'planned'
                 CHECK (status IN ('planned','in_progress','done','failed','skipped')),
    attempts     INTEGER NOT NULL DEFAULT 0 CHECK (attempts >= 0),
    started_utc  TEXT,
    finished_utc TEXT,
    run_id       INTEGER REFERENCES runs(run_id),
    summary      TEXT,                      -- JSON, present exactly when done
    fail_reason  TEXT,
    fault_id     INTEGER REFERENCES faults(fault_id),
    CHECK ((status = 'done') = (summary IS NOT NULL))
);
CREATE INDEX steps_by_status ON steps(status, order_index);
CREATE INDEX steps_by_phase ON steps(phase_id);
CREATE TABLE step_arrays (
    step_id      INTEGER NOT NULL REFERENCES steps(step_id),
    name         TEXT NOT NULL,
    dtype        TEXT NOT NULL,
    shape        TEXT NOT NULL,
    sha256       TEXT NOT NULL,
    data         BLOB NOT NULL,
    PRIMARY KEY (step_id, name)
);
-- A done step is final, and its data immutable: enforced below the Python code too.
CREATE TRIGGER steps_done_is_final BEFORE UPDATE OF status ON steps
    WHEN OLD.status = 'done'
    BEGIN SELECT RAISE(ABORT, 'journal: step already done'); END;
CREATE TRIGGER step_arrays_only_in_progress BEFORE INSERT ON step_arrays
    WHEN (SELECT status FROM steps WHERE step_id = NEW.step_id) IS NOT 'in_progress'
    BEGIN SELECT RAISE(ABORT, 'journal: step data may only be written to a step in progress'); END;
CREATE TRIGGER step_arrays_immutable BEFORE UPDATE ON step_arrays
    BEGIN SELECT RAISE(ABORT, 'journal: step data is immutable'); END;
CREATE TABLE transitions (
    id           INTEGER PRIMARY KEY,
    run_id       INTEGER REFERENCES runs(run_id),
    t_robot_s    REAL,
    t_wall_utc   TEXT NOT NULL,
    from_state   TEXT NOT NULL,
    to_state     TEXT NOT NULL,
    trigger      TEXT NOT NULL,
    step_id      INTEGER REFERENCES steps(step_id)
);
CREATE TABLE faults (
    fault_id     INTEGER PRIMARY KEY,
    run_id       INTEGER REFERENCES runs(run_id),
    kind         TEXT NOT NULL,
    t_robot_s    REAL,
    t_wall_utc   TEXT NOT NULL,
    step_id      INTEGER REFERENCES steps(step_id),
    message      TEXT NOT NULL,
    policy_action TEXT,
    raw_dtype    TEXT, raw_shape TEXT, raw_sha256 TEXT, raw BLOB   -- (N,7) t_s, F xyz, T xyz
);
CREATE TABLE events (
    id           INTEGER PRIMARY KEY,
    run_id       INTEGER REFERENCES runs(run_id),
    t_wall_utc   TEXT NOT NULL,
    t_robot_s    REAL,
    kind         TEXT NOT NULL,
    record       TEXT NOT NULL              -- JSON
);
CREATE TABLE robot_time (
    category     TEXT PRIMARY KEY,
    seconds      REAL NOT NULL
);
CREATE TABLE models (
    region       INTEGER NOT NULL,
    member       INTEGER NOT NULL,
    path         TEXT NOT NULL,             -- relative to the session directory when inside it
    sha256       TEXT NOT NULL,
    metrics      TEXT NOT NULL,             -- JSON
    recorded_utc TEXT NOT NULL,
    PRIMARY KEY (region, member)
);
CREATE TABLE artifacts (
    name         TEXT PRIMARY KEY,
    path         TEXT NOT NULL,
    sha256       TEXT NOT NULL,
    recorded_utc TEXT NOT NULL
);
"""

_IMMUTABLE_PROVENANCE = ("plan", "cell")


def _software_version() -> str | None:
    try:
        import importlib.metadata
        return importlib.metadata.version("elastoprobe")
    except Exception:   # noqa: BLE001
        return None


# ============================================================================ the journal
class Journal:
    """A session's journal. Create with :meth:`create`, reopen with :meth:`open`, read from
    another process with :meth:`open_readonly`. Use as a context manager or call :meth:`close`.

    The writer holds the session lock (``DIR/session.lock``) while open unless ``lock=False``.
    """

    def __init__(self, session_dir: Path, conn: sqlite3.Connection, readonly: bool,
                 lock: SessionLock | None, run_id: int | None) -> None:
        self.session_dir = session_dir
        self.path = session_dir / JOURNAL_NAME
        self._conn = conn
        self.readonly = readonly
        self._lock = lock
        self.run_id = run_id
        self._depth = 0

    # ------------------------------------------------------------------ opening
    @staticmethod
    def _connect(path: Path, readonly: bool) -> sqlite3.Connection:
        """Open and configure a connection; the file must already be a journal of a known schema
        (checked before anything is written to it, so a foreign SQLite file stays untouched)."""
        if readonly:
            conn = Journal._reader(path)
        else:
            if not path.is_file():
                raise JournalCorruption(f"{path}: not a file")
            conn = sqlite3.connect(str(path), isolation_level=None, timeout=10.0)
        try:
            Journal._check_schema(conn, path)
        except BaseException:
            conn.close()
            raise
        if not readonly:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                conn.close()
                raise InputError(f"the journal cannot use write-ahead logging here (got {mode!r}); "
                                 f"use a local disk", path=str(path))
            conn.execute("PRAGMA synchronous=FULL")
        conn.execute("PRAGMA foreign_keys=ON")
        conn.execute("PRAGMA busy_timeout=10000")
        return conn

    @staticmethod
    def _reader(path: Path) -> sqlite3.Connection:
        """A read-only connection. On a disk where SQLite cannot make the shared-memory index
        a WAL reader needs (read-only media or mount, a full disk), the file is opened as
        immutable — nothing can be writing it there — unless a write-ahead log lies beside
        it (a session killed there), which cannot be read without that index."""
        base = "file:" + urllib.parse.quote(os.fsencode(path)) + "?mode=ro"   # bytes: any name the OS allows
        if not path.is_file():
            raise JournalCorruption(f"{path}: not a file")
        if _writable(path.parent):
            conn = sqlite3.connect(base, uri=True, isolation_level=None, timeout=10.0)
            try:
                conn.execute("PRAGMA schema_version").fetchone()
                conn.execute("PRAGMA query_only=ON")
                return conn
            except sqlite3.OperationalError as exc:
                conn.close()
                if not _sqlite_error(exc, "SQLITE_IOERR", "SQLITE_CANTOPEN"):
                    raise _damage_error(exc, path) from None
            except sqlite3.DatabaseError as exc:
                conn.close()
                raise JournalCorruption(f"{path}: not a readable session journal ({exc})") from None
        wal = Path(str(path) + "-wal")
        if wal.exists() and wal.stat().st_size > 0:
            raise DiskError("the journal's write-ahead log cannot be read where SQLite cannot write its index "
                            "(read-only or full disk): copy the session directory to a writable disk, or free "
                            "space", path=str(path.parent))
        conn = sqlite3.connect(base + "&immutable=1", uri=True, isolation_level=None, timeout=10.0)
        conn.execute("PRAGMA query_only=ON")
        return conn

    @staticmethod
    def _prepare_dir(session_dir: Path, min_free_bytes: int, mounts_text: str | None) -> None:
        ensure_dir(session_dir)
        journal = session_dir / JOURNAL_NAME
        if journal.exists() and not os.access(journal, os.W_OK):
            raise DiskError("cannot write the journal (no permission)", path=str(journal))
        check_local_filesystem(session_dir, mounts_text)
        check_free_disk(session_dir, min_free_bytes)

    @classmethod
    def create(cls, session_dir: str | os.PathLike[str], meta: SessionMeta | Mapping[str, Any], *,
               lock: bool = True, min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
               mounts_text: str | None = None) -> "Journal":
        """Start a new session journal in ``session_dir`` (created if needed).

        Refuses network file systems, a nearly full disk, and a directory that already has
        a journal (resume it instead). The schema is built in a temporary file that is
        renamed into place, so a kill during creation leaves no half-made journal.
        """
        if not isinstance(meta, SessionMeta):
            meta = SessionMeta(**dict(meta))
        d = Path(session_dir)
        refuse_nested_session(d)
        cls._prepare_dir(d, min_free_bytes, mounts_text)
        held = SessionLock(d).acquire() if lock else None
        try:
            path = d / JOURNAL_NAME
            if path.exists():
                raise InputError("this directory already holds a session journal; resume it "
                                 "(elastoprobe resume DIR) or choose another --out", path=str(path))
            try:
                cls._build(d, meta)
            except sqlite3.OperationalError as exc:   # the disk refused the new file
                raise DiskError(f"cannot create the journal: {exc}", path=str(path)) from None
            conn = cls._connect(path, readonly=False)
            journal = cls(d, conn, readonly=False, lock=held, run_id=None)
            journal._start_run("create")
            return journal
        except BaseException:
            if held is not None:
                held.release()
            raise

    @classmethod
    def _build(cls, d: Path, meta: SessionMeta, fill: Callable[[sqlite3.Connection], None] | None = None) -> None:
        """Build a journal in a temporary file and rename it into place; ``fill`` adds rows in
        the same transaction (a salvage copies a damaged journal's intact parts)."""
        tmp = d / (JOURNAL_NAME + ".init")
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(str(tmp) + suffix).unlink(missing_ok=True)
        conn = sqlite3.connect(str(tmp), isolation_level=None)
        try:
            conn.execute(f"PRAGMA application_id={APPLICATION_ID}")
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("BEGIN IMMEDIATE")
            # Statement by statement: executescript() would commit the open transaction first.
            for statement in _split_sql(_SCHEMA):
                conn.execute(statement)
            now = _utc_now()
            conn.execute("INSERT INTO schema_version VALUES (?,?,?)", (SCHEMA_VERSION, now, _software_version()))
            conn.execute("INSERT INTO session (id, created_utc, plan_name, seed, status, status_utc) "
                         "VALUES (1,?,?,?,'created',?)", (now, meta.plan_name, int(meta.seed), now))
            for key, value in meta.provenance.items():
                conn.execute("INSERT INTO provenance VALUES (?,?,?)", (key, to_json(value), now))
            if fill is not None:
                fill(conn)
            conn.execute("COMMIT")
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            conn.close()
        os.replace(tmp, d / JOURNAL_NAME)
        fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    @classmethod
    def open(cls, session_dir: str | os.PathLike[str], *, lock: bool = True,
             min_free_bytes: int = DEFAULT_MIN_FREE_BYTES, mounts_text: str | None = None) -> "Journal":
        """Reopen a session's journal for writing (resume). Takes the session lock.

        The whole journal is checked first, through a reader (SQLite's integrity check
        and every checksum, :meth:`verify`): a damaged journal raises JournalCorruption
        naming the damage, and nothing is written to it."""
        d = Path(session_dir)
        path = d / JOURNAL_NAME
        if not path.exists():
            raise InputError("no session journal here (expected journal.sqlite)", path=str(d))
        cls._prepare_dir(d, min_free_bytes, mounts_text)
        held = SessionLock(d).acquire() if lock else None
        try:
            cls.open_readonly(d, check="full").close()
            conn = cls._connect(path, readonly=False)
            journal = cls(d, conn, readonly=False, lock=held, run_id=None)
            journal._start_run("resume")
            journal._note_resume(held)
            return journal
        except BaseException:
            if held is not None:
                held.release()
            raise

    @classmethod
    def open_readonly(cls, session_dir: str | os.PathLike[str], check: str = "full") -> "Journal":
        """A reader for another process (status, report): never blocks the writer, never writes.

        ``check="full"`` (the default) verifies the whole journal first (:meth:`verify`,
        about one read of the file) and raises JournalCorruption naming what is damaged;
        ``"none"`` leaves that to the reads themselves (each verifies what it reads), for
        polls of a running session."""
        if check not in ("full", "none"):
            raise ValueError(f"check must be 'full' or 'none', not {check!r}")
        d = Path(session_dir)
        path = d / JOURNAL_NAME
        if not path.exists():
            raise InputError("no session journal here (expected journal.sqlite)", path=str(d))
        conn = cls._connect(path, readonly=True)
        journal = cls(d, conn, readonly=True, lock=None, run_id=None)
        if check == "full":
            problems = journal.verify()
            if problems:
                journal.close()
                raise JournalCorruption(describe_damage(problems))
        return journal

    @staticmethod
    def _check_schema(conn: sqlite3.Connection, path: Path) -> None:
        conn.execute("PRAGMA busy_timeout=10000")
        try:
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            if app_id != APPLICATION_ID:
                raise JournalCorruption(f"{path}: not an elastoprobe session journal")
            row = conn.execute("SELECT max(version) FROM schema_version").fetchone()
        except sqlite3.DatabaseError as exc:
            raise JournalCorruption(f"{path}: not a readable session journal ({exc})") from None
        if row is None or row[0] is None:
            raise JournalCorruption(f"{path}: session journal without a schema version")
        version = row[0]
        if not isinstance(version, int) or version < 1:
            raise JournalCorruption(f"{path}: journal schema version {version!r} is not one any elastoprobe "
                                    f"wrote (stored data is damaged)")
        if version > SCHEMA_VERSION:
            raise JournalVersionError(f"{path}: journal schema version {version} is newer than this "
                                      f"elastoprobe understands ({SCHEMA_VERSION}); upgrade elastoprobe")
        # Older versions would be migrated here; version 1 is the first.

    def abandon(self) -> None:
        """Close without writing anything (the journal is damaged or its disk fails), release the lock."""
        if self._conn is not None:
            with contextlib.suppress(sqlite3.Error):
                self._conn.close()
            self._conn = None   # type: ignore[assignment]
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def close(self, end_status: str | None = None) -> None:
        """End the run (recording ``end_status``), close the connection, release the lock."""
        if self._conn is None:
            return
        try:
            if not self.readonly and self.run_id is not None:
                with self.transaction():
                    self._conn.execute("UPDATE runs SET ended_utc=?, end_status=? WHERE run_id=?",
                                       (_utc_now(), end_status, self.run_id))
        finally:
            self._conn.close()
            self._conn = None   # type: ignore[assignment]
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close("error" if exc_type is not None else None)

    def _note_resume(self, held: SessionLock | None) -> None:
        """Journal what the previous run left behind: a dead holder's lock, interrupted steps."""
        if held is not None and held.took_over_from:
            self.log_event("stale_lock_taken_over", {"previous_holder": held.took_over_from})
        interrupted = [s.step_id for s in self.steps(statuses=["in_progress"])]
        if interrupted:
            self.log_event("interrupted_steps", {"step_ids": interrupted})

    def _start_run(self, mode: str) -> None:
        with self.transaction() as c:
            cur = c.execute("INSERT INTO runs (mode, started_utc, pid, host) VALUES (?,?,?,?)",
                            (mode, _utc_now(), os.getpid(), socket.gethostname()))
            self.run_id = int(cur.lastrowid)

    # ------------------------------------------------------------------ transactions
    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """``with journal.transaction() as c:`` — one ``BEGIN IMMEDIATE`` … ``COMMIT``.

        Nested uses join the outermost transaction (so a caller can group, e.g., a step
        commit with its transition). Any exception rolls everything back. An operator's
        pause or stop never lands inside (signals.deferred_interrupts).
        """
        with deferred_interrupts():
            with self._transaction() as c:
                yield c

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        if self.readonly:
            raise JournalError("journal opened read-only")
        if self._conn is None:
            raise JournalError("journal is closed")
        if self._depth:
            self._depth += 1
            try:
                yield self._conn
            finally:
                self._depth -= 1
            return
        self._conn.execute("BEGIN IMMEDIATE")
        self._depth = 1
        try:
            yield self._conn
        except BaseException as exc:
            self._depth = 0
            with contextlib.suppress(sqlite3.Error):   # never mask the original error
                self._conn.execute("ROLLBACK")
            if isinstance(exc, sqlite3.DatabaseError) and _is_damage(exc):
                raise _damage_error(exc, self.path) from None
            raise
        self._depth = 0
        try:
            self._conn.execute("COMMIT")
        except sqlite3.OperationalError as exc:
            with contextlib.suppress(sqlite3.Error):
                self._conn.execute("ROLLBACK")
            if _sqlite_error(exc, "SQLITE_FULL"):
                raise JournalError(f"journal: disk full, the last write was not saved ({exc})") from None
            raise

    def _q(self, sql: str, args: Sequence[Any] = ()) -> list[sqlite3.Row]:
        if self._conn is None:
            raise JournalError("journal is closed")
        try:
            return self._conn.execute(sql, args).fetchall()
        except sqlite3.DatabaseError as exc:
            raise _damage_error(exc, self.path) from None

    # ------------------------------------------------------------------ session & provenance
    def session(self) -> dict[str, Any]:
        rows = self._q("SELECT created_utc, plan_name, seed, status, status_utc, status_reason FROM session")
        row = rows[0] if rows else None
        if row is None or not isinstance(row[1], str) or not isinstance(row[2], int) \
                or row[3] not in SESSION_STATUSES or not (row[5] is None or isinstance(row[5], str)):
            raise JournalCorruption("journal: the session record is damaged (plan name, seed or status unreadable)")
        return {"created_utc": row[0], "plan_name": row[1], "seed": row[2], "status": row[3],
                "status_utc": row[4], "status_reason": row[5]}

    def set_status(self, status: str, reason: str | None = None) -> None:
        if status not in SESSION_STATUSES:
            raise ValueError(f"unknown session status {status!r}")
        with self.transaction() as c:
            c.execute("UPDATE session SET status=?, status_utc=?, status_reason=? WHERE id=1",
                      (status, _utc_now(), reason))

    def provenance(self) -> dict[str, Any]:
        return {k: _json(v, f"provenance {k!r}") for k, v in self._q("SELECT key, value FROM provenance ORDER BY key")}

    def set_provenance(self, key: str, value: Any) -> None:
        """Add or update a provenance entry (device identities once connected, seeds, ...).
        The plan and cell entries are fixed at creation."""
        if key in _IMMUTABLE_PROVENANCE and self._q("SELECT 1 FROM provenance WHERE key=?", (key,)):
            raise JournalError(f"provenance {key!r} is fixed when the session is created")
        with self.transaction() as c:
            c.execute("INSERT INTO provenance VALUES (?,?,?) ON CONFLICT(key) DO UPDATE SET "
                      "value=excluded.value, recorded_utc=excluded.recorded_utc", (key, to_json(value), _utc_now()))

    def verify_inputs(self, plan_text: str | bytes, cell_text: str | bytes) -> None:
        """Raise :class:`InputsChanged` if the plan or cell differs from the session's start."""
        prov = self.provenance()
        for what, text in (("plan", plan_text), ("cell", cell_text)):
            stored = prov.get(what)
            if not stored or "sha256" not in stored:
                raise JournalError(f"journal has no {what} provenance to check against")
            data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
            if _sha256(data) != stored["sha256"]:
                raise InputsChanged(
                    f"the {what} file changed since this session started (sha256 "
                    f"{stored['sha256'][:12]}… now {_sha256(data)[:12]}…){_first_difference(stored.get('text'), data)}; "
                    f"resume would not reproduce the session — restore the original or start a new session",
                    path=stored.get("path"))

    # ------------------------------------------------------------------ phases
    def commit_phase(self, name: str, round: int, outputs: Mapping[str, Any],
                     arrays: Mapping[str, np.ndarray] | None = None,
                     planned_steps: Sequence[StepPlan] = ()) -> str:
        """Commit a phase's outputs, arrays and the steps it plans in ONE transaction.

        Returns the phase hash (sha256 over the canonical outputs, the arrays' checksums
        and the planned steps). A phase (name, round) commits once; step ids must be new.
        """
        arrays = dict(arrays or {})
        encoded = {k: encode_array(v) for k, v in sorted(arrays.items())}
        steps = [s.canonical() for s in planned_steps]
        outputs_json = to_json(dict(outputs))
        digest = _phase_digest(outputs_json, {k: e[2] for k, e in encoded.items()}, steps)
        now = _utc_now()
        with self.transaction() as c:
            if c.execute("SELECT 1 FROM phases WHERE name=? AND round=?", (name, round)).fetchone():
                raise JournalError(f"phase {name!r} round {round} is already committed")
            cur = c.execute("INSERT INTO phases (name, round, status, outputs, outputs_hash, n_steps, "
                            "committed_utc, run_id) VALUES (?,?,'committed',?,?,?,?,?)",
                            (name, int(round), outputs_json, digest, len(steps), now, self.run_id))
            phase_id = int(cur.lastrowid)
            crash_point("commit_phase:after_phase_row")
            c.executemany("INSERT INTO phase_arrays VALUES (?,?,?,?,?,?)",
                          [(phase_id, k, *e) for k, e in encoded.items()])
            half = len(steps) // 2
            try:
                c.executemany(_INSERT_STEP, [_step_row(s, phase_id, name, round) for s in steps[:half]])
                crash_point("commit_phase:half_steps")
                c.executemany(_INSERT_STEP, [_step_row(s, phase_id, name, round) for s in steps[half:]])
            except sqlite3.IntegrityError as exc:
                raise JournalError(f"phase {name!r} round {round}: planned step ids collide with "
                                   f"existing steps ({exc})") from None
            crash_point("commit_phase:before_commit")
        return digest

    def complete_phase(self, name: str, round: int) -> None:
        """Mark a committed phase complete (all its steps done, failed for good or skipped)."""
        with self.transaction() as c:
            row = c.execute("SELECT phase_id, status FROM phases WHERE name=? AND round=?", (name, round)).fetchone()
            if row is None:
                raise JournalError(f"phase {name!r} round {round} was never committed")
            open_steps = c.execute("SELECT count(*) FROM steps WHERE phase_id=? AND status IN "
                                   "('planned','in_progress')", (row[0],)).fetchone()[0]
            if open_steps:
                raise StepStateError(f"phase {name!r} round {round} still has {open_steps} open steps")
            c.execute("UPDATE phases SET status='complete', completed_utc=? WHERE phase_id=?", (_utc_now(), row[0]))

    def phase(self, name: str, round: int) -> PhaseRecord | None:
        """A committed phase, verified (outputs hash and array checksums), or None."""
        rows = self._q("SELECT phase_id, status, outputs, outputs_hash, n_steps, committed_utc, completed_utc "
                       "FROM phases WHERE name=? AND round=?", (name, round))
        if not rows:
            return None
        phase_id, status, outputs_json, digest, n_steps, committed, completed = rows[0]
        what = f"phase {name!r} round {round}"
        arrays, sums = {}, {}
        for aname, dtype, shape, sha, data in self._q(
                "SELECT name, dtype, shape, sha256, data FROM phase_arrays WHERE phase_id=? ORDER BY name", (phase_id,)):
            arrays[aname] = decode_array(dtype, shape, sha, data, f"{what} array {aname!r}")
            sums[aname] = sha
        step_rows = self._q(f"SELECT {_STEP_PLAN_COLS} FROM steps WHERE phase_id=? ORDER BY rowid", (phase_id,))
        steps = [_plan_from_row(r).canonical() for r in step_rows]
        if len(steps) != n_steps or _phase_digest(outputs_json, sums, steps) != digest:
            raise JournalCorruption(f"journal: {what} does not match its hash (outputs or planned steps damaged)")
        return PhaseRecord(name=name, round=round, status=status, outputs=_json(outputs_json, f"{what} outputs"),
                           outputs_hash=digest, arrays=arrays, step_ids=[s["step_id"] for s in steps],
                           committed_utc=committed, completed_utc=completed)

    def phases(self) -> list[dict[str, Any]]:
        """Committed phases in commit order: name, round, status, outputs_hash, n_steps (unverified)."""
        return [{"name": r[0], "round": r[1], "status": r[2], "outputs_hash": r[3], "n_steps": r[4],
                 "committed_utc": r[5]} for r in
                self._q("SELECT name, round, status, outputs_hash, n_steps, committed_utc FROM phases ORDER BY phase_id")]

    def next_step_id(self) -> int:
        """The smallest step id above every planned step (for a phase about to plan more)."""
        return int(self._q("SELECT coalesce(max(step_id), -1) + 1 FROM steps")[0][0])

    # ------------------------------------------------------------------ steps
    def begin_step(self, step_id: int) -> int:
        """Mark a step in progress and count an attempt; returns the attempt number (1-based).

        Allowed from planned, in_progress (interrupted by a crash) and failed; a done or
        skipped step raises :class:`StepStateError`.
        """
        with self.transaction() as c:
            status, attempts = self._step_state(c, step_id)
            if status in ("done", "skipped"):
                raise StepStateError(f"step {step_id} is {status}; it cannot be started again")
            attempt = attempts + 1
            c.execute("UPDATE steps SET status='in_progress', attempts=?, started_utc=?, finished_utc=NULL, "
                      "run_id=?, fail_reason=NULL, fault_id=NULL WHERE step_id=?",
                      (attempt, _utc_now(), self.run_id, step_id))
            crash_point("begin_step:before_commit")
        return attempt

    def commit_step(self, step_id: int, attempt: int, result: StepResult) -> None:
        """Store a step's measurements and mark it done, in ONE transaction.

        The step must be ``in_progress`` with this ``attempt`` (else :class:`StepStateError`:
        a step is never done twice, nor completed by a stale attempt). Robot time of the
        step is added to the ``probing`` account in the same transaction.
        """
        result.validate()
        arrays = result.arrays()
        encoded = [(step_id, name, *encode_array(a)) for name, a in arrays.items()]
        summary = dict(result.summary)
        summary.update({"attempt": int(attempt), "robot_time_s": float(result.robot_time_s),
                        "arrays": {e[1]: e[4] for e in encoded}})
        summary_json = to_json(summary)
        with self.transaction() as c:
            status, attempts = self._step_state(c, step_id)
            if status == "done":
                raise StepStateError(f"step {step_id} is already done; nothing was written twice")
            if status != "in_progress" or attempts != attempt:
                raise StepStateError(f"step {step_id}: attempt {attempt} is not the one in progress "
                                     f"(status {status}, attempts {attempts})")
            # Leftovers cannot exist (a step's data is written in the transaction that
            # makes it done), but a stale row must never be mistaken for this attempt's.
            c.execute("DELETE FROM step_arrays WHERE step_id=?", (step_id,))
            half = len(encoded) // 2
            c.executemany("INSERT INTO step_arrays VALUES (?,?,?,?,?,?)", encoded[:half])
            crash_point("commit_step:half_arrays")
            c.executemany("INSERT INTO step_arrays VALUES (?,?,?,?,?,?)", encoded[half:])
            crash_point("commit_step:after_arrays")
            c.execute("UPDATE steps SET status='done', finished_utc=?, summary=? WHERE step_id=?",
                      (_utc_now(), summary_json, step_id))
            self._add_robot_time(c, "probing", float(result.robot_time_s))
            crash_point("commit_step:before_commit")

    def fail_step(self, step_id: int, attempt: int, reason: str, fault_id: int | None = None) -> None:
        """Mark the attempt in progress as failed (the step stays pending for a retry)."""
        with self.transaction() as c:
            status, attempts = self._step_state(c, step_id)
            if status != "in_progress" or attempts != attempt:
                raise StepStateError(f"step {step_id}: cannot fail attempt {attempt} "
                                     f"(status {status}, attempts {attempts})")
            c.execute("UPDATE steps SET status='failed', finished_utc=?, fail_reason=?, fault_id=? "
                      "WHERE step_id=?", (_utc_now(), reason, fault_id, step_id))
            crash_point("fail_step:before_commit")

    def skip_step(self, step_id: int, reason: str) -> None:
        """Give up on a step that is not done (fault policy, budget): it leaves the pending list."""
        with self.transaction() as c:
            status, _ = self._step_state(c, step_id)
            if status == "done":
                raise StepStateError(f"step {step_id} is done; it cannot be skipped")
            c.execute("UPDATE steps SET status='skipped', finished_utc=?, fail_reason=? WHERE step_id=?",
                      (_utc_now(), reason, step_id))

    @staticmethod
    def _step_state(c: sqlite3.Connection, step_id: int) -> tuple[str, int]:
        row = c.execute("SELECT status, attempts FROM steps WHERE step_id=?", (int(step_id),)).fetchone()
        if row is None:
            raise StepStateError(f"step {step_id} was never planned")
        return row[0], int(row[1])

    def steps(self, phase: str | None = None, round: int | None = None,
              statuses: Sequence[str] | None = None, step_ids: Sequence[int] | None = None) -> list[StepRecord]:
        """Steps in execution order (order_index, then step_id), optionally filtered."""
        where, args = [], []
        if step_ids is not None:
            ids = [int(i) for i in step_ids]
            where.append(f"step_id IN ({','.join('?' * len(ids))})" if ids else "0")
            args.extend(ids)
        if phase is not None:
            where.append("phase=?")
            args.append(phase)
        if round is not None:
            where.append("round=?")
            args.append(int(round))
        if statuses is not None:
            bad = set(statuses) - set(STEP_STATUSES)
            if bad:
                raise ValueError(f"unknown step statuses {sorted(bad)}")
            where.append(f"status IN ({','.join('?' * len(statuses))})")
            args.extend(statuses)
        sql = (f"SELECT {_STEP_PLAN_COLS}, phase, round, status, attempts, started_utc, finished_utc, "
               f"fail_reason, fault_id, summary FROM steps")
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY order_index, step_id"
        out = []
        for r in self._q(sql, args):
            n = len(_STEP_PLAN_COLS.split(","))
            out.append(StepRecord(plan=_plan_from_row(r[:n]), phase=r[n], round=r[n + 1], status=r[n + 2],
                                  attempts=r[n + 3], started_utc=r[n + 4], finished_utc=r[n + 5],
                                  fail_reason=r[n + 6], fault_id=r[n + 7],
                                  summary=_json(r[n + 8], f"step {r[0]} summary") if r[n + 8] else None))
        return out

    def step(self, step_id: int) -> StepRecord:
        recs = self.steps(step_ids=[step_id])
        if not recs:
            raise StepStateError(f"step {step_id} was never planned")
        return recs[0]

    def pending_steps(self, phase: str | None = None, round: int | None = None,
                      include_failed: bool = True, max_attempts: int | None = None) -> list[StepRecord]:
        """What a resume still has to do, in order: planned and interrupted (in_progress)
        steps, and failed ones (unless ``include_failed`` is False, or they have used
        ``max_attempts``)."""
        statuses = ["planned", "in_progress"] + (["failed"] if include_failed else [])
        out = self.steps(phase, round, statuses)
        if max_attempts is not None:
            out = [s for s in out if s.status != "failed" or s.attempts < max_attempts]
        return out

    def status_counts(self, phase: str | None = None) -> dict[str, int]:
        counts = dict.fromkeys(STEP_STATUSES, 0)
        sql = "SELECT status, count(*) FROM steps" + (" WHERE phase=?" if phase else "") + " GROUP BY status"
        for status, n in self._q(sql, (phase,) if phase else ()):
            counts[status] = int(n)
        return counts

    def step_result(self, step_id: int) -> StepResult:
        """The stored measurements of a done step, checksums verified."""
        results = self.step_results([step_id])
        if step_id not in results:
            raise StepStateError(f"step {step_id} is not done")
        return results[step_id]

    def step_results(self, step_ids: Sequence[int] | None = None, phase: str | None = None,
                     round: int | None = None) -> dict[int, StepResult]:
        """Measurements of done steps (all, or those listed / of a phase), verified on read:
        :class:`JournalCorruption` if any blob fails its checksum or a listed array is missing."""
        records = self.steps(phase, round, ["done"], step_ids=step_ids)
        out: dict[int, StepResult] = {}
        for rec in records:
            out[rec.step_id] = self._load_step_result(rec)
        return out

    def _load_step_result(self, rec: StepRecord) -> StepResult:
        summary = dict(rec.summary or {})
        listed: dict[str, str] = summary.pop("arrays", {})
        rows = self._q("SELECT name, dtype, shape, sha256, data FROM step_arrays WHERE step_id=?", (rec.step_id,))
        arrays: dict[str, np.ndarray] = {}
        for name, dtype, shape, sha, data in rows:
            if listed.get(name) != sha:
                raise JournalCorruption(f"journal: step {rec.step_id} array {name!r} does not match its record")
            arrays[name] = decode_array(dtype, shape, sha, data, f"step {rec.step_id} array {name!r}")
        missing = (set(listed) | set(STEP_ARRAYS_REQUIRED)) - set(arrays)
        if missing:
            raise JournalCorruption(f"journal: step {rec.step_id} is done but misses {sorted(missing)}")
        robot_time_s = float(summary.pop("robot_time_s", 0.0))
        return StepResult(**{k: arrays[k] for k in STEP_ARRAYS_REQUIRED},
                          **{k: arrays.get(k) for k in STEP_ARRAYS_OPTIONAL},
                          robot_time_s=robot_time_s, summary=summary)

    # ------------------------------------------------------------------ transitions, faults, events
    def record_transition(self, from_state: str, to_state: str, trigger: str,
                          t_robot_s: float | None = None, step_id: int | None = None) -> None:
        with self.transaction() as c:
            c.execute("INSERT INTO transitions (run_id, t_robot_s, t_wall_utc, from_state, to_state, trigger, "
                      "step_id) VALUES (?,?,?,?,?,?,?)",
                      (self.run_id, t_robot_s, _utc_now(), from_state, to_state, trigger, step_id))

    def receive(self, doc: Document) -> None:
        """The journal's subscription to the engine's documents: each transition one row."""
        self.record_transition(doc.source, doc.dest, doc.trigger, doc.t_robot_s, doc.step_id)

    def transitions(self, run_id: int | None = None, last: int | None = None) -> list[dict[str, Any]]:
        """Journaled transitions, oldest first (only the ``last`` n if given)."""
        sql = "SELECT id, run_id, t_robot_s, t_wall_utc, from_state, to_state, trigger, step_id FROM transitions"
        args: tuple[Any, ...] = (run_id,) if run_id is not None else ()
        sql += " WHERE run_id=?" if run_id is not None else ""
        if last is not None:
            sql = f"SELECT * FROM ({sql} ORDER BY id DESC LIMIT {int(last)})"
        rows = self._q(sql + " ORDER BY id", args)
        keys = ("id", "run_id", "t_robot_s", "t_wall_utc", "from_state", "to_state", "trigger", "step_id")
        return [dict(zip(keys, r)) for r in rows]

    def record_fault(self, kind: str, message: str, t_robot_s: float | None = None, step_id: int | None = None,
                     policy_action: str | None = None, raw: Any = None) -> int:
        """Journal a fault with the raw F/T data of its last seconds; returns the fault id.

        ``raw``: a ``WrenchBlock`` or an (N, 7) array of t_s, Fx, Fy, Fz (N), Tx, Ty, Tz (N m).
        """
        blob: tuple[Any, Any, Any, Any] = (None, None, None, None)
        if raw is not None:
            blob = encode_array(wrench_to_array(raw))
        with self.transaction() as c:
            cur = c.execute("INSERT INTO faults (run_id, kind, t_robot_s, t_wall_utc, step_id, message, "
                            "policy_action, raw_dtype, raw_shape, raw_sha256, raw) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                            (self.run_id, kind, t_robot_s, _utc_now(), step_id, message, policy_action, *blob))
            crash_point("record_fault:before_commit")
            return int(cur.lastrowid)

    def faults(self, step_id: int | None = None, with_raw: bool = True) -> list[FaultRecord]:
        """Faults (of one step, if given), oldest first; raw F/T data verified, or left out
        (``raw=None``) with ``with_raw=False`` — cheap for counting retries."""
        raw_cols = "raw_dtype, raw_shape, raw_sha256, raw" if with_raw else "NULL, NULL, NULL, NULL"
        sql = (f"SELECT fault_id, kind, t_robot_s, t_wall_utc, step_id, message, policy_action, {raw_cols}, run_id "
               f"FROM faults" + (" WHERE step_id=?" if step_id is not None else "") + " ORDER BY fault_id")
        out = []
        for r in self._q(sql, (int(step_id),) if step_id is not None else ()):
            raw = None if r[10] is None else decode_array(r[7], r[8], r[9], r[10], f"fault {r[0]} raw F/T")
            out.append(FaultRecord(fault_id=r[0], kind=r[1], t_robot_s=r[2], t_wall_utc=r[3], step_id=r[4],
                                   message=r[5], policy_action=r[6], raw=raw, run_id=r[11]))
        return out

    def last_step_of_run(self, run_id: int) -> StepRecord | None:
        """The step run ``run_id`` began last (None: it began none): where a killed run was.
        A step that a later run began again belongs to that run now."""
        rows = self._q("SELECT step_id FROM steps WHERE run_id = ? AND started_utc IS NOT NULL "
                       "ORDER BY started_utc DESC LIMIT 1", (int(run_id),))
        return self.step(int(rows[0][0])) if rows else None

    def runs(self) -> list[dict[str, Any]]:
        """Every run (one controller process each: the first, then each resume), oldest first."""
        keys = ("run_id", "mode", "started_utc", "pid", "host", "ended_utc", "end_status")
        return [dict(zip(keys, r)) for r in self._q(f"SELECT {', '.join(keys)} FROM runs ORDER BY run_id")]

    def log_event(self, kind: str, record: Mapping[str, Any] | None = None, t_robot_s: float | None = None) -> int:
        """A free-form JSON record (decisions, warnings, progress) in the session log."""
        with self.transaction() as c:
            cur = c.execute("INSERT INTO events (run_id, t_wall_utc, t_robot_s, kind, record) VALUES (?,?,?,?,?)",
                            (self.run_id, _utc_now(), t_robot_s, kind, to_json(dict(record or {}))))
            return int(cur.lastrowid)

    def events(self, kind: str | None = None, after_id: int = 0) -> list[dict[str, Any]]:
        """Events with id > ``after_id`` (for ``status --follow``), oldest first."""
        sql = "SELECT id, run_id, t_wall_utc, t_robot_s, kind, record FROM events WHERE id>?"
        args: list[Any] = [after_id]
        if kind is not None:
            sql += " AND kind=?"
            args.append(kind)
        return [{"id": r[0], "run_id": r[1], "t_wall_utc": r[2], "t_robot_s": r[3], "kind": r[4],
                 "record": _json(r[5], f"event {r[0]}")} for r in self._q(sql + " ORDER BY id", args)]

    # ------------------------------------------------------------------ robot time
    @staticmethod
    def _add_robot_time(c: sqlite3.Connection, category: str, seconds: float) -> None:
        if not np.isfinite(seconds) or seconds < 0:
            raise ValueError(f"robot time must be finite and >= 0 s, got {seconds}")
        c.execute("INSERT INTO robot_time VALUES (?,?) ON CONFLICT(category) DO UPDATE SET "
                  "seconds = seconds + excluded.seconds", (category, seconds))

    def add_robot_time(self, category: str, seconds: float) -> None:
        """Account robot time (s) to ``category`` (travel, sweep, recovery, ...); probing
        time is added by :meth:`commit_step` itself."""
        with self.transaction() as c:
            self._add_robot_time(c, category, seconds)

    def robot_time_s(self) -> dict[str, float]:
        """Robot time per category and ``total`` (s)."""
        out = {k: float(v) for k, v in self._q("SELECT category, seconds FROM robot_time ORDER BY category")}
        out["total"] = float(sum(out.values()))
        return out

    # ------------------------------------------------------------------ models & artifacts
    def _rel(self, path: str | os.PathLike[str]) -> str:
        p = Path(path).resolve()
        try:
            return str(p.relative_to(self.session_dir.resolve()))
        except ValueError:
            return str(p)

    def record_model(self, region: int, member: int, path: str | os.PathLike[str],
                     metrics: Mapping[str, Any] | None = None, sha256: str | None = None) -> str:
        """Register a model file (written atomically before); returns its sha256."""
        digest = sha256 or sha256_file(path)
        with self.transaction() as c:
            c.execute("INSERT INTO models VALUES (?,?,?,?,?,?) ON CONFLICT(region, member) DO UPDATE SET "
                      "path=excluded.path, sha256=excluded.sha256, metrics=excluded.metrics, "
                      "recorded_utc=excluded.recorded_utc",
                      (int(region), int(member), self._rel(path), digest, to_json(dict(metrics or {})), _utc_now()))
        return digest

    def models(self) -> list[dict[str, Any]]:
        return [{"region": r[0], "member": r[1], "path": r[2], "sha256": r[3], "metrics": _json(r[4], "model metrics")}
                for r in self._q("SELECT region, member, path, sha256, metrics FROM models ORDER BY region, member")]

    def record_artifact(self, name: str, path: str | os.PathLike[str], sha256: str | None = None) -> str:
        digest = sha256 or sha256_file(path)
        with self.transaction() as c:
            c.execute("INSERT INTO artifacts VALUES (?,?,?,?) ON CONFLICT(name) DO UPDATE SET path=excluded.path, "
                      "sha256=excluded.sha256, recorded_utc=excluded.recorded_utc",
                      (name, self._rel(path), digest, _utc_now()))
        return digest

    def artifacts(self) -> list[dict[str, Any]]:
        return [{"name": r[0], "path": r[1], "sha256": r[2]}
                for r in self._q("SELECT name, path, sha256 FROM artifacts ORDER BY name")]

    def verify_files(self) -> list[str]:
        """Models and artifacts whose file is missing or differs from its recorded hash."""
        problems = []
        for kind, rows in (("model", self.models()), ("artifact", self.artifacts())):
            for r in rows:
                p = Path(r["path"])
                p = p if p.is_absolute() else self.session_dir / p
                if not p.exists():
                    problems.append(f"{kind} {p}: missing")
                elif sha256_file(p) != r["sha256"]:
                    problems.append(f"{kind} {p}: changed since it was recorded")
        return problems

    # ------------------------------------------------------------------ whole-journal checks
    def verify(self) -> list[str]:
        """Full check: SQLite's integrity check and foreign keys, every JSON record, every
        phase hash, every done step's arrays and every fault blob. Returns the problems
        found, each naming the damaged part (empty = sound). Reads one consistent snapshot
        (safe while a controller writes); never raises on damage."""
        problems: list[str] = []

        def check(what: str, read: Callable[[], Any]) -> Any:
            try:
                return read()
            except (JournalError, sqlite3.DatabaseError, ValueError, KeyError, TypeError, IndexError) as exc:
                problems.append(f"{what}: {exc}" if what not in str(exc) else str(exc))
                return None

        in_snapshot = self._conn is not None and not self._conn.in_transaction
        if in_snapshot:
            check("journal", lambda: self._q("BEGIN"))
        try:
            ic = check("sqlite integrity check", lambda: [r[0] for r in self._q("PRAGMA integrity_check")])
            if ic is not None and ic != ["ok"]:
                problems.extend(f"sqlite: {m}" for m in ic[:20])
            fk = check("sqlite foreign keys", lambda: self._q("PRAGMA foreign_key_check"))
            problems.extend(f"foreign key: {tuple(r)}" for r in (fk or [])[:20])
            check("session record", self.session)
            check("provenance", self.provenance)
            check("events", self.events)
            check("models", self.models)
            check("transitions", self.transitions)
            for p in check("phases", self.phases) or []:
                check(f"phase {p['name']!r} round {p['round']}", lambda p=p: self.phase(p["name"], p["round"]))
            for rec in check("steps", lambda: self.steps(statuses=["done"])) or []:
                check(f"step {rec.step_id}", lambda rec=rec: self._load_step_result(rec))
            n_orphans = check("step arrays", lambda: self._q(
                "SELECT count(*) FROM step_arrays a JOIN steps s USING (step_id) WHERE s.status != 'done'")[0][0])
            if n_orphans:
                problems.append(f"{n_orphans} step arrays belong to steps that are not done")
            check("faults", self.faults)
        finally:
            if in_snapshot and self._conn is not None and self._conn.in_transaction:
                with contextlib.suppress(sqlite3.Error):
                    self._conn.execute("COMMIT")
        return problems

    def summary(self) -> dict[str, Any]:
        """A snapshot for ``elastoprobe status``: session, step counts, phases, robot time,
        last transition and fault, runs."""
        last_t = self._q("SELECT from_state, to_state, trigger, t_robot_s, t_wall_utc, step_id FROM transitions "
                         "ORDER BY id DESC LIMIT 1")
        last_f = self._q("SELECT kind, message, t_wall_utc, step_id FROM faults ORDER BY fault_id DESC LIMIT 1")
        return {
            "session": self.session(),
            "steps": self.status_counts(),
            "phases": self.phases(),
            "robot_time_s": self.robot_time_s(),
            "last_transition": dict(zip(("from", "to", "trigger", "t_robot_s", "t_wall_utc", "step_id"),
                                        last_t[0])) if last_t else None,
            "last_fault": dict(zip(("kind", "message", "t_wall_utc", "step_id"), last_f[0])) if last_f else None,
            "runs": self.runs(),
        }


def describe_damage(problems: Sequence[str], limit: int = 8) -> str:
    """One message for the damage :meth:`Journal.verify` found (the first ``limit`` parts)."""
    shown = "; ".join(problems[:limit])
    more = f"; and {len(problems) - limit} more" if len(problems) > limit else ""
    return f"the session journal is damaged: {shown}{more}"


# ============================================================================ row helpers
_STEP_PLAN_COLS = "step_id, target_index, px, py, pz, nx, ny, nz, tx, ty, tz, angle_deg, force_n, order_index"
_INSERT_STEP = ("INSERT INTO steps (step_id, phase_id, phase, round, target_index, px, py, pz, nx, ny, nz, "
                "tx, ty, tz, angle_deg, force_n, order_index) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)")


def _step_row(s: dict[str, Any], phase_id: int, phase: str, round: int) -> tuple[Any, ...]:
    return (s["step_id"], phase_id, phase, int(round), s["target_index"], *s["point_mm"], *s["normal"], *s["t"],
            s["angle_deg"], s["force_n"], s["order_index"])


def _plan_from_row(r: Sequence[Any]) -> StepPlan:
    return StepPlan(step_id=int(r[0]), target_index=int(r[1]), point_mm=np.array(r[2:5], dtype=float),
                    normal=np.array(r[5:8], dtype=float), t=np.array(r[8:11], dtype=float),
                    angle_deg=float(r[11]), force_n=float(r[12]), order_index=int(r[13]))


def _phase_digest(outputs_json: str, array_sums: Mapping[str, str], steps: list[dict[str, Any]]) -> str:
    return _sha256(to_json({"outputs": outputs_json, "arrays": dict(sorted(array_sums.items())),
                            "steps": steps}).encode("utf-8"))


def _split_sql(script: str) -> list[str]:
    """Split the schema into statements (triggers contain ';' inside BEGIN ... END)."""
    statements, current = [], []
    for line in script.splitlines():
        stripped = line.split("--", 1)[0].rstrip()
        if not stripped:
            continue
        current.append(stripped)
        text = "\n".join(current)
        if stripped.endswith(";") and (not text.lstrip().upper().startswith("CREATE TRIGGER")
                                       or stripped.upper().endswith("END;")):
            statements.append(text)
            current = []
    if current:
        statements.append("\n".join(current))
    return statements


def wrench_to_array(raw: Any) -> np.ndarray:
    """(N, 7) float64 ``t_s, Fx, Fy, Fz, Tx, Ty, Tz`` from a WrenchBlock or such an array."""
    if hasattr(raw, "force_n") and hasattr(raw, "torque_nm") and hasattr(raw, "t_s"):
        return np.column_stack([np.asarray(raw.t_s, dtype=float), np.asarray(raw.force_n, dtype=float),
                                np.asarray(raw.torque_nm, dtype=float)]).reshape(-1, 7)
    a = np.asarray(raw, dtype=float)
    if a.ndim != 2 or a.shape[1] != 7:
        raise ValueError(f"raw F/T must be (N, 7) t_s, Fx..Tz, got {a.shape}")
    return a


def _first_difference(old_text: str | None, new_data: bytes) -> str:
    """`` (first difference at line k: 'old' -> 'new')`` to help the user see what changed."""
    if old_text is None:
        return ""
    new_text = new_data.decode("utf-8", errors="replace")
    old_lines, new_lines = old_text.splitlines(), new_text.splitlines()
    for k in range(max(len(old_lines), len(new_lines))):
        a = old_lines[k] if k < len(old_lines) else "<end of file>"
        b = new_lines[k] if k < len(new_lines) else "<end of file>"
        if a != b:
            return f" (first difference at line {k + 1}: {a.strip()[:60]!r} -> {b.strip()[:60]!r})"
    return ""


def newest_phase(j: Journal, name: str) -> tuple[int, PhaseRecord | None]:
    """(round, record) of the newest committed round of phase ``name`` (rounds count up
    from 0 without gaps); (-1, None) if there is none."""
    r, rec = 0, None
    while (nxt := j.phase(name, r)) is not None:
        rec, r = nxt, r + 1
    return r - 1, rec
