"""What the engine emits while a session runs, and who hears it (docs/design.md §4).

The engine publishes a document for each thing that happened; its subscribers (the
journal first) receive every one, in order, as it happens. Today the documents are the
state machine's transitions, named by leaf state (``ramping``, never ``probing.ramping``),
the names the journal has always stored. A subscriber that raises ends the run as any
error would (a journal that cannot write is a disk error the engine answers).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class TransitionDoc:
    """The session moved from ``source`` to ``dest`` on ``trigger``, at robot time
    ``t_robot_s`` (s), with ``step_id`` in flight (None between steps)."""

    source: str
    dest: str
    trigger: str
    t_robot_s: float
    step_id: int | None


Document = TransitionDoc
Subscriber = Callable[[Document], None]


class Publisher:
    """Hands every document to its subscribers, in the order they subscribed."""

    def __init__(self, *subscribers: Subscriber) -> None:
        self._subscribers = list(subscribers)

    def subscribe(self, subscriber: Subscriber) -> None:
        self._subscribers.append(subscriber)

    def emit(self, doc: Document) -> None:
        for subscriber in self._subscribers:
            subscriber(doc)
