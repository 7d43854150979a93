"""The controller's one test seam (controller/testing.py): every crash point has one meaning
(exactly the n-th pass, at once or after a delay), a disk error is played only where the
simulated cell scheduled one, and the fault kinds are one list everywhere."""
from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from types import SimpleNamespace
from typing import Any

import pytest

from elastoprobe.controller.core.config import FaultSpec
from elastoprobe.controller.core.faultkinds import INJECTED_FAULT_NAMES, InjectedFault
from elastoprobe.controller.testing import CRASH_AT_ENV, play_disk_error
from elastoprobe.sim.faults import FaultPlan

# Passes the points named on the command line in turn, printing each pass, then idles.
CHILD = """
import sys, time
from elastoprobe.controller.testing import crash_point
for name in sys.argv[1:]:
    crash_point(name)
    print(name, flush=True)
time.sleep(float({idle_s}))
"""


def _child(spec: str | None, points: list[str], idle_s: float = 0.0) -> tuple[int, list[str]]:
    env = dict(os.environ)
    env.pop(CRASH_AT_ENV, None)
    if spec is not None:
        env[CRASH_AT_ENV] = spec
    proc = subprocess.run([sys.executable, "-c", CHILD.format(idle_s=idle_s), *points], env=env,
                          capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stdout.split()


def test_a_crash_point_kills_at_exactly_its_nth_pass() -> None:
    assert _child(None, ["a", "a", "a"]) == (0, ["a", "a", "a"])
    assert _child("a", ["b", "a", "a"]) == (-9, ["b"])                 # default: the first pass
    assert _child("a@2", ["a", "b", "a", "a"]) == (-9, ["a", "b"])
    assert _child("a@3", ["a", "a"]) == (0, ["a", "a"])                # never reached: no kill


def test_several_crash_points_armed_together_kill_at_the_first_one_reached() -> None:
    assert _child("b@2,a@2", ["a", "b", "a", "b"]) == (-9, ["a", "b"])   # a's 2nd pass comes first
    assert _child("a@9,b", ["a", "b"]) == (-9, ["a"])
    assert _child("a@2,a@3", ["a", "a"]) == (-9, ["a"])                   # one count per pass
    assert _child("a@3,b@2", ["a", "b", "a"]) == (0, ["a", "b", "a"])       # neither reached


def test_a_crash_point_says_which_point_killed() -> None:
    env = dict(os.environ)
    env[CRASH_AT_ENV] = "x@1,a@2"
    proc = subprocess.run([sys.executable, "-c", CHILD.format(idle_s=0.0), "a", "a"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9 and "crash point a@2" in proc.stderr


def test_a_delayed_crash_point_kills_later_and_only_its_nth_pass_arms_it() -> None:
    # The 2nd pass arms a timer; the process goes on (3rd pass printed) and dies in its idle time.
    code, passed = _child("a@2+0.5", ["a", "a", "a"], idle_s=60.0)
    assert code == -9 and passed == ["a", "a", "a"]


class _Journal:
    def __init__(self) -> None:
        self.faults: list[tuple[Any, ...]] = []

    def record_fault(self, kind: str, message: str, **kw: Any) -> int:
        self.faults.append((kind, message, kw))
        return len(self.faults)


def _cell(due: set[tuple[int, int]] | None) -> Any:
    clock = SimpleNamespace(now_s=lambda: 12.5)
    if due is None:                      # a real cell: no fault injector
        return SimpleNamespace(clock=clock)
    faults = SimpleNamespace(take_disk_error=lambda step, retry: (step, retry) in due)
    return SimpleNamespace(clock=clock, faults=faults)


def test_a_disk_error_is_played_only_where_the_simulated_cell_scheduled_it() -> None:
    logged: list[tuple[str, dict[str, Any]]] = []

    def log(event: str, **kw: Any) -> None:
        logged.append((event, kw))

    journal = _Journal()
    play_disk_error(_cell(None), journal, 3, 0, log)           # type: ignore[arg-type]
    play_disk_error(_cell({(3, 1)}), journal, 3, 0, log)       # type: ignore[arg-type]
    assert journal.faults == [] and logged == []
    with pytest.raises(sqlite3.OperationalError, match="disk I/O error"):
        play_disk_error(_cell({(3, 1)}), journal, 3, 1, log)   # type: ignore[arg-type]
    (kind, _, kw), = journal.faults
    assert kind == "disk_error" and kw == {"t_robot_s": 12.5, "step_id": 3, "policy_action": "pause"}
    assert logged == [("fault", {"kind": "disk_error", "step": 3, "action": "pause"})]


def test_one_list_of_fault_kinds_for_the_cell_file_and_the_injector() -> None:
    assert INJECTED_FAULT_NAMES == tuple(InjectedFault) and len(set(INJECTED_FAULT_NAMES)) == 11
    for name in INJECTED_FAULT_NAMES:
        spec = FaultSpec(kind=name, step=1)
        assert spec.kind == name
        plan = FaultPlan(spec.kind, step=1)
        assert plan.kind == name and type(plan.kind) is str      # records carry the plain name
    with pytest.raises(ValueError, match="disk_error"):
        FaultSpec(kind="gremlins", step=1)
    with pytest.raises(ValueError, match="unknown fault kind"):
        FaultPlan("gremlins", step=1)
