"""The simulated overnight soak (issues #7, #15): faults of many kinds, SIGKILLs and resumes,
and nothing lost, nothing done twice, every fault recovered or cleanly paused, the journal sound.

The driver is bench/soak.py (one place for the logic): it runs the real CLI in child
processes on a private copy of the simulated cell with rate-based faults, kills and
resumes it, plays the operator (an e-stop is released, then the session resumed), and
judges the outcome against the simulator's own durable record of what it injected.

The short soak runs by default (a small plan; e-stop, disk error, force spike, protective
stop, scanner timeout and connection loss at a few per 100 steps, a protective stop in the
sweep, follow-ups while recovering; a kill at a random moment, one inside a journal
transaction and one in the learning phase). The night (>= 8 h of robot time, every fault
kind at about one every ten steps in total, faults in the sweep and in learning phases,
follow-ups during recovery, 24 kills) is marked soak.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench import soak

# Fates that are not a failure of the controller: a scanner fault with no scan asked for
# or a slip with no contact changed nothing any device showed; a fault whose process was
# SIGKILLed before it could journal it died with that process (the kill is the fault).
HARMLESS = {"no_effect", "lost_to_kill"}
# Known gap (tests/test_session_faults.py, strict xfail there): a moved object is not
# detected yet. The soak counts it as undetected and says so; it is not hidden.
KNOWN_UNDETECTED = {"object_moved"}
# Memory: a real night is 8-12 h. 5 MB per robot hour is < 60 MB over 12 h (about 10 %
# of the controller's ~0.5 GB, torch included), while keeping each step's raw scans
# (~0.3 MB x ~300 steps per robot hour) would grow ~90 MB/h and fail this clearly.
MAX_RSS_GROWTH_MB_PER_H = 5.0


def _assert_sound(result: dict[str, Any]) -> None:
    assert result["status"] == "done", (result["status"], result["status_reason"], result["exit_codes"],
                                        result["last_stderr"])
    assert result["journal_problems"] == []
    assert result["steps_lost"] == 0, result["steps_lost_ids"]
    assert result["steps_duplicated"] == 0, result["steps_duplicated_ids"]
    assert result["steps_done"] > 0
    bad = [f for f in result["faults_neither"]
           if f["fate"] not in HARMLESS and not (f["fate"] == "undetected" and f["kind"] in KNOWN_UNDETECTED)]
    assert bad == [], bad
    assert result["faults_recovered"] + result["faults_paused"] + len(result["faults_neither"]) \
        == result["faults_injected"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return soak.run_soak(soak.QUICK, tmp_path_factory.mktemp("soak_quick"))


# About 45 s of CPU (five CLI children, each importing torch); more wall time on a busy machine.
@pytest.mark.timeout(900)
def test_short_soak_loses_nothing_and_every_fault_is_recovered_or_paused(quick: dict[str, Any]) -> None:
    _assert_sound(quick)
    # The run must have exercised what it claims to: faults recovered by retry, a pause,
    # the operator releasing an e-stop, a disk error on the journal's write, kills.
    assert quick["faults_recovered"] >= 1
    assert quick["faults_paused"] >= 1 and quick["operator_clears"] >= 1
    assert quick["faults_by_kind"].get("emergency_stop", {}).get("paused", 0) >= 1
    assert quick["faults_by_kind"].get("disk_error", {}).get("paused", 0) >= 1
    assert quick["kills"] >= 2          # which kinds land depends on where the pauses fall
    assert sum(quick["faults_by_phase"].get("sweeping", {}).values()) >= 1


def test_short_soak_figures_are_reported(quick: dict[str, Any]) -> None:
    for key in ("robot_hours", "faults_injected", "faults_recovered", "faults_paused", "kills", "steps_lost",
                "steps_duplicated", "peak_rss_mb", "rss_growth_mb_per_h"):
        assert key in quick
    assert quick["peak_rss_mb"] > quick["baseline_rss_mb"] > 0


def test_a_paused_child_the_driver_lost_is_judged_from_the_session(quick: dict[str, Any], tmp_path: Path) -> None:
    """The driver stopped after a child paused but before it saved that child (the night of
    stop 24): the session's own runs and log say how the child ended, and its fault is
    judged paused, as it was, not unresolved."""
    import json
    import shutil

    work = tmp_path / "soak"
    shutil.copytree(Path(quick["session_dir"]).parent, work)
    state = json.loads((work / "state.json").read_text())
    paused = [i for i, c in enumerate(state["children"][:-1]) if c["returncode"] == 3]
    assert paused
    lost = state["children"].pop(paused[0])
    (work / "state.json").write_text(json.dumps(state))
    judged = soak.summarize(work)
    assert judged["children_lost_by_driver"] == 1
    assert judged["faults_paused"] == quick["faults_paused"]
    assert judged["faults_unresolved"] == quick["faults_unresolved"] == 0
    assert judged["pauses"] == quick["pauses"] and lost["pause_reason"] in judged["pauses"]


@pytest.mark.soak
@pytest.mark.timeout(4 * 3600)
def test_overnight_soak(tmp_path: Path) -> None:
    result = soak.run_soak(soak.FULL, tmp_path)
    print(result)
    _assert_sound(result)
    assert result["robot_hours"] >= 8.0
    # About 300 faults per 8 robot hours (a fault every ten steps or so), of every kind, in
    # every phase, some while recovering from another; at least 20 kills of every kind.
    assert result["faults_injected"] / result["robot_hours"] * 8.0 >= 240
    assert set(result["faults_by_kind"]) == set(soak_kinds())
    assert {"sweeping", "survey", "characterize", "densify", "learning"} <= set(result["faults_by_phase"])
    assert sum(result["faults_during_recovery"].values()) >= 5
    # A retry-kind fault met while recovering gets one nested recovery (docs/design.md).
    assert result["nested_recoveries"] >= 1
    # Kills that landed on a running child (its own exit status says SIGKILL), spread over the
    # phases: a moment of the child's progress, inside a journal transaction, in learning.
    assert result["kills"] >= 20 and set(result["kills_by_mode"]) == {"progress", "aimed", "learning"}
    assert {"survey", "characterize", "learning"} <= set(result["kills_by_phase"])
    assert result["rss_growth_mb_per_h"] is not None
    assert abs(result["rss_growth_mb_per_h"]) <= MAX_RSS_GROWTH_MB_PER_H
    assert result["rss_growth_across_children_mb_per_h"] is not None
    assert abs(result["rss_growth_across_children_mb_per_h"]) <= MAX_RSS_GROWTH_MB_PER_H


def soak_kinds() -> tuple[str, ...]:
    from elastoprobe.controller.core.faultkinds import INJECTED_FAULT_NAMES

    return INJECTED_FAULT_NAMES


def test_a_fault_during_recovery_counts_as_the_pause_it_caused() -> None:
    # The CI run of cad5053 met it: a motion was refused at step 0, and while retracting a
    # protective stop struck. The session journaled "during recovery from motion_refused:
    # ..." and paused naming the fault it was recovering from; the judge matched pause
    # reasons only against the journaled fault's own kind and called it unresolved.
    from elastoprobe.controller.journal import FaultRecord

    def fault(fault_id: int, kind: str, message: str) -> FaultRecord:
        return FaultRecord(fault_id=fault_id, kind=kind, t_robot_s=83.0 + fault_id, t_wall_utc="", step_id=None,
                           message=message, policy_action="pause", raw=None)

    faults = [fault(3, "motion_refused", "collision: scanner comes within 3.7 mm"),
              fault(4, "protective_stop", "during recovery from motion_refused: the robot is in a protective stop")]
    paused = soak.ChildRun([], 101, 3, None, 1.0, 1.0, [], pause_reason="motion_refused: collision: scanner comes")
    resumed = soak.ChildRun([], 102, 0, None, 1.0, 1.0, [])
    got = soak._paused_fault_ids([paused, resumed], faults, {3: 1, 4: 1}, {101: 1, 102: 2})
    assert got == {4}
    # A pause naming another fault does not claim it.
    other = soak.ChildRun([], 101, 3, None, 1.0, 1.0, [], pause_reason="force_spike: force 52 N")
    assert soak._paused_fault_ids([other, resumed], faults, {3: 1, 4: 1}, {101: 1, 102: 2}) == set()


def test_a_stop_of_a_stopped_arm_claims_no_journaled_fault_and_phases_come_from_keys() -> None:
    # The quick soak met it: a follow-up protective stop fired while the arm was already
    # stopped (it changed nothing) and took the journaled fault of the next real stop, which
    # was then called undetected.
    from elastoprobe.controller.journal import FaultRecord

    stop = FaultRecord(fault_id=2, kind="protective_stop", t_robot_s=11.3, t_wall_utc="", step_id=None,
                       message="during a sweep of the object: the robot is in a protective stop",
                       policy_action="retry", raw=None)
    idle = {"kind": "protective_stop", "t_s": 5.0, "key": [1, soak.SWEEP_KEY, 0], "effective": False}
    real = {"kind": "protective_stop", "t_s": 11.263, "key": [1, soak.SWEEP_KEY, 1]}
    assert soak.journaled_match(idle, 1, [stop], {2: 1}, set()) is None
    assert soak.journaled_match(real, 1, [stop], {2: 1}, set()) is stop
    assert soak.journaled_match(real, 2, [stop], {2: 1}, set()) is None          # another run's
    from elastoprobe.controller.phases import SWEEP_STEP_KEY
    from elastoprobe.controller.session import LEARN_STEP_KEY

    assert (soak.SWEEP_KEY, soak.LEARN_KEY) == (SWEEP_STEP_KEY, LEARN_STEP_KEY)
    assert soak.phase_of_key((1, soak.SWEEP_KEY, 3), {}) == "sweeping"
    assert soak.phase_of_key((1, soak.LEARN_KEY - 2, 0), {}) == "learning"
    assert soak.phase_of_key((1, 12, 0), {12: "regions"}) == "characterize"


def test_a_moved_object_does_not_take_the_slip_fault_a_later_slip_caused() -> None:
    # The night of issue #15 met it: the object moved at 594 s (never seen), a slip fired at
    # 628 s and the slip monitor journaled it at once; the moved object, matched first with
    # its open-ended window, took that slip fault: the move was called recovered and the
    # slip undetected.
    from elastoprobe.controller.journal import FaultRecord

    slip_fault = FaultRecord(fault_id=82, kind="slip", t_robot_s=628.85, t_wall_utc="", step_id=441,
                             message="tip slipped 6.00 mm along the surface (limit 6.0 mm)",
                             policy_action="retry", raw=None)
    moved = {"pid": 7, "kind": "object_moved", "t_s": 594.111, "key": [1, 438, 0], "plan": 10}
    slip = {"pid": 7, "kind": "slip", "t_s": 628.473, "key": [1, 441, 0], "plan": 7}
    claimed: set[int] = set()
    got = {}
    for rec in soak.judging_order([moved, slip], {7: 12}):
        match = soak.journaled_match(rec, 12, [slip_fault], {82: 12}, claimed)
        if match is not None:
            claimed.add(match.fault_id)
        got[rec["kind"]] = match
    assert got == {"slip": slip_fault, "object_moved": None}


def test_a_fault_unseen_long_before_its_process_was_killed_is_undetected_not_lost_to_kill() -> None:
    # A frozen stream re-armed unseen at 238 s of a run SIGKILLed minutes later was judged
    # "lost_to_kill" (harmless): the run had lived far past its match window.
    killed = soak.ChildRun([], 101, -9, "delay 257.3 s", 1.0, 1.0, [])
    frozen = {"kind": "ft_frozen", "t_s": 238.17}
    assert soak.lost_to_kill(frozen, 14, [killed], {101: 14}, {14: 511.5}) is False
    assert soak.lost_to_kill(frozen, 14, [killed], {101: 14}, {14: 240.0}) is True
    paused = soak.ChildRun([], 101, 3, None, 1.0, 1.0, [])
    assert soak.lost_to_kill(frozen, 14, [paused], {101: 14}, {14: 240.0}) is False


def test_two_scanner_faults_on_one_burst_are_judged_by_the_one_fault_they_showed_as() -> None:
    # The night met it: a short burst and a timeout drawn for the same retry both struck one
    # burst (0 of 40 profiles); the controller journaled one scanner fault and retried, and
    # the judge called the second injection undetected.
    short = {"kind": "scanner_short_burst", "key": [1, 757, 1], "run_id": 27, "t_s": 155.45,
             "effect_t_s": 163.43, "fault_id": 143, "fate": "recovered"}
    timeout = {"kind": "scanner_timeout", "key": [1, 757, 1], "run_id": 27, "t_s": 156.134,
               "effect_t_s": 163.43, "fate": "undetected"}
    elsewhere = {"kind": "scanner_timeout", "key": [1, 800, 0], "run_id": 27, "t_s": 700.0,
                 "effect_t_s": 705.0, "fate": "undetected"}
    fates = [short, timeout, elsewhere]
    soak.share_burst(fates)
    assert timeout["fate"] == "recovered" and timeout["same_burst_as"] == 143
    assert elsewhere["fate"] == "undetected"


def _fake_child(tmp_path: Path, code: str, kill: "soak.ProgressKill | None", env: dict | None = None) -> soak.ChildRun:
    import os
    import sys

    return soak.run_child([], {**os.environ, **(env or {})}, tmp_path / "no-session", kill, 0.05, 60.0, set(),
                          tmp_path / "stderr.log", cli=[sys.executable, "-c", code])


def test_a_kill_counts_only_when_it_lands_on_a_running_child(tmp_path: Path) -> None:
    # The night of issue #15 landed 4 kills of 24: most were due after the child had already
    # exited on a pause. A child that exits before its kill's moment is not killed and no kill
    # is counted; one still running is killed, and its own status says SIGKILL.
    gone = _fake_child(tmp_path, "import sys; sys.exit(3)", soak.ProgressKill(0, 3.0))
    assert (gone.returncode, gone.killed) == (3, None)
    running = _fake_child(tmp_path, "import time; time.sleep(30)", soak.ProgressKill(0, 0.3))
    assert running.returncode == -9 and running.killed == "progress 0 steps +0.3 s"
    # A crash point says which point killed the child (controller/testing.py).
    aimed = _fake_child(tmp_path, "from elastoprobe.controller.testing import crash_point as c; c('a'); c('a')",
                        None, {"ELASTOPROBE_JOURNAL_CRASH_AT": f"{soak.LEARNING_POINT},a@2"})
    assert aimed.returncode == -9 and aimed.killed == "aimed a@2"


def test_a_kill_not_due_at_a_childs_start_lands_at_its_robot_moment(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # The night on 280 units landed 14 kills of 24: a kill was armed only in a child started
    # after its robot moment, and a child runs for hours between pauses. Now one armed for a
    # later robot moment lands when the child's journal reaches it; a child that exits before
    # that moment is not a miss (kill_due False).
    polls = iter(range(0, 10**6, 10))
    monkeypatch.setattr(soak, "_journal_poll", lambda _dir: (float(next(polls)), set(), 0))
    later = soak.ProgressKill(0, 0.0, at_robot_s=60.0)
    running = _fake_child(tmp_path, "import time; time.sleep(30)", later)
    assert running.returncode == -9 and running.killed == later.describe() and running.kill_due
    assert running.samples == [] or running.samples[-1][2] >= 60.0
    polls = iter(range(0, 10**6, 1))
    early = _fake_child(tmp_path, "import sys; sys.exit(3)", soak.ProgressKill(0, 0.0, at_robot_s=10**7))
    assert (early.returncode, early.killed, early.kill_due) == (3, None, False)


def _child_samples(start_h: float, span_h: float, rss_at: Any) -> soak.ChildRun:
    """A child sampled every 8 robot seconds: start-up at one robot time, then probing."""
    hours = start_h + np.arange(0.0, span_h, 8.0 / 3600.0)
    samples = [(0.0, 150.0, start_h * 3600.0, 2), (1.0, 190.0, start_h * 3600.0, 2)]
    samples += [(2.0 + k, float(rss_at(h - start_h)), h * 3600.0, 2) for k, h in enumerate(hours)]
    samples.append((3.0 + len(hours), 260.0, hours[-1] * 3600.0 + 30.0, 2))   # the pause: a spike
    return soak.ChildRun([], 1, 3, None, 1.0, 1.0, samples)


def test_rss_growth_sees_a_leak_in_sparse_steps_and_not_a_warm_up_or_a_pause_spike() -> None:
    # A leak of 6 MB per robot hour that the heap takes in 0.5 MB chunks, over children of
    # 0.3 robot hours (a warm-up of 4 MB in each first): well over the 5 MB/h bound.
    def leak(h: float) -> float:
        return 200.0 + 4.0 * min(h / 0.08, 1.0) + 0.5 * np.floor(6.0 * h / 0.5)
    leaky = [_child_samples(0.4 * k, 0.3, leak) for k in range(12)]
    growth, used_h = soak.rss_growth_mb_per_h(leaky)
    assert growth is not None and used_h > 1.5
    assert growth > 5.0, growth

    # The same children without the leak: a warm-up that levels off and a spike where each
    # pauses. The per-stretch Theil-Sen slope from the child's start read these as growth.
    def settled(h: float) -> float:
        return 200.0 + 4.0 * min(h / 0.08, 1.0)
    flat = [_child_samples(0.4 * k, 0.3, settled) for k in range(12)]
    growth, _ = soak.rss_growth_mb_per_h(flat)
    assert growth is not None and abs(growth) < 0.5, growth
    across, used = soak.rss_growth_across_children_mb_per_h(flat)
    assert used == 12 and across is not None and abs(across) < 0.5

    # What a session carries from child to child (its level rises with the night) is seen
    # across children even though each child alone is flat.
    carried = [_child_samples(0.4 * k, 0.3, lambda h, k=k: settled(h) + 8.0 * 0.4 * k) for k in range(12)]
    across, _ = soak.rss_growth_across_children_mb_per_h(carried)
    assert across is not None and abs(across - 8.0) < 0.5


def test_a_contact_fault_after_its_contacts_retry_fault_is_absorbed_by_the_retry() -> None:
    # The night of issue #15 met it: the link dropped at 151.77 s during step 2091 (journaled,
    # retry), and a slip drawn under the same key fired 1 s later, while the recovery
    # retracted; the contact was pressed again from its first level under a new key and
    # step 2091 was done. The slip touched nothing that was kept: absorbed, not undetected.
    from elastoprobe.controller.journal import FaultRecord

    lost = FaultRecord(fault_id=378, kind="connection", t_robot_s=151.77, t_wall_utc="", step_id=2091,
                       message="lost the connection to the robot", policy_action="retry", raw=None, run_id=49)
    slip = {"pid": 7869, "kind": "slip", "t_s": 152.749, "key": [1, 2091, 0], "plan": 7}
    assert soak.absorbed_by_retry(slip, 49, [lost], {378: 49}, {2091: "done"}) == 378
    # The attempt the retry made (key attempt 1) is the one in flight: a slip there is its own.
    assert soak.absorbed_by_retry({**slip, "key": [1, 2091, 1]}, 49, [lost], {378: 49}, {2091: "done"}) is None
    # Not a contact's fault (a moved object stays moved), not done, another run, a pause,
    # or long after: no absorption.
    assert soak.absorbed_by_retry({**slip, "kind": "object_moved"}, 49, [lost], {378: 49}, {2091: "done"}) is None
    assert soak.absorbed_by_retry(slip, 49, [lost], {378: 49}, {2091: "planned"}) is None
    assert soak.absorbed_by_retry(slip, 50, [lost], {378: 49}, {2091: "done"}) is None
    paused = dataclasses.replace(lost, policy_action="pause")
    assert soak.absorbed_by_retry(slip, 49, [paused], {378: 49}, {2091: "done"}) is None
    late = {**slip, "t_s": 151.77 + soak.MATCH_WINDOW_S + 1.0}
    assert soak.absorbed_by_retry(late, 49, [lost], {378: 49}, {2091: "done"}) is None
