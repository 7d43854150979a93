"""One controller per session directory and per cell: advisory ``flock`` locks with a holder record.

A lock is an exclusive ``fcntl.flock`` on a small file that also holds, as JSON, who
holds it (pid, host, start time, command line). The kernel drops a flock when the
last descriptor of its open file goes away, so a holder killed with SIGKILL frees
the lock at once: a later controller takes it over and can see (``took_over_from``)
the record the dead holder left behind. The file is never deleted (unlinking a lock
file races with a process that has just opened it).

Forks: a child created with ``fork`` (without exec) inherits the descriptor and would
keep the lock alive after the parent dies; an at-fork hook closes held lock
descriptors in every child, so only the process that took a lock holds it.
"""
from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import re
import socket
import sys
import tempfile
import weakref
from pathlib import Path
from typing import Any

from .core.errors import InputError

SESSION_LOCK_NAME = "session.lock"

_held: "weakref.WeakSet[_FileLock]" = weakref.WeakSet()


def _close_held_in_child() -> None:
    for lock in list(_held):
        lock._forget_in_child()


os.register_at_fork(after_in_child=_close_held_in_child)


class LockHeld(InputError):
    """The lock is held by another live process (exit code 2: the invocation cannot proceed)."""

    def __init__(self, what: str, lock_path: Path, holder: dict[str, Any] | None) -> None:
        self.holder = holder or {}
        self.lock_path = lock_path
        if holder:
            who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}, "
                   f"since {holder.get('started_utc', '?')}")
        else:
            who = "another process (no holder record yet)"
        super().__init__(f"{what} is in use by {who}; stop that controller first "
                         f"(lock file {lock_path})")


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def read_holder(lock_path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The holder record in a lock file, or None if empty/missing/garbled.

    Adds ``alive``: whether that controller still holds the lock (only decidable on this
    host; else None) — see :func:`holder_alive`. Reading never takes the lock, so
    ``elastoprobe status`` cannot get in a controller's way.
    """
    try:
        text = Path(lock_path).read_text(encoding="utf-8")
        record = json.loads(text) if text.strip() else None
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict):
        return None
    alive: bool | None = None
    if record.get("host") == socket.gethostname() and isinstance(record.get("pid"), int):
        alive = holder_alive(Path(lock_path), record)
    record["alive"] = alive
    return record


def holder_alive(lock_path: Path, record: dict[str, Any]) -> bool:
    """Whether the process a (local) holder record names still holds the lock.

    A record outlives its holder after a kill -9, and the pid may be reused by another
    process since; so the lock itself is asked first (the kernel's table of flocks,
    /proc/locks, without taking it), then the pid: it must run and have started no later
    than it took the lock (psutil), or it is another process that got the same pid."""
    holders = _flock_holders(lock_path)
    if holders is not None and int(record["pid"]) not in holders:
        return False
    return _same_process(int(record["pid"]), record.get("started_utc"))


def _flock_holders(lock_path: Path) -> set[int] | None:
    """The pids holding a flock on ``lock_path`` (Linux /proc/locks); None if unknown."""
    try:
        st = os.stat(lock_path)
        table = Path("/proc/locks").read_text()
    except OSError:
        return None
    ident = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    out = set()
    for line in table.splitlines():      # "1: FLOCK ADVISORY WRITE <pid> <maj:min:inode> 0 EOF"
        parts = line.split()
        if parts[1:2] == ["FLOCK"] and len(parts) > 5 and parts[5] == ident and parts[4].isdigit():
            out.add(int(parts[4]))
    return out


def _same_process(pid: int, started_utc: Any) -> bool:
    import psutil

    try:
        proc = psutil.Process(pid)
        created = proc.create_time()
        if proc.status() == psutil.STATUS_ZOMBIE:
            return False
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return False
    except psutil.AccessDenied:
        return True     # exists, owned by someone else: cannot tell more
    try:
        taken = _dt.datetime.fromisoformat(str(started_utc)).timestamp()
    except ValueError:
        return True
    return created <= taken + 2.0       # the record is written to the second


class _FileLock:
    """An exclusive, non-blocking flock on ``path`` with a JSON holder record."""

    def __init__(self, path: Path, what: str) -> None:
        self.path = path
        self.what = what
        self._fd: int | None = None
        self.took_over_from: dict[str, Any] | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "_FileLock":
        """Take the lock now or raise :class:`LockHeld` naming the holder (never waits)."""
        if self._fd is not None:
            raise RuntimeError(f"{self.what}: lock already held by this object")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise LockHeld(self.what, self.path, read_holder(self.path)) from None
        except BaseException:
            os.close(fd)
            raise
        try:
            # A non-empty record under a free lock was left by a holder that died.
            previous = read_holder(self.path)
            self.took_over_from = previous
            record = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": _utc_now(),
                      "argv": sys.argv[:8], "what": self.what}
            data = json.dumps(record).encode("utf-8")
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        _held.add(self)
        return self

    def release(self) -> None:
        """Clear the holder record and drop the lock (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        _held.discard(self)
        try:
            os.ftruncate(fd, 0)   # an empty record means "released cleanly"
        except OSError:
            pass
        finally:
            os.close(fd)          # closing the only descriptor releases the flock

    def _forget_in_child(self) -> None:
        # In a forked child: close our copy of the descriptor without touching the
        # record; the parent keeps the lock.
        fd, self._fd = self._fd, None
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "_FileLock":
        if self._fd is None:
            self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:   # pragma: no cover - safety net only
        fd = getattr(self, "_fd", None)
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass


class SessionLock(_FileLock):
    """One controller per session directory: ``DIR/session.lock``.

    ``with SessionLock(dir): ...`` or ``lock = SessionLock(dir).acquire(); ...; lock.release()``.
    """

    def __init__(self, session_dir: str | os.PathLike[str]) -> None:
        d = Path(session_dir)
        d.mkdir(parents=True, exist_ok=True)
        super().__init__(d / SESSION_LOCK_NAME, f"session {d}")


def default_lock_dir() -> Path:
    """Where cell locks live: ``$ELASTOPROBE_LOCK_DIR``, else ``<tmp>/elastoprobe-locks``.

    The temporary directory is shared by all users of the machine, which is what a
    physical cell needs (two users must not drive one robot).
    """
    env = os.environ.get("ELASTOPROBE_LOCK_DIR")
    return Path(env) if env else Path(tempfile.gettempdir()) / "elastoprobe-locks"


_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


class CellLock(_FileLock):
    """One controller per cell (robot): ``<lock dir>/cell-<name>.lock``."""

    def __init__(self, cell_name: str, lock_dir: str | os.PathLike[str] | None = None) -> None:
        if not cell_name.strip():
            raise ValueError("cell name is empty")
        d = Path(lock_dir) if lock_dir is not None else default_lock_dir()
        if not d.exists():
            d.mkdir(parents=True, exist_ok=True)
            try:
                os.chmod(d, 0o1777)   # shared by users, like /tmp (sticky)
            except OSError:
                pass
        safe = _SAFE_NAME.sub("_", cell_name.strip())
        super().__init__(d / f"cell-{safe}.lock", f"cell {cell_name!r}")


def session_lock_holder(session_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
    """Who holds (or last held, if ``alive`` is False) a session's lock; for status/pause/stop."""
    return read_holder(Path(session_dir) / SESSION_LOCK_NAME)
