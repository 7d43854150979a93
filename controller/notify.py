"""Telling the operator, and watching the disk, during an unattended session (docs/design.md §6, §11).

:class:`Notifier` runs the user's command (``notify.command`` in the cell file, an argv
list — never through a shell) with a JSON payload on stdin when the session pauses,
faults, finishes, or will not finish by its deadline (``finish_by``). It never raises
into the controller: a missing program, a non-zero exit, a hang (killed after
``timeout_s`` with its whole process group) are returned as a :class:`NotifyResult` and
handed to the optional ``log`` callback — a notification that fails must not stop a
night's probing.

:class:`DiskWatch` says "ok", "warn" or "pause" from the free space of the session's
disk, so the session pauses (finishing the step, saving everything) before the disk
fills and the journal would have to refuse a write.

Payload (UTF-8 JSON, one object, then EOF)::

    {"event": "fault", "session_dir": "/data/sessions/2024-05-01-ball", "plan": "ball",
     "time_utc": "2024-05-02T03:14:15+00:00", "t_robot_s": 12345.6,
     "counts": {"planned": 10, "done": 300, ...}, "message": "force spike at step 301",
     "extra": {...}}

The command also gets ``ELASTOPROBE_EVENT`` and ``ELASTOPROBE_SESSION_DIR`` in its
environment, for scripts that would rather not parse JSON.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Mapping

from .journal import DEFAULT_MIN_FREE_BYTES

if TYPE_CHECKING:
    from .core.config import NotifySpec

EVENTS = ("pause", "fault", "finish", "finish_by")
STDERR_TAIL_BYTES = 2000
KILL_GRACE_S = 5.0          # after SIGKILL, how long to wait for the process to be reaped

LogFn = Callable[[str, Mapping[str, Any]], None]


@dataclass(frozen=True)
class NotifyResult:
    """What became of one notification. ``ok``: the command ran and exited 0."""

    event: str
    ran: bool                     # a process was started
    ok: bool
    skipped: str | None = None    # why nothing ran (no command configured, event not subscribed)
    returncode: int | None = None
    timed_out: bool = False
    error: str | None = None      # could not start, or failed (non-zero exit, timeout)
    duration_s: float = 0.0
    stderr_tail: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def build_payload(event: str, session_dir: str | os.PathLike[str], plan: str | None,
                  counts: Mapping[str, int] | None, message: str, t_robot_s: float | None = None,
                  extra: Mapping[str, Any] | None = None, time_utc: str | None = None) -> dict[str, Any]:
    """The JSON object the command reads on stdin (see the module docstring)."""
    return {"event": event, "session_dir": os.fspath(session_dir), "plan": plan,
            "time_utc": time_utc or _utc_now(),
            "t_robot_s": None if t_robot_s is None else float(t_robot_s),
            "counts": {k: int(v) for k, v in (counts or {}).items()}, "message": str(message),
            "extra": dict(extra or {})}


class Notifier:
    """Runs the cell's notify command for the events it subscribes to.

    ``spec`` None (no ``notify`` in the cell file) makes every call a no-op that says so.
    ``log(kind, record)`` (e.g. ``journal.log_event``) receives every attempt's result;
    errors raised by ``log`` itself are swallowed too. Calls block for at most
    ``spec.timeout_s`` plus a few seconds of reaping.
    """

    def __init__(self, spec: "NotifySpec | None", log: LogFn | None = None,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.spec = spec
        self._log = log
        self._monotonic = monotonic

    def wants(self, event: str) -> bool:
        return self.spec is not None and event in self.spec.on

    def notify(self, event: str, session_dir: str | os.PathLike[str], *, plan: str | None = None,
               counts: Mapping[str, int] | None = None, message: str = "", t_robot_s: float | None = None,
               extra: Mapping[str, Any] | None = None) -> NotifyResult:
        """Send one notification; never raises (the result says what happened)."""
        try:
            result = self._notify(event, session_dir, plan, counts, message, t_robot_s, extra)
        except Exception as exc:      # e.g. a payload that is not JSON-able: report, do not raise
            result = NotifyResult(event=event, ran=False, ok=False, error=f"{type(exc).__name__}: {exc}")
        self._record(result)
        return result

    def _notify(self, event: str, session_dir: str | os.PathLike[str], plan: str | None,
                counts: Mapping[str, int] | None, message: str, t_robot_s: float | None,
                extra: Mapping[str, Any] | None) -> NotifyResult:
        if event not in EVENTS:
            return NotifyResult(event=event, ran=False, ok=False, error=f"unknown event {event!r} (one of {EVENTS})")
        if self.spec is None:
            return NotifyResult(event=event, ran=False, ok=False, skipped="no notify command configured")
        if event not in self.spec.on:
            return NotifyResult(event=event, ran=False, ok=False, skipped=f"not subscribed to {event!r}")
        payload = build_payload(event, session_dir, plan, counts, message, t_robot_s, extra)
        data = json.dumps(payload, allow_nan=False, ensure_ascii=False).encode("utf-8")
        env = dict(os.environ, ELASTOPROBE_EVENT=event, ELASTOPROBE_SESSION_DIR=os.fspath(session_dir))
        return run_command(list(self.spec.command), data, float(self.spec.timeout_s), event, env, self._monotonic)

    def _record(self, result: NotifyResult) -> None:
        if self._log is None:
            return
        try:
            self._log("notify", result.to_dict())
        except Exception:   # the log is best effort here; the result is still returned
            pass


def run_command(argv: list[str], stdin_data: bytes, timeout_s: float, event: str = "",
                env: Mapping[str, str] | None = None,
                monotonic: Callable[[], float] = time.monotonic) -> NotifyResult:
    """Run ``argv`` (no shell) with ``stdin_data`` on stdin, at most ``timeout_s``.

    The command runs in its own session (process group) so that on timeout the group —
    the command and anything it started — is killed. stdout is discarded; stderr goes to
    a temporary file (never a pipe, which a surviving grandchild could hold open and
    hang us) and its tail is returned.
    """
    t0 = monotonic()
    with tempfile.TemporaryFile() as err:
        try:
            proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=err,
                                    env=dict(env) if env is not None else None, start_new_session=True,
                                    close_fds=True)
        except (OSError, ValueError) as exc:
            return NotifyResult(event=event, ran=False, ok=False, error=f"cannot run {argv[0]!r}: {exc}",
                                duration_s=monotonic() - t0)
        timed_out = False
        try:
            proc.communicate(stdin_data, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            _kill_group(proc)
        except OSError:
            # stdin closed early by the command (it did not want the payload): wait for its exit.
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                timed_out = True
                _kill_group(proc)
        rc = proc.returncode
        err.seek(0, os.SEEK_END)
        size = err.tell()
        err.seek(max(0, size - STDERR_TAIL_BYTES))
        tail = err.read().decode("utf-8", errors="replace")
    duration = monotonic() - t0
    if timed_out:
        return NotifyResult(event=event, ran=True, ok=False, returncode=rc, timed_out=True,
                            error=f"{argv[0]!r} did not finish within {timeout_s:g} s; killed",
                            duration_s=duration, stderr_tail=tail)
    ok = rc == 0
    return NotifyResult(event=event, ran=True, ok=ok, returncode=rc, duration_s=duration, stderr_tail=tail,
                        error=None if ok else f"{argv[0]!r} exited with status {rc}")


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    """SIGKILL the command's process group (we started it in its own session), then reap it."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    except PermissionError:
        proc.kill()
    try:
        proc.wait(timeout=KILL_GRACE_S)
    except subprocess.TimeoutExpired:
        pass
    if proc.stdin is not None:
        try:
            proc.stdin.close()
        except OSError:
            pass


