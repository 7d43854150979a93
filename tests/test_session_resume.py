"""kill -9 the controller at random and chosen moments, resume until done: the session
equals an uninterrupted one (docs/design.md §6; issue "The probing controller", Done when).

Each session runs the real CLI in a child process on the tiny plan (tests/data/session/
tiny.yaml) and a private copy of the simulated cell. Kills land after random delays and
at chosen points: inside a step commit, inside a phase commit, around a model save and
during the report (``ELASTOPROBE_JOURNAL_CRASH_AT``, the crash points of
controller/testing.py). After every kill the journal must be sound
(``PRAGMA integrity_check``, checksums, no half-written step); at the end every step is
done or skipped exactly as in the uninterrupted run, with the same raw data, the same
models (model hashes) and the same region map (final cloud labels).
"""
from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from test_session_util import Outcome, child_env, outcome, start_or_resume

from elastoprobe.controller.journal import Journal

SEED = 2                      # two regions and a densify round with this seed
MAX_FINAL_RESUMES = 4

# Aimed kills: (crash spec, where it lands). Counts are per process (each resume counts anew).
AIMED = [
    ("commit_step:half_arrays@3", "inside a step commit, half its arrays written"),
    ("commit_phase:half_steps@2", "inside the second phase commit of a run, half its steps planned"),
    ("report:begin+1.0", "one second into the report"),
]


@pytest.fixture
def setup(tiny_session: dict) -> dict:
    """The shared tiny session's cell, plan and lock directory (conftest.py); killed runs
    write beside its finished one, never into it."""
    assert tiny_session["seed"] == SEED
    return tiny_session


@pytest.fixture
def reference(setup: dict) -> Outcome:
    """The uninterrupted session with the same seed: the shared tiny session. Its wall time
    (``wall_s``) says how long a whole session takes on this machine now: random kills are
    placed as fractions of it, so they land inside the session however fast the machine is."""
    ref = setup["outcome"]
    assert ref.status == "done" and ref.integrity == ["ok"] and not ref.problems
    assert sum(s == "done" for s in ref.step_status.values()) >= 10
    return ref


def _check_sound(session_dir: Path) -> None:
    """After a kill: SQLite intact, every done step complete with valid checksums."""
    if not (session_dir / "journal.sqlite").exists():
        return
    j = Journal.open_readonly(session_dir)
    try:
        assert [r[0] for r in j._q("PRAGMA integrity_check")] == ["ok"]
        assert j.verify() == []
    finally:
        j.close()


def _kill_and_resume(setup: dict, name: str, kills: list[tuple[str, object]],
                     aimed_must_land: bool = True) -> tuple[Path, list[int]]:
    """Run the session through ``kills`` (("delay", seconds) or ("crash", spec)), then
    resume until it is done. Returns the directory and the exit codes in order.
    ``aimed_must_land``: every crash spec must kill its run (else that moment went untested)."""
    out = setup["tmp"] / name
    codes = []
    for kind, value in kills:
        if kind == "delay":
            child = start_or_resume(setup["plan"], out, SEED, setup["env"], kill_after_s=float(value))  # type: ignore[arg-type]
        else:
            env = child_env(setup["tmp"] / "locks", crash_at=str(value))
            child = start_or_resume(setup["plan"], out, SEED, env)
            if aimed_must_land:
                assert child.returncode == -9, \
                    f"{value}: expected a SIGKILL, got {child.returncode}\n{child.stderr[-2000:]}"
        codes.append(child.returncode)
        assert child.returncode in (-9, 0), child.stderr[-3000:]
        _check_sound(out)
        if child.returncode == 0:
            break
    for _ in range(MAX_FINAL_RESUMES):
        if codes and codes[-1] == 0:
            break
        child = start_or_resume(setup["plan"], out, SEED, setup["env"])
        codes.append(child.returncode)
        assert child.returncode in (0, 3), child.stderr[-3000:]
    assert codes[-1] == 0, f"session never finished: exit codes {codes}"
    return out, codes


def _assert_equal_to_reference(out: Path, ref: Outcome) -> None:
    got = outcome(out)
    assert got.status == "done"
    assert got.integrity == ["ok"] and got.problems == []
    # Every planned step ended done (or skipped by policy) exactly as without kills ...
    assert got.step_status == ref.step_status
    assert set(got.step_status.values()) <= {"done", "skipped"}
    # ... with the same raw data, so the same models and region map.
    assert got.step_data == ref.step_data
    assert got.model_hashes == ref.model_hashes
    assert got.labels_sha256 == ref.labels_sha256
    # Nothing was committed twice: one step_done event per done step over all runs.
    done_events: dict[int, int] = {}
    for line in (out / "log.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec["event"] == "step_done":
            done_events[rec["step"]] = done_events.get(rec["step"], 0) + 1
    # A kill between COMMIT and the log line loses the line, never adds one.
    assert all(n == 1 for n in done_events.values()), {k: n for k, n in done_events.items() if n != 1}
    assert (out / "report" / "index.html").exists()


def test_kill_at_aimed_and_random_moments_then_resume_equals_uninterrupted(setup: dict, reference: Outcome) -> None:
    rnd = random.Random(13)
    # Early in the session (a fraction of an uninterrupted run's wall time), so enough of it
    # is left for the aimed kills after it: a fixed 6-14 s landed near the end once the
    # simulator got faster, and the step-commit kill that follows found no third commit.
    kills: list[tuple[str, object]] = [("delay", rnd.uniform(0.1, 0.25) * setup["wall_s"])]
    kills += [("crash", spec) for spec, _ in AIMED]
    out, codes = _kill_and_resume(setup, "killed", kills)
    assert codes.count(-9) >= 4
    _assert_equal_to_reference(out, reference)


STEP_POINTS = ["commit_step:half_arrays", "commit_step:after_arrays", "commit_step:before_commit",
               "begin_step:before_commit"]
LATE_POINTS = ["commit_phase:half_steps@1", "models:before_save@1", "models:after_save@1", "models:before_commit@1",
               "final:before_report", "report:begin+1.0", "final:after_report"]


@pytest.mark.slow
def test_twenty_kills_then_resume_equals_uninterrupted(setup: dict, reference: Outcome) -> None:
    """A fault being journaled, then step commits (aimed at the 1st or 2nd commit of a run)
    alternating with random delays, then phase commits, model saves and the report."""
    rnd = random.Random(7)
    # Wall-clock delays depend on the machine's load: a few short ones (they land in the
    # start-up, the sweep or the first steps); the rest are aimed, each run making at
    # most one step of progress, so twenty kills fit in the tiny session.
    kills: list[tuple[str, object]] = [("delay", rnd.uniform(1.5, 3.0)), ("crash", "record_fault:before_commit@1")]
    for k in range(16):
        # Mostly the first commit of a run (no progress), every third the second.
        kills.append(("crash", f"{rnd.choice(STEP_POINTS)}@{2 if k % 3 == 2 else 1}"))
    kills.append(("delay", rnd.uniform(1.5, 3.0)))
    kills += [("crash", spec) for spec in LATE_POINTS]
    out, codes = _kill_and_resume(setup, "killed20", kills, aimed_must_land=False)
    landed = codes.count(-9)
    print(f"kills landed: {landed}; runs: {len(codes)}; exit codes: {codes}")
    assert landed >= 20, f"only {landed} kills landed: {codes}"
    _assert_equal_to_reference(out, reference)
