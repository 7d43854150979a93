"""The session state machine (docs/design.md §4): one declarative table, readable at a glance.

The session's lifecycle is the top level; the probe's micro-steps are the substates of
one ``probing`` state (``transitions``' hierarchical machine), so what may happen in any
of them (a fault, an abort) is declared once, on ``probing``.

The machine records *where* the session is; the engine fires the lifecycle's triggers
and the probing executor the probe's. Every transition is handed to ``on_transition``
(the journal) as the *leaf* states' names (``ramping``, never ``probing.ramping``), the
names the journal has always stored, and ``state`` is the leaf too. The safety monitor is
not a state: it runs where the F/T data arrives and stops the arm; the executor then
fires ``fault``.

``elastoprobe diagram`` writes the Mermaid diagram of this table to
docs/state_machine.md; a test fails when the committed diagram is stale.
"""
from __future__ import annotations

from typing import Any, Callable

from transitions import MachineError
from transitions.extensions import HierarchicalGraphMachine, HierarchicalMachine
from transitions.extensions.nesting import NestedState

from .signals import deferred_interrupts

PROBING = "probing"
# One contact, in order.
PROBE_STEPS: list[str] = ["moving_to_standoff", "reference_scan", "seeking_contact", "ramping", "holding",
                          "scanning", "unloading", "retracting"]
# Every leaf state, in the order the report lists them (the names the journal stores).
STATES: list[str] = ["idle", "preflight", "sweeping", "planning", *PROBE_STEPS,
                     "learning", "paused", "fault", "recovering", "aborted", "done"]

SEP = "."     # state names contain "_", transitions' default separator


def _p(*steps: str) -> list[str]:
    """The paths of probe steps inside ``probing``."""
    return [PROBING + SEP + s for s in steps]


_HIERARCHY: list[Any] = [*STATES[:4], {"name": PROBING, "children": PROBE_STEPS}, *STATES[4 + len(PROBE_STEPS):]]
# Where a fault may strike, and so an abort: the session at work.
_ACTIVE = ["preflight", "sweeping", "planning", PROBING, "learning", "recovering"]

#  trigger              source(s)                                                 dest
TRANSITIONS: list[dict[str, Any]] = [
    {"trigger": "start",        "source": "idle",                                 "dest": "preflight"},
    {"trigger": "sweep",        "source": ["preflight", *_p("retracting")],       "dest": "sweeping"},
    {"trigger": "plan",         "source": ["preflight", "sweeping", "learning", *_p("retracting")],
                                                                                   "dest": "planning"},
    {"trigger": "go_to_target", "source": ["planning", "preflight", "recovering", *_p("retracting")],
                                                                                   "dest": _p("moving_to_standoff")[0]},
    # One contact, inside probing.
    {"trigger": "at_standoff",  "source": _p("moving_to_standoff"),               "dest": _p("reference_scan")[0]},
    {"trigger": "reference_ok", "source": _p("reference_scan"),                   "dest": _p("seeking_contact")[0]},
    {"trigger": "contact",      "source": _p("seeking_contact"),                  "dest": _p("ramping")[0]},
    {"trigger": "at_force",     "source": _p("ramping"),                          "dest": _p("holding")[0]},
    {"trigger": "settled",      "source": _p("holding"),                          "dest": _p("scanning")[0]},
    {"trigger": "next_level",   "source": _p("scanning"),                         "dest": _p("ramping")[0]},
    {"trigger": "unload",       "source": ["recovering", *_p("scanning", "ramping", "holding", "seeking_contact")],
                                                                                   "dest": _p("unloading")[0]},
    {"trigger": "retract",      "source": ["recovering", *_p("unloading", "moving_to_standoff", "reference_scan",
                                                             "seeking_contact")], "dest": _p("retracting")[0]},
    {"trigger": "learn",        "source": ["planning", "preflight", *_p("retracting")], "dest": "learning"},
    {"trigger": "pause",        "source": ["planning", "learning", "recovering", "preflight", "fault",
                                           *_p("retracting")],                    "dest": "paused"},
    {"trigger": "resume",       "source": "paused",                               "dest": "preflight"},
    {"trigger": "fault",        "source": _ACTIVE,                                "dest": "fault"},
    {"trigger": "recover",      "source": "fault",                                "dest": "recovering"},
    {"trigger": "abort",        "source": [*_ACTIVE, "fault", "paused"],          "dest": "aborted"},
    {"trigger": "finish",       "source": ["planning", "learning", *_p("retracting")], "dest": "done"},
]


class _State(NestedState):
    # NestedState.separator is shared by every machine in the process: set it on our own class.
    separator = SEP


class _Machine(HierarchicalMachine):
    state_cls = _State


def leaf(path: str) -> str:
    """The leaf state of a state path (``probing.ramping`` -> ``ramping``)."""
    return path.rsplit(SEP, 1)[-1]


def path_of(state: str) -> str:
    """The path of a leaf state (``ramping`` -> ``probing.ramping``)."""
    return _p(state)[0] if state in PROBE_STEPS else state


class SessionMachine:
    """The model the ``transitions`` machine drives; ``state`` is the current leaf state."""

    path: str     # where the machine stands, e.g. "probing.ramping"

    def __init__(self, on_transition: Callable[[str, str, str], None] | None = None,
                 initial: str = "idle") -> None:
        self._on_transition = on_transition
        self._source = initial
        self.machine = _Machine(model=self, states=_HIERARCHY, transitions=TRANSITIONS, initial=path_of(initial),
                                auto_transitions=False, send_event=True, model_attribute="path",
                                before_state_change="_note_source", after_state_change="_journal",
                                on_exception="_reraise")

    @property
    def state(self) -> str:
        return leaf(self.path)

    def _note_source(self, event: Any) -> None:
        # A transition declared on ``probing`` names ``probing`` as its source: the journal
        # keeps the step the session was in.
        self._source = self.state

    def _journal(self, event: Any) -> None:
        if self._on_transition is not None:
            self._on_transition(self._source, self.state, event.event.name)

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
        """Whether ``trigger`` may fire where the machine stands (declared on it or on its parent)."""
        return trigger in self.machine.get_triggers(self.path)


class _GraphMachine(HierarchicalGraphMachine):
    state_cls = _State


def mermaid_diagram() -> str:
    """The state diagram as Mermaid source, generated from the table above."""

    class _Model:
        pass

    model = _Model()
    _GraphMachine(model=model, states=_HIERARCHY, transitions=TRANSITIONS, initial="idle",
                  auto_transitions=False, graph_engine="mermaid", title="Elastoprobe session")
    return model.get_graph().draw(None)   # type: ignore[attr-defined]


def diagram_markdown() -> str:
    return ("# Session state machine\n\n"
            "Generated by `elastoprobe diagram` from `controller/machine.py`; do not edit by hand.\n\n"
            "```mermaid\n" + mermaid_diagram().rstrip() + "\n```\n")
