"""kill -9 at random moments and inside transactions: the journal stays sound and resumable.

A child process (this file run as a script) plans phases and measures steps in a loop,
resuming whatever the journal says is not done. The test SIGKILLs it again and again —
from outside at random times, and from inside at chosen points of the transactions
(``ELASTOPROBE_JOURNAL_CRASH_AT``) — and after every kill reopens the journal and checks:
SQLite integrity, every done step complete with its exact data and checksums, phases
all-or-nothing, done steps never lost or repeated, robot time counted once. Finally the
resumed session must equal an uninterrupted one.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.journal import Journal, SessionMeta, StepPlan, StepResult

HERE = Path(__file__).resolve()
SURVEY_STEPS = 24
DENSIFY_STEPS = 12
ROUNDS = 4                 # survey (round 0) + densify rounds 1..3 (soak: more)
N_SCANS, N_SAMPLES = 30, 256
PLAN_TEXT = "name: crashy\nseed: 3\n"
CELL_TEXT = "name: sim\n"


# ----------------------------------------------------------------------------- the child's work
def expected_result(step_id: int) -> StepResult:
    """The 'measurement' of a step: a pure function of its id (like keyed simulator noise)."""
    rng = np.random.default_rng(1000 + step_id)
    scans = rng.normal(0.0, 5.0, (N_SCANS, N_SAMPLES, 2)).astype(np.float32)
    scans[:, ::17, 1] = np.nan
    return StepResult(scans_xz_mm=scans, scan_force_n=rng.normal(0, 1, (N_SCANS, 3)),
                      scan_pose=rng.normal(0, 100, (N_SCANS, 6)), profile_depth_mm=rng.normal(0, 1, N_SAMPLES),
                      force_direction=np.array([0.0, 0.0, -1.0]),
                      reference_xz_mm=rng.normal(0, 5, (3, N_SAMPLES, 2)).astype(np.float32),
                      scan_t_s=np.arange(N_SCANS) * 0.02, robot_time_s=1.0 + step_id / 8.0,
                      summary={"force_measured_n": 1.0 + step_id})


def phase_plan(round_: int, first_id: int) -> tuple[str, dict, dict, list[StepPlan]]:
    n = SURVEY_STEPS if round_ == 0 else DENSIFY_STEPS
    name = "survey" if round_ == 0 else "densify"
    rng = np.random.default_rng(round_)
    units = rng.normal(0, 30, (n, 3))
    plans = [StepPlan(step_id=first_id + k, target_index=k // 2, point_mm=units[k], normal=np.array([0, 0, 1.0]),
                      t=np.array([1.0, 0, 0]), angle_deg=90.0, force_n=2.0 + k % 2, order_index=first_id + k)
             for k in range(n)]
    outputs = {"round": round_, "n_units": n, "cloud_sha256": "c0ffee", "units_mm": "array:units"}
    return name, outputs, {"units": units, "labels": np.arange(n, dtype=np.int64)}, plans


def child_main(session_dir: Path, step_pause_s: float = 0.0, rounds: int = ROUNDS) -> None:
    """Run (or resume) the toy session to the end."""
    if (session_dir / "journal.sqlite").exists():
        journal = Journal.open(session_dir, min_free_bytes=0)
        journal.verify_inputs(PLAN_TEXT, CELL_TEXT)
    else:
        prov = {"plan": {"text": PLAN_TEXT, "sha256": _sha(PLAN_TEXT)},
                "cell": {"text": CELL_TEXT, "sha256": _sha(CELL_TEXT)}}
        journal = Journal.create(session_dir, SessionMeta("crashy", 3, prov), min_free_bytes=0)
    print("ready", flush=True)
    with journal:
        for round_ in range(rounds):
            name = "survey" if round_ == 0 else "densify"
            if journal.phase(name, round_) is None:
                pname, outputs, arrays, plans = phase_plan(round_, journal.next_step_id())
                journal.commit_phase(pname, round_, outputs, arrays, plans)
            for rec in journal.pending_steps(name, round_):
                attempt = journal.begin_step(rec.step_id)
                journal.record_transition("planning", "moving_to_standoff", "go_to_target", 0.1, rec.step_id)
                if step_pause_s:
                    time.sleep(step_pause_s)          # the step "measures": a kill here loses only it
                if rec.step_id % 5 == 3 and attempt == 1:
                    fid = journal.record_fault("force", "spike", 0.2, rec.step_id, "retry",
                                               np.arange(70, dtype=float).reshape(10, 7))
                    journal.fail_step(rec.step_id, attempt, "force spike", fid)
                    attempt = journal.begin_step(rec.step_id)
                journal.commit_step(rec.step_id, attempt, expected_result(rec.step_id))
            journal.complete_phase(name, round_)
        journal.set_status("done")


def _sha(text: str) -> str:
    import hashlib
    return hashlib.sha256(text.encode()).hexdigest()


# ----------------------------------------------------------------------------- checks
def check_sound(session_dir: Path, previous_done: set[int]) -> set[int]:
    """Every invariant a crash must not break; returns the done step ids."""
    if not (session_dir / "journal.sqlite").exists():
        assert not previous_done
        return set()
    # A reader in another process first (must cope with a crashed writer's WAL) ...
    reader = Journal.open_readonly(session_dir)
    reader_counts = reader.status_counts()
    reader.close()
    # ... then the resuming writer, which recovers the WAL.
    with Journal.open(session_dir, min_free_bytes=0) as j:
        assert j.verify() == []
        steps = j.steps()
        done = {s.step_id for s in steps if s.status == "done"}
        assert reader_counts["done"] == len(done)
        assert previous_done <= done, "a committed step was lost"
        results = j.step_results()
        assert set(results) == done
        for sid, res in results.items():
            exp = expected_result(sid)
            np.testing.assert_array_equal(res.scans_xz_mm, exp.scans_xz_mm)
            np.testing.assert_array_equal(res.reference_xz_mm, exp.reference_xz_mm)
            np.testing.assert_array_equal(res.scan_pose, exp.scan_pose)
            assert res.scans_xz_mm.dtype == np.float32
        for s in steps:
            assert s.status in ("planned", "in_progress", "done", "failed")
            if s.status == "done":
                assert s.attempts >= 1
        # Phases are all-or-nothing: a committed phase has all its steps (hash-checked
        # by verify) and no step exists without its phase.
        phase_steps = 0
        for p in j.phases():
            rec = j.phase(p["name"], p["round"])
            assert rec is not None
            n = SURVEY_STEPS if p["round"] == 0 else DENSIFY_STEPS
            assert len(rec.step_ids) == n and rec.arrays["units"].shape == (n, 3)
            phase_steps += n
        assert phase_steps == len(steps)
        # Robot time is added in the step's own transaction: counted exactly once.
        probing = j.robot_time_s().get("probing", 0.0)
        assert probing == pytest.approx(sum(expected_result(s).robot_time_s for s in done))
        # Faults belong to failed attempts; their raw data survive intact.
        for f in j.faults():
            assert f.raw is not None and f.raw.shape == (10, 7)
    return done


CRASH_POINTS = [
    "commit_phase:after_phase_row@1", "commit_phase:half_steps@1", "commit_phase:before_commit@1",
    "begin_step:before_commit@1", "commit_step:half_arrays@1", "commit_step:after_arrays@2",
    "commit_step:before_commit@3", "record_fault:before_commit@1", "fail_step:before_commit@1",
    "commit_phase:half_steps@2", "commit_step:after_arrays@5", "commit_phase:before_commit@1",
    "commit_step:half_arrays@4",
]


def _run_child(session_dir: Path, crash_at: str | None = None, kill_after_s: float | None = None,
               step_pause_s: float = 0.03, rounds: int = ROUNDS) -> int:
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    env.pop("ELASTOPROBE_JOURNAL_CRASH_AT", None)
    if crash_at:
        env["ELASTOPROBE_JOURNAL_CRASH_AT"] = crash_at
    proc = subprocess.Popen([sys.executable, str(HERE), str(session_dir), str(step_pause_s), str(rounds)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        if kill_after_s is not None:
            line = proc.stdout.readline() if proc.stdout else ""   # wait until it really runs
            if line.strip() == "ready":
                time.sleep(kill_after_s)
            proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if proc.returncode not in (0, -signal.SIGKILL):
        raise AssertionError(f"child failed (rc {proc.returncode}):\n{err}")
    return proc.returncode


def _kill_and_resume(tmp_path: Path, n_timer_kills: int, seed: int, rounds: int = ROUNDS,
                     step_pause_s: float = 0.03) -> None:
    """Kill at every crash point, then ``n_timer_kills`` times at random moments; whenever a
    session runs to its end, check it against an uninterrupted one and start a new one."""
    rng = random.Random(seed)
    reference = tmp_path / "reference"
    child_main(reference, rounds=rounds)
    n_sessions = 0

    def new_session() -> Path:
        nonlocal n_sessions
        n_sessions += 1
        return tmp_path / f"crashy{n_sessions}"

    session, done = new_session(), set()
    self_kills = 0
    for point in CRASH_POINTS:
        rc = _run_child(session, crash_at=point, step_pause_s=step_pause_s, rounds=rounds)
        self_kills += rc == -signal.SIGKILL
        done = check_sound(session, done)
    assert self_kills == len(CRASH_POINTS), "a crash point was not reached"
    timer_kills = 0
    for _ in range(4 * n_timer_kills):        # bounded: most runs are killed
        if timer_kills >= n_timer_kills:
            break
        rc = _run_child(session, kill_after_s=rng.uniform(0.0, 0.3), step_pause_s=step_pause_s, rounds=rounds)
        done = check_sound(session, done)
        if rc == -signal.SIGKILL:
            timer_kills += 1
        else:
            _assert_same_as(session, reference)
            session, done = new_session(), set()
    assert self_kills + timer_kills >= 20
    # Resume to the end without kills; the outcome equals an uninterrupted session.
    assert _run_child(session, step_pause_s=0.0, rounds=rounds) == 0
    check_sound(session, done)
    _assert_same_as(session, reference)


def _assert_same_as(session: Path, reference: Path) -> None:
    with Journal.open_readonly(session) as a, Journal.open_readonly(reference) as b:
        assert a.session()["status"] == b.session()["status"] == "done"
        assert [(p["name"], p["round"], p["outputs_hash"], p["status"]) for p in a.phases()] == \
               [(p["name"], p["round"], p["outputs_hash"], p["status"]) for p in b.phases()]
        sa, sb = a.steps(), b.steps()
        assert [s.plan.canonical() for s in sa] == [s.plan.canonical() for s in sb]
        assert all(s.status == "done" for s in sa)
        ra, rb = a.step_results(), b.step_results()
        assert set(ra) == set(rb)
        for sid in rb:
            np.testing.assert_array_equal(ra[sid].scans_xz_mm, rb[sid].scans_xz_mm)
            np.testing.assert_array_equal(ra[sid].profile_depth_mm, rb[sid].profile_depth_mm)
        assert a.robot_time_s()["probing"] == pytest.approx(b.robot_time_s()["probing"])


def test_kill9_at_random_moments_and_mid_transaction(tmp_path: Path) -> None:
    _kill_and_resume(tmp_path, n_timer_kills=10, seed=1)


@pytest.mark.slow
def test_kill9_soak_many_random_kills(tmp_path: Path) -> None:
    _kill_and_resume(tmp_path, n_timer_kills=80, seed=2, rounds=12, step_pause_s=0.06)


def test_resume_journals_what_the_killed_run_left(tmp_path: Path) -> None:
    session = tmp_path / "s"
    assert _run_child(session, crash_at="commit_step:after_arrays@1", step_pause_s=0.0) == -signal.SIGKILL
    with Journal.open(session, min_free_bytes=0) as j:
        assert [s.step_id for s in j.steps(statuses=["in_progress"])] == [0]
        assert j.status_counts()["done"] == 0
        assert j.events("interrupted_steps")[0]["record"] == {"step_ids": [0]}
        holder = j.events("stale_lock_taken_over")[0]["record"]["previous_holder"]
        assert holder["alive"] is False and isinstance(holder["pid"], int)
        assert [r["mode"] for r in j.summary()["runs"]] == ["create", "resume"]
        assert j.pending_steps()[0].step_id == 0 and j.pending_steps()[0].attempts == 1


def test_check_sound_can_fail(tmp_path: Path) -> None:
    """The oracle itself catches a lost step (so the crash test can fail)."""
    session = tmp_path / "s"
    child_main(session)
    with Journal.open(session, min_free_bytes=0) as j:
        done = {s.step_id for s in j.steps()}
    with pytest.raises(AssertionError):
        check_sound(session, done | {10_000})


if __name__ == "__main__":
    child_main(Path(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]))
