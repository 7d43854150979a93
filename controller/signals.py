"""Operator requests by signal (docs/design.md §11), honoured in every phase.

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

Library code that swallows the interrupt (trimesh imports its optional modules under
``except BaseException``) cannot lose the request: until the interrupt is seen leaving the
computation, SIGALRM raises it again every :data:`REASSERT_S`.

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
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Iterator

from .core.errors import InputError
from .locking import session_lock_holder

# How often an interrupt that library code swallowed is raised again (s).
REASSERT_S = 0.2

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
    _in_flight: bool = False         # an OperatorInterrupt raised, not yet seen leaving a section
    _ours: bool = False              # the process's one real-time timer is armed for _on_alarm
    _foreign: tuple[float, float, float] = (0.0, 0.0, 0.0)   # the timer it displaced: delay, interval, when

    # Signals seen, counted from both sides (see _on_signal): handler calls and wakeup-pipe bytes.
    _calls: dict[int, int] = field(default_factory=dict)
    _bytes: dict[int, int] = field(default_factory=dict)
    _counted: dict[int, int] = field(default_factory=dict)
    _wakeup: tuple[int, int] | None = None   # pipe the C-level handler writes each signal's number to
    _previous_wakeup: int = -1

    # -- handler: set flags, then interrupt a computation if one is in progress
    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        # Python makes one handler call for all the signals of one number that arrive while
        # the main thread is inside one C call (two SIGINTs 50 ms apart inside a torch or
        # numpy operation), but the C-level handler writes a byte per signal to the wakeup
        # pipe. Neither count alone is exact: calls coalesce, and a byte is written just
        # after the flag that makes the call (when another thread took the signal, the call
        # can come first). Both are lower bounds of the signals delivered, so the larger one
        # is counted: nothing is counted twice and a single signal is never lost.
        self._calls[signum] = self._calls.get(signum, 0) + 1
        for sig, n in self._drain().items():
            self._bytes[sig] = self._bytes.get(sig, 0) + n
        for sig in (signal.SIGINT, signal.SIGTERM):
            seen = max(self._calls.get(sig, 0), self._bytes.get(sig, 0))
            new = seen - self._counted.get(sig, 0)
            if new <= 0:
                continue
            self._counted[sig] = seen
            self.requests += new
            self.pause_requested = True
            if sig == signal.SIGINT:
                self.interrupts += new
        if self.interrupts >= 2:
            self.stop_now = True
        self._raise_if_pending()

    def _drain(self) -> dict[int, int]:
        """Signal number -> bytes read from the wakeup pipe since the last drain."""
        counts: dict[int, int] = {}
        if self._wakeup is None:
            return counts
        while True:
            try:
                data = os.read(self._wakeup[0], 512)
            except (BlockingIOError, InterruptedError):
                break
            if not data:
                break
            for sig in data:
                counts[sig] = counts.get(sig, 0) + 1
        return counts

    def _raise_if_pending(self) -> None:
        if self.requests > self._answered and self._interruptible and not self._deferred:
            self._answered = self.requests
            self._raise_in_flight()

    def _raise_in_flight(self) -> None:
        # Library code may swallow the exception (trimesh imports its optional modules under
        # ``except BaseException``): until it is seen leaving a section, SIGALRM raises it again.
        self._in_flight = True
        self._arm(REASSERT_S)
        raise OperatorInterrupt(self.stop_now)

    def _on_alarm(self, signum: int, frame: FrameType | None) -> None:
        if not self._ours:              # the timer someone else had set (a test runner's timeout)
            previous = self._previous.get(signal.SIGALRM)
            if callable(previous):
                previous(signum, frame)
            return
        if not self._in_flight:
            self._restore_timer()
        elif self._interruptible and not self._deferred:
            self._raise_in_flight()
        else:
            self._arm(REASSERT_S)       # inside a block a request must not cut: later

    def _land(self) -> None:
        """The interrupt in flight reached its handler (or the session acts on it)."""
        self._in_flight = False
        if self._ours:
            self._restore_timer()

    def _arm(self, seconds: float) -> None:
        if signal.SIGALRM not in self._previous:
            return
        delay, interval = signal.setitimer(signal.ITIMER_REAL, seconds)
        if not self._ours:              # the timer found, given back by _restore_timer
            self._foreign = (delay, interval, time.monotonic())
            self._ours = True

    def _restore_timer(self) -> None:
        delay, interval, at = self._foreign
        self._ours, self._foreign = False, (0.0, 0.0, 0.0)
        left = max(delay - (time.monotonic() - at), 1e-3) if delay > 0 else 0.0
        signal.setitimer(signal.ITIMER_REAL, left, interval)

    def acknowledge(self) -> None:
        """The session acts on the requests so far (it pauses): only a new one interrupts again."""
        self._answered = self.requests
        self._land()

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
        except OperatorInterrupt:
            self._land()
            raise
        finally:
            self._interruptible -= 1
        if self._in_flight and not self._deferred:
            # Raised, yet the section ended normally (swallowed before SIGALRM came): the
            # request still stands.
            self._land()
            raise OperatorInterrupt(self.stop_now)

    def install(self) -> "OperatorFlags":
        """Take SIGINT and SIGTERM (and SIGALRM, see :meth:`_raise_in_flight`) for this process
        until :meth:`restore`.

        Only the main thread can take signals; elsewhere (a controller embedded in a
        thread) nothing is installed and the flags stay as they are, so requests go to
        whatever the main thread does with them."""
        global _active
        if threading.current_thread() is not threading.main_thread():
            return self
        r, w = os.pipe()
        try:
            os.set_blocking(r, False)
            os.set_blocking(w, False)
            self._previous_wakeup = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        except BaseException:
            os.close(r)
            os.close(w)
            raise
        self._wakeup = (r, w)
        try:
            self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._on_signal)
            self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._on_signal)
            self._previous[signal.SIGALRM] = signal.signal(signal.SIGALRM, self._on_alarm)
        except BaseException:
            self.restore()
            raise
        _active = self
        return self

    def restore(self) -> None:
        """Give back the handlers and wakeup fd found by :meth:`install` (nested installs
        restore in reverse order, as the session inside the CLI does)."""
        global _active
        self._land()
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)   # type: ignore[arg-type]
        self._previous.clear()
        if self._wakeup is not None:
            signal.set_wakeup_fd(self._previous_wakeup)
            for fd in self._wakeup:
                os.close(fd)
            self._wakeup = None
            self._previous_wakeup = -1
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
