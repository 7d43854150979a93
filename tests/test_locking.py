"""Session and cell locks: one holder, named in the refusal; freed when the holder is SIGKILLed."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from elastoprobe.controller.locking import (
    CellLock, LockHeld, SessionLock, read_holder, session_lock_holder,
)

HOLDER = textwrap.dedent("""
    import sys, time
    from elastoprobe.controller.locking import SessionLock, CellLock
    kind, where = sys.argv[1], sys.argv[2]
    lock = SessionLock(where) if kind == "session" else CellLock("ur5e-lab", lock_dir=where)
    lock.acquire()
    print("locked", flush=True)
    time.sleep(60)          # bounded: the test kills it long before
""")


def _start_holder(kind: str, where: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, kind, str(where)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    return proc


@pytest.mark.parametrize("kind", ["session", "cell"])
def test_second_process_refused_then_freed_by_sigkill(tmp_path: Path, kind: str) -> None:
    proc = _start_holder(kind, tmp_path)
    try:
        make = (lambda: SessionLock(tmp_path)) if kind == "session" else (lambda: CellLock("ur5e-lab", tmp_path))
        with pytest.raises(LockHeld, match=f"in use by pid {proc.pid} on ") as exc:
            make().acquire()
        assert exc.value.holder["pid"] == proc.pid and exc.value.holder["alive"] is True
        assert exc.value.exit_code == 2
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    lock = make().acquire()           # the kernel released the dead holder's flock
    try:
        assert lock.took_over_from is not None and lock.took_over_from["pid"] == proc.pid
        assert lock.took_over_from["alive"] is False
        assert read_holder(lock.path)["pid"] == os.getpid()
    finally:
        lock.release()


def test_same_process_twice_is_refused_and_release_clears(tmp_path: Path) -> None:
    with SessionLock(tmp_path) as first:
        assert session_lock_holder(tmp_path)["pid"] == os.getpid()
        with pytest.raises(LockHeld):
            SessionLock(tmp_path).acquire()
        assert first.held
    assert session_lock_holder(tmp_path) is None       # released cleanly: empty record
    again = SessionLock(tmp_path).acquire()
    assert again.took_over_from is None
    again.release()
    again.release()                                     # idempotent


def test_cell_names_are_made_safe(tmp_path: Path) -> None:
    a = CellLock("lab/ur5e #1", tmp_path)
    assert a.path.parent == tmp_path and "/" not in a.path.name[len("cell-"):]
    with a, pytest.raises(LockHeld, match="cell 'lab/ur5e #1'"):
        CellLock("lab/ur5e #1", tmp_path).acquire()
    with pytest.raises(ValueError):
        CellLock("  ", tmp_path)


def test_forked_child_does_not_keep_the_lock(tmp_path: Path) -> None:
    """A child forked while the lock is held (e.g. a device driver process) must not hold it."""
    lock = SessionLock(tmp_path).acquire()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:                                       # child: outlive the parent's release a bit
        os.write(w, b"1")                              # the at-fork hooks have run by now
        time.sleep(3.0)
        os._exit(0)
    try:
        assert os.read(r, 1) == b"1"
        lock.release()
        other = SessionLock(tmp_path).acquire()        # would fail if the child held the flock
        other.release()
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(r)
        os.close(w)
