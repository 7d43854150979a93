"""The session state machine (docs/design.md §4): one declarative table, readable at a glance.

The machine records *where* the session is; the probing executor does the work
and fires the triggers. Every transition is handed to ``on_transition`` (the
journal) with the robot time. The safety monitor is not a state: it runs where
the F/T data arrives and stops the arm; the executor then fires ``fault``.

``elastoprobe diagram`` writes the Mermaid diagram of this table to
docs/state_machine.md; a test fails when the committed diagram is stale.
"""
from __future__ import annotations

from typing import Any, Callable

from transitions import Machine, MachineError

from .signals import deferred_interrupts

STATES: list[str] = [
    "idle", "preflight", "sweeping", "planning", "moving_to_standoff", "reference_scan",
    "seeking_contact", "ramping", "holding", "scanning", "unloading", "retracting",
    "learning", "paused", "fault", "recovering", "aborted", "done",
]

# The probing states: a fault may strike in any of them.
_ACTIVE = ["preflight", "sweeping", "planning", "moving_to_standoff", "reference_scan", "seeking_contact",
           "ramping", "holding", "scanning", "unloading", "retracting", "learning"]

#  trigger              source(s)                                        dest
TRANSITIONS: list[dict[str, Any]] = [
    {"trigger": "start",        "source": "idle",                        "dest": "preflight"},
    {"trigger": "sweep",        "source": ["preflight", "retracting"],   "dest": "sweeping"},
    {"trigger": "plan",         "source": ["preflight", "sweeping", "learning", "retracting"], "dest": "planning"},
    {"trigger": "go_to_target", "source": ["planning", "retracting", "preflight", "recovering"],
                                                                          "dest": "moving_to_standoff"},
    {"trigger": "at_standoff",  "source": "moving_to_standoff",          "dest": "reference_scan"},
    {"trigger": "reference_ok", "source": "reference_scan",              "dest": "seeking_contact"},
    {"trigger": "contact",      "source": "seeking_contact",             "dest": "ramping"},
    {"trigger": "at_force",     "source": "ramping",                     "dest": "holding"},
    {"trigger": "settled",      "source": "holding",                     "dest": "scanning"},
    {"trigger": "next_level",   "source": "scanning",                    "dest": "ramping"},
    {"trigger": "unload",       "source": ["scanning", "ramping", "holding", "seeking_contact", "recovering"],
                                                                          "dest": "unloading"},
    {"trigger": "retract",      "source": ["unloading", "moving_to_standoff", "reference_scan",
                                           "seeking_contact", "recovering"], "dest": "retracting"},
    {"trigger": "learn",        "source": ["planning", "retracting", "preflight"], "dest": "learning"},
    {"trigger": "pause",        "source": ["retracting", "planning", "learning", "recovering", "preflight", "fault"],
                                                                          "dest": "paused"},
    {"trigger": "resume",       "source": "paused",                      "dest": "preflight"},
    {"trigger": "fault",        "source": _ACTIVE + ["recovering"],      "dest": "fault"},
    {"trigger": "recover",      "source": "fault",                       "dest": "recovering"},
    {"trigger": "abort",        "source": _ACTIVE + ["fault", "recovering", "paused"], "dest": "aborted"},
    {"trigger": "finish",       "source": ["planning", "learning", "retracting"], "dest": "done"},
]


class SessionMachine:
    """The model the ``transitions`` machine drives; ``state`` is the current state."""

    state: str

    def __init__(self, on_transition: Callable[[str, str, str], None] | None = None,
                 initial: str = "idle") -> None:
        self._on_transition = on_transition
        self.machine = Machine(model=self, states=STATES, transitions=TRANSITIONS, initial=initial,
                               auto_transitions=False, send_event=True,
                               after_state_change="_journal", on_exception="_reraise")

    def _journal(self, event: Any) -> None:
        if self._on_transition is not None:
            self._on_transition(event.transition.source, event.transition.dest, event.event.name)

    @staticmethod
    def _reraise(event: Any) -> None:
        # transitions catches BaseException here; KeyboardInterrupt and SystemExit
        # (and every other error) must propagate, never be swallowed.
        raise event.error

    def fire(self, trigger: str) -> None:
        """Fire ``trigger``; an impossible transition is a programming error, said plainly."""
        try:
            with deferred_interrupts():     # the state and its journal record change together
                self.trigger(trigger)   # type: ignore[attr-defined]
        except MachineError as exc:
            raise RuntimeError(f"state machine: cannot {trigger!r} from {self.state!r}") from exc

    def can(self, trigger: str) -> bool:
        return bool(self.machine.get_triggers(self.state).count(trigger))


def mermaid_diagram() -> str:
    """The state diagram as Mermaid source, generated from the table above."""
    from transitions.extensions import GraphMachine

    class _Model:
        pass

    model = _Model()
    GraphMachine(model=model, states=STATES, transitions=TRANSITIONS, initial="idle",
                 auto_transitions=False, graph_engine="mermaid", title="Elastoprobe session")
    return model.get_graph().draw(None)   # type: ignore[attr-defined]


def diagram_markdown() -> str:
    return ("# Session state machine\n\n"
            "Generated by `elastoprobe diagram` from `controller/machine.py`; do not edit by hand.\n\n"
            "```mermaid\n" + mermaid_diagram().rstrip() + "\n```\n")
