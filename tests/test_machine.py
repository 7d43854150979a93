from pathlib import Path

import pytest
from transitions.extensions.nesting import NestedState

from elastoprobe.controller.machine import (PROBE_STEPS, PROBING, STATES, TRANSITIONS, SessionMachine,
                                            diagram_markdown)

DOC = Path(__file__).resolve().parent.parent / "docs" / "state_machine.md"
TRIGGERS = sorted({t["trigger"] for t in TRANSITIONS})
LIFECYCLE = [s for s in STATES if s not in PROBE_STEPS]


def leaf_edges() -> set[tuple[str, str, str]]:
    """Every (source, dest, trigger) the machine journals, found by firing every trigger in
    every leaf state: what a transition declared on ``probing`` means for each step."""
    edges = set()
    for state in STATES:
        for trig in TRIGGERS:
            log: list[tuple[str, str, str]] = []
            m = SessionMachine(lambda a, b, t: log.append((a, b, t)), initial=state)
            if not m.can(trig):
                with pytest.raises(RuntimeError, match=f"cannot {trig!r} from {state!r}"):
                    m.fire(trig)
                assert m.state == state and not log
                continue
            m.fire(trig)
            assert len(log) == 1 and log[0][0] == state and log[0][1] == m.state, (state, trig, log)
            edges.add(log[0])
    return edges


def test_committed_diagram_is_current() -> None:
    assert DOC.read_text() == diagram_markdown(), "docs/state_machine.md is stale: run `elastoprobe diagram`"


def test_one_probe_walks_the_design_sequence_and_is_journaled_with_leaf_names() -> None:
    log: list[tuple[str, str, str]] = []
    m = SessionMachine(lambda a, b, trig: log.append((a, b, trig)))
    for trig in ["start", "plan", "go_to_target", "at_standoff", "reference_ok", "contact", "at_force",
                 "settled", "next_level", "at_force", "settled", "unload", "retract", "finish"]:
        m.fire(trig)
    assert m.state == "done"
    assert [b for _, b, _ in log][:4] == ["preflight", "planning", "moving_to_standoff", "reference_scan"]
    assert ("scanning", "ramping", "next_level") in log
    assert log[-1] == ("retracting", "done", "finish")
    assert len(log) == 14
    assert all(a in STATES and b in STATES for a, b, _ in log)


def test_the_probe_steps_are_substates_of_probing() -> None:
    m = SessionMachine(initial="planning")
    m.fire("go_to_target")
    assert m.state == "moving_to_standoff" and m.path == f"{PROBING}.moving_to_standoff"
    assert SessionMachine(initial="done").path == "done"


def test_impossible_transition_is_refused() -> None:
    m = SessionMachine()
    with pytest.raises(RuntimeError, match="cannot 'contact' from 'idle'"):
        m.fire("contact")
    assert m.state == "idle"


def test_fault_and_abort_declared_on_probing_fire_from_every_step_and_journal_the_step() -> None:
    edges = leaf_edges()
    for step in PROBE_STEPS:
        assert (step, "fault", "fault") in edges
        assert (step, "aborted", "abort") in edges
        m = SessionMachine(initial=step)
        m.fire("fault")
        m.fire("abort")
        assert m.state == "aborted"
        assert not any(m.can(t) for t in TRIGGERS)    # abort is final


def test_a_contacts_steps_stay_inside_probing() -> None:
    # The steps of one contact lead only to each other, or out through the lifecycle's
    # triggers from retracting (the only step the session leaves probing from on its own).
    exits = {(a, b, t) for a, b, t in leaf_edges() if a in PROBE_STEPS and b not in PROBE_STEPS}
    assert {t for a, _, t in exits if a != "retracting"} == {"fault", "abort"}
    assert {t for a, _, t in exits if a == "retracting"} == {"fault", "abort", "sweep", "plan", "learn",
                                                                "pause", "finish"}


def test_keyboard_interrupt_in_a_callback_is_not_swallowed() -> None:
    def boom(*_: object) -> None:
        raise KeyboardInterrupt

    m = SessionMachine(boom)
    with pytest.raises(KeyboardInterrupt):
        m.fire("start")


def test_every_state_is_reachable_from_idle_and_only_done_aborted_are_final() -> None:
    edges = leaf_edges()
    seen, frontier = {"idle"}, ["idle"]
    while frontier:
        s = frontier.pop()
        for a, b, _ in edges:
            if a == s and b not in seen:
                seen.add(b)
                frontier.append(b)
    assert seen == set(STATES)
    assert {s for s in STATES if not any(a == s for a, _, _ in edges)} == {"done", "aborted"}
    assert set(LIFECYCLE) | set(PROBE_STEPS) == set(STATES)


def test_the_machine_leaves_the_process_wide_separator_alone() -> None:
    SessionMachine()
    diagram_markdown()
    assert NestedState.separator == "_"
