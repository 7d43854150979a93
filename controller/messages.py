"""What a plan says to the engine, and how a run ends without finishing (docs/design.md §4).

The session's phases are *plans*: generators that compute what they can themselves
(clouds, targets, regions, models; each committed to the journal) and yield a
message for everything that moves the arm or the session's lifecycle. The engine
(:mod:`.engine`) carries the message out and sends back its reply; an error met
while carrying it out (the budget spent, a pause) is thrown into the plan at its
``yield``, where a plan may handle it (the budget) or let it end the run.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generator, Literal, Mapping, Union

from .probe import ProbeTarget
from .signals import OperatorFlags


@dataclass(frozen=True)
class Lifecycle:
    """Move the session's lifecycle on: ``plan`` (the controller plans steps) or ``learn``
    (it fits models). The engine fires the trigger unless the session already stands in
    its state (``LIFECYCLE_STATES``). Reply: None."""

    trigger: Literal["plan", "learn"]


# Where each lifecycle trigger leaves the session.
LIFECYCLE_STATES: dict[str, str] = {"plan": "planning", "learn": "learning"}


@dataclass(frozen=True, eq=False)
class ProbeRound:
    """Run every pending step the journal holds for ``phase`` round ``round_`` (planned and
    committed by the plan before it yields this), contact by contact, at ``targets``.
    Between contacts the engine answers the operator and checks the budget and the disk;
    a spent budget is thrown into the plan as ``BudgetSpent``. Reply: None."""

    phase: str
    round_: int
    targets: Mapping[int, ProbeTarget]


@dataclass(frozen=True)
class Sweep:
    """Sweep the scanner over the object where it is believed to be, the simulator keyed
    by ``key_step``. Reply: the :class:`~.acquire.SweepResult`."""

    key_step: int


Message = Union[Lifecycle, ProbeRound, Sweep]
# A plan: yields messages, receives each one's reply, returns nothing.
Plan = Generator[Message, Any, None]

PauseKind = Literal["pause", "operator_pause", "finish_by"]


class SessionPaused(Exception):
    """The session stopped cleanly with work left (exit 3). ``kind`` says why, for what the
    engine does next: ``operator_pause`` when it answers the operator's pause request (a
    stop requested while that pause is saved is recorded over it), ``finish_by`` when the
    plan's deadline was reached (its own notification), else ``pause`` (a stop, a fault
    whose policy pauses, a full disk, ...)."""

    def __init__(self, reason: str, kind: PauseKind = "pause") -> None:
        super().__init__(reason)
        self.kind: PauseKind = kind


def operator_pause(flags: OperatorFlags, context: str = "") -> SessionPaused:
    """The pause that answers the operator's request (a pause, or a stop: ``flags.reason``),
    ``context`` appended to the reason."""
    return SessionPaused(flags.reason + context, kind="pause" if flags.stop_now else "operator_pause")
