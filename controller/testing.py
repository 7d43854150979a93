"""The controller's test seam, in one place: crash points and the faults the simulated cell
schedules but cannot play itself.

Nothing here changes what the controller does on a real cell: with the environment variable
unset a crash point is one dict lookup, and a real cell has no fault injector.

Crash points (kill -9 tests, tests/test_session_resume.py and bench/soak.py):
``ELASTOPROBE_JOURNAL_CRASH_AT=name[@n][+delay_s]`` SIGKILLs this process the n-th time
(default the first) it passes the point ``name``: at once, or ``delay_s`` seconds later from a
timer (to land inside long work such as the report). One meaning for every point: exactly the
n-th pass, counted per process (a resumed process counts anew). Several points, comma-separated,
are armed together: whichever comes first kills (the soak arms a learning point beside a journal
one, as a child may pause before it reaches either). Before the kill one line
``crash point NAME@N`` goes to stderr, so a driver knows which point landed. The points:

- in the journal's transactions (controller/journal.py): ``commit_phase:after_phase_row``,
  ``commit_phase:half_steps``, ``commit_phase:before_commit``, ``begin_step:before_commit``,
  ``commit_step:half_arrays``, ``commit_step:after_arrays``, ``commit_step:before_commit``,
  ``fail_step:before_commit``, ``record_fault:before_commit``;
- in the phases (controller/phases.py): ``models:before_save``, ``models:after_save``,
  ``models:before_commit``, ``final:before_report``, ``report:begin`` (give a delay),
  ``final:after_report``.

Disk errors: the simulator decides when a ``disk_error`` fault is due (the same keyed schedule
as every fault, sim/faults.py) but cannot reach the disk, so the session asks
:func:`play_disk_error` before it commits a step's data.
"""
from __future__ import annotations

import os
import signal
import sqlite3
import sys
import threading
from typing import TYPE_CHECKING, Any, Callable

from .core.faultkinds import InjectedFault

if TYPE_CHECKING:   # the journal calls crash_point: only its type is needed here
    from .core.devices import Cell
    from .journal import Journal

CRASH_AT_ENV = "ELASTOPROBE_JOURNAL_CRASH_AT"

_crash_counts: dict[str, int] = {}


def crash_point(name: str) -> None:
    """SIGKILL this process here if ``ELASTOPROBE_JOURNAL_CRASH_AT`` names this point and this
    is its n-th pass (see the module's docstring)."""
    specs = os.environ.get(CRASH_AT_ENV)
    if not specs:
        return
    counted = False
    for spec in specs.split(","):
        head, _, delay_text = spec.strip().partition("+")
        point, _, nth_text = head.partition("@")
        if point != name:
            continue
        if not counted:     # one pass of the point, however many specs name it
            _crash_counts[name] = _crash_counts.get(name, 0) + 1
            counted = True
        nth = int(nth_text) if nth_text else 1
        if _crash_counts[name] != nth:
            continue
        try:
            sys.stderr.write(f"crash point {name}@{nth}{'+' + delay_text if delay_text else ''}\n")
            sys.stderr.flush()
        except (OSError, ValueError, AttributeError):   # no stderr to say it on: kill all the same
            pass
        if delay_text:
            timer = threading.Timer(float(delay_text), os.kill, (os.getpid(), signal.SIGKILL))
            timer.daemon = True
            timer.start()
        else:
            os.kill(os.getpid(), signal.SIGKILL)


def play_disk_error(cell: Cell, journal: Journal, step_id: int, retry: int,
                    log: Callable[..., Any]) -> None:
    """Fail the journal write of ``step_id`` (at ``retry``) if the simulated cell scheduled a
    disk error for it: the fault is journaled and logged (a resume draws a new key and does not
    meet it again), then this raises what SQLite raises on a failing disk. No-op on a cell
    without a fault injector (every real cell)."""
    take = getattr(getattr(cell, "faults", None), "take_disk_error", None)
    if take is None or not take(step_id, retry):
        return
    kind = InjectedFault.DISK_ERROR.value
    journal.record_fault(kind, "injected disk error: the step's write failed",
                         t_robot_s=cell.clock.now_s(), step_id=step_id, policy_action="pause")
    log("fault", kind=kind, step=step_id, action="pause")
    raise sqlite3.OperationalError(f"disk I/O error (injected by the simulated cell at step {step_id})")
