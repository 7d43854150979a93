"""Operator requests by signal (DESIGN §11): the handlers only set flags.

SIGINT once or SIGTERM: deferred pause — finish the step in flight, unload,
retract, save, exit 3. SIGINT a second time: safe stop now — stop the arm,
unload, retract, save, exit 3. ``elastoprobe pause DIR`` and ``elastoprobe stop
DIR`` send these signals to the controller holding the session lock.
"""
from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

from .errors import InputError
from .locking import session_lock_holder


@dataclass
class OperatorFlags:
    pause_requested: bool = False
    stop_now: bool = False
    interrupts: int = 0
    _previous: dict[int, object] = field(default_factory=dict)

    def _on_sigint(self, signum: int, frame: FrameType | None) -> None:
        self.interrupts += 1
        self.pause_requested = True
        if self.interrupts >= 2:
            self.stop_now = True

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        self.pause_requested = True

    def install(self) -> "OperatorFlags":
        self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._on_sigint)
        self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._on_sigterm)
        return self

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)   # type: ignore[arg-type]
        self._previous.clear()


def _holder_pid(session_dir: Path) -> int:
    holder = session_lock_holder(session_dir)
    if not holder or not holder.get("pid"):
        raise InputError("no controller is running this session (no lock holder)", path=str(session_dir))
    pid = int(holder["pid"])
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        raise InputError(f"the controller (pid {pid}) is not running", path=str(session_dir)) from None
    return pid


def request_pause(session_dir: Path) -> int:
    """Ask the running controller to pause after the step in flight; returns its pid."""
    pid = _holder_pid(session_dir)
    os.kill(pid, signal.SIGTERM)
    return pid


def request_stop(session_dir: Path) -> int:
    """Ask the running controller to stop safely now (SIGINT twice); returns its pid."""
    pid = _holder_pid(session_dir)
    os.kill(pid, signal.SIGINT)
    time.sleep(0.05)
    os.kill(pid, signal.SIGINT)
    return pid