# ============================================================================ disk watch
DiskLevel = Literal["ok", "warn", "pause"]


@dataclass(frozen=True)
class DiskStatus:
    """``level``: ok, warn (tell the operator) or pause (stop before the disk fills)."""

    level: DiskLevel
    free_bytes: int | None
    message: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class DiskWatch:
    """Free space of the session's disk against two thresholds (bytes available to us).

    ``check(next_write_bytes)`` is cheap (one statvfs): call it before each step with the
    bytes the step will write (e.g. scans x samples x 8 plus overhead), so the session
    pauses while the step still fits above ``min_free_bytes`` — the journal's own floor
    for opening, so a resume works once space is freed. A statvfs that fails (disk gone,
    I/O error) says "pause": nothing can be trusted to be saved.
    """

    def __init__(self, session_dir: str | os.PathLike[str], min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
                 warn_free_bytes: int | None = None,
                 statvfs: Callable[[str], Any] = os.statvfs) -> None:
        warn = 2 * min_free_bytes if warn_free_bytes is None else warn_free_bytes
        if min_free_bytes < 0 or warn < min_free_bytes:
            raise ValueError(f"need 0 <= min_free_bytes ({min_free_bytes}) <= warn_free_bytes ({warn})")
        self.session_dir = Path(session_dir)
        self.min_free_bytes = int(min_free_bytes)
        self.warn_free_bytes = int(warn)
        self._statvfs = statvfs
        self.last: DiskStatus | None = None

    def free_bytes(self) -> int:
        """Bytes an unprivileged writer may still use on the session's file system."""
        st = self._statvfs(os.fspath(self._existing_dir()))
        return int(st.f_bavail) * int(st.f_frsize)

    def _existing_dir(self) -> Path:
        # Before the session directory exists, the disk that will hold it is its nearest parent's.
        p = self.session_dir
        while not p.exists() and p != p.parent:
            p = p.parent
        return p

    def check(self, next_write_bytes: int = 0) -> DiskStatus:
        """ok / warn / pause, counting ``next_write_bytes`` about to be written."""
        try:
            free = self.free_bytes()
        except OSError as exc:
            status = DiskStatus("pause", None, f"cannot read the free space of {self.session_dir}: {exc}")
            self.last = status
            return status
        after = free - max(0, int(next_write_bytes))
        mib = 2 ** 20
        if after < self.min_free_bytes:
            status = DiskStatus("pause", free, f"{free / mib:.0f} MiB free on the session's disk; "
                                f"pausing before it falls below {self.min_free_bytes / mib:.0f} MiB "
                                f"(free space, then resume)")
        elif after < self.warn_free_bytes:
            status = DiskStatus("warn", free, f"{free / mib:.0f} MiB free on the session's disk "
                                f"(warning below {self.warn_free_bytes / mib:.0f} MiB, pause below "
                                f"{self.min_free_bytes / mib:.0f} MiB)")
        else:
            status = DiskStatus("ok", free, f"{free / mib:.0f} MiB free")
        self.last = status
        return status

    def preflight(self, expected_bytes: int = 0) -> DiskStatus:
        """Before starting (or resuming): is there room for the whole plan's data
        (``expected_bytes``, e.g. steps x bytes per step) above the pause threshold?
        "pause" here means: do not start; "warn": the plan will not fit, it will pause
        part-way unless space is freed."""
        status = self.check(0)
        if status.level == "pause" or status.free_bytes is None:
            return status
        if status.free_bytes - int(expected_bytes) < self.min_free_bytes:
            mib = 2 ** 20
            status = DiskStatus("warn", status.free_bytes,
                                f"{status.free_bytes / mib:.0f} MiB free but the plan needs about "
                                f"{expected_bytes / mib:.0f} MiB above the {self.min_free_bytes / mib:.0f} MiB "
                                f"floor: the session will pause part-way unless space is freed")
            self.last = status
        return status
