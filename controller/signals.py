"""Operator requests by signal (DESIGN §11), honoured in every phase.

SIGINT once or SIGTERM: pause — finish the step in flight, unload, retract, save,
exit 3. SIGINT a second time: safe stop now — stop the arm, unload, retract, save,
exit 3. ``elastoprobe pause DIR`` and ``elastoprobe stop DIR`` send these signals to
the controller holding the session lock.

Two kinds of work answer a request differently:

- Work with the arm or the journal (a contact, a sweep, a journal transaction, a state
  transition) runs inside :func:`deferred_interrupts`: the handler only sets flags, and
  the work ends at its own checkpoint (the contact's last level; the sweep polls the
  flags at every control tick).
- Computation (planning, learning, training, the report) runs inside
  :meth:`OperatorFlags.interruptible`: the handler raises :class:`OperatorInterrupt` in
  the main thread at once (Python runs handlers between bytecodes, so within a
  numpy, torch or SQLite call's return). Nothing it computed is committed yet, so the
  checkpoint is the last committed phase and ``resume`` recomputes from there.

Each request interrupts at most one computation: once the session has acknowledged it
(:meth:`OperatorFlags.acknowledge`, when it starts to pause), only a new request raises
again. What the session does then (parking, saving) is never cut short; a further
request turns the pause into a stop, and skips the report a pause writes if that is
still being written (``elastoprobe report`` writes it later).
"""
from __future__ import annotations

import contextlib
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Iterator

from .errors import InputError
from .locking import session_lock_holder

# The active flags of this process (the handlers are process-wide): what
# :func:`deferred_interrupts` consults.
_active: "OperatorFlags | None" = None


class OperatorInterrupt(BaseException):
    """A pause or stop request that ended a computation in progress.

    A BaseException, like KeyboardInterrupt: ``except Exception`` in library code must
    not swallow it."""

    def __init__(self, stop: bool) -> None:
        self.stop = stop
        super().__init__("stop requested by the operator" if stop else "pause requested by the operator")


@dataclass
class OperatorFlags:
    pause_requested: bool = False
    stop_now: bool = False
    interrupts: int = 0
    requests: int = 0                # every SIGINT or SIGTERM
    _previous: dict[int, object] = field(default_factory=dict)
    _interruptible: int = 0          # depth of interruptible sections
    _deferred: int = 0               # depth of deferred sections (inside an interruptible one)
    _answered: int = 0               # requests already raised or acknowledged

    # -- handlers: set flags, then interrupt a computation if one is in progress
    def _on_sigint(self, signum: int, frame: FrameType | None) -> None:
        self.interrupts += 1
        self.requests += 1
        self.pause_requested = True
        if self.interrupts >= 2:
            self.stop_now = True
        self._raise_if_pending()

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        self.requests += 1
        self.pause_requested = True
        self._raise_if_pending()

    def _raise_if_pending(self) -> None:
        if self.requests > self._answered and self._interruptible and not self._deferred:
            self._answered = self.requests
            raise OperatorInterrupt(self.stop_now)

    def acknowledge(self) -> None:
        """The session acts on the requests so far (it pauses): only a new one interrupts again."""
        self._answered = self.requests

    @property
    def reason(self) -> str:
        """What the operator asked for, as the pause reason says it."""
        return "stopped by the operator" if self.stop_now else "pause requested by the operator"

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """Computation: a request (also one that came before) raises OperatorInterrupt here."""
        self._interruptible += 1
        try:
            self._raise_if_pending()
            yield
        finally:
            self._interruptible -= 1

    def install(self) -> "OperatorFlags":
        global _active
        self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._on_sigint)
        self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._on_sigterm)
        _active = self
        return self

    def restore(self) -> None:
        global _active
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)   # type: ignore[arg-type]
        self._previous.clear()
        if _active is self:
            _active = None


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """A block a request must not cut in two (a journal transaction, a device command, a
    state transition): a request that arrives inside is held, and raised (if a computation
    is in progress around the block) once the block has ended normally."""
    flags = _active
    if flags is None:
        yield
        return
    flags._deferred += 1
    try:
        yield
    finally:
        flags._deferred -= 1
    flags._raise_if_pending()


def _holder_pid(session_dir: Path) -> int:
    holder = session_lock_holder(session_dir)
    if not holder or not holder.get("pid"):
        raise InputError("no controller is running this session (no lock holder)", path=str(session_dir))
    pid = int(holder["pid"])
    if holder.get("alive") is None:
        raise InputError(f"the controller (pid {pid}) runs on host {holder.get('host')!r}, not this one: "
                         f"pause or stop it there", path=str(session_dir))
    if holder.get("alive") is False:
        raise InputError(f"the controller (pid {pid}) is not running; continue with: elastoprobe resume "
                         f"{session_dir}", path=str(session_dir))
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
