from pathlib import Path

import pytest

from elastoprobe.controller.machine import STATES, TRANSITIONS, SessionMachine, diagram_markdown

DOC = Path(__file__).resolve().parent.parent / "docs" / "state_machine.md"


def test_committed_diagram_is_current() -> None:
    assert DOC.read_text() == diagram_markdown(), "docs/state_machine.md is stale: run `elastoprobe diagram`"


def test_one_probe_walks_the_design_sequence_and_is_journaled() -> None:
    log: list[tuple[str, str, str]] = []
    m = SessionMachine(lambda a, b, trig: log.append((a, b, trig)))
    for trig in ["start", "plan", "go_to_target", "at_standoff", "reference_ok", "contact", "at_force",
                 "settled", "next_level", "at_force", "settled", "unload", "retract", "finish"]:
        m.fire(trig)
    assert m.state == "done"
    assert [b for _, b, _ in log][:4] == ["preflight", "planning", "moving_to_standoff", "reference_scan"]
    assert len(log) == 14


def test_impossible_transition_is_refused() -> None:
    m = SessionMachine()
    with pytest.raises(RuntimeError, match="cannot 'contact' from 'idle'"):
        m.fire("contact")
    assert m.state == "idle"


def test_fault_reachable_from_every_active_state_and_abort_is_final() -> None:
    for state in ["moving_to_standoff", "seeking_contact", "ramping", "holding", "scanning", "unloading"]:
        m = SessionMachine(initial=state)
        m.fire("fault")
        assert m.state == "fault"
        m.fire("abort")
        assert m.state == "aborted"
        assert not any(m.can(t["trigger"]) for t in TRANSITIONS)


def test_keyboard_interrupt_in_a_callback_is_not_swallowed() -> None:
    def boom(*_: object) -> None:
        raise KeyboardInterrupt

    m = SessionMachine(boom)
    with pytest.raises(KeyboardInterrupt):
        m.fire("start")


def test_every_state_is_reachable_from_idle() -> None:
    seen = {"idle"}
    frontier = ["idle"]
    while frontier:
        s = frontier.pop()
        for t in TRANSITIONS:
            srcs = t["source"] if isinstance(t["source"], list) else [t["source"]]
            if s in srcs and t["dest"] not in seen:
                seen.add(t["dest"])
                frontier.append(t["dest"])
    assert seen == set(STATES)
