"""Clocks: the one source of time for the controller and the simulated cell.

The controller never calls ``time.sleep`` or ``time.monotonic`` directly; it is
given a :class:`Clock`. On the real cell that is :class:`RealClock`. In a dry run it
is :class:`VirtualClock`, whose ``sleep_s`` does not sleep but advances virtual
time and lets every registered listener (the simulated world) catch up to it, so
a dry run takes wall-clock seconds while reporting the real robot time.
"""
from __future__ import annotations

import time
from typing import Callable, Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Monotonic time in seconds."""

    def now_s(self) -> float:
        """Seconds since an arbitrary epoch, monotonic."""
        ...

    def sleep_s(self, duration_s: float) -> None:
        """Let ``duration_s`` seconds pass (wall or virtual)."""
        ...

    @property
    def is_virtual(self) -> bool: ...


class RealClock:
    """Wall-clock time (time.monotonic)."""

    is_virtual = False

    def now_s(self) -> float:
        return time.monotonic()

    def sleep_s(self, duration_s: float) -> None:
        if duration_s > 0:
            time.sleep(duration_s)


class VirtualClock:
    """Event-driven virtual time for the single-threaded simulator.

    ``sleep_s(dt)`` advances the time to ``now + dt`` and calls each listener with
    the new time, in registration order; a listener integrates its state up to
    that instant. Nothing sleeps.
    """

    is_virtual = True

    def __init__(self, start_s: float = 0.0) -> None:
        self._now_s = float(start_s)
        self._listeners: list[Callable[[float], None]] = []

    def now_s(self) -> float:
        return self._now_s

    def add_listener(self, advance_to: Callable[[float], None]) -> None:
        """Register ``advance_to(t_s)``, called every time the clock moves."""
        self._listeners.append(advance_to)

    def sleep_s(self, duration_s: float) -> None:
        if duration_s < 0:
            raise ValueError(f"cannot sleep a negative duration ({duration_s} s)")
        target_s = self._now_s + duration_s
        self._now_s = target_s
        for advance_to in self._listeners:
            advance_to(target_s)
