"""The UR arm's motion primitives over the link, in the controller's units, with ur_rtde's thread rule.

What the force loop's supervisor (controller/core/forceloop.py) commands a UR with: a straight move
(moveL, asynchronous), a speed command (speedL) and a stop. ur_rtde 1.6.5's control script runs
speedL in a thread of its own, which a moveL does not stop and a stopL does not reach: a moveL
or a stopL while it runs makes a second thread command the robot, and URScript halts the
program (docs/ur_emulation.md, "Threads"). So the primitives track that thread (``speeding``:
a speedL since the last speedStop or program start) and keep to the rule: a move ends the
speed command with speedStop first, and a stop is speedStop while it runs, stopL otherwise.

Not thread-safe by itself: the hardware process calls it under its gate lock. Units: mm,
mm/s, mm/s^2 (the link speaks ur_rtde's m, m/s, m/s^2).
"""
from __future__ import annotations

import numpy as np

from .ur_link import LinkMove, URLink


class URPrimitives:
    """Moves, speed commands and stops of the UR behind ``link``; stops at ``stop_decel_mm_s2``.

    ``direct_stop``: stops go down the link's stop pipe (``URLink.stop_now``) rather than as a
    call behind its request lock (bench/safety_latency.py times both).
    """

    def __init__(self, link: URLink, stop_decel_mm_s2: float, direct_stop: bool = True) -> None:
        self.link = link
        self.stop_decel_mm_s2 = float(stop_decel_mm_s2)
        self.direct_stop = bool(direct_stop)
        self.speeding = False

    def move_linear(self, target_ur: np.ndarray, speed_mm_s: float, accel_mm_s2: float) -> LinkMove:
        """moveL (asynchronous) to ``target_ur`` (ur units: m, rotation vector), after a
        speedStop if a speed command runs."""
        if self.speeding:
            self.link.speed_stop(self.stop_decel_mm_s2 * 1e-3)
            self.speeding = False
        return self.link.move_linear(target_ur, speed_mm_s * 1e-3, accel_mm_s2 * 1e-3)

    def speed_linear(self, velocity_mm_s: np.ndarray, accel_mm_s2: float) -> None:
        """speedL: the TCP velocity (base frame, no rotation) reached at ``accel_mm_s2``."""
        self.link.speed_linear(np.concatenate([np.asarray(velocity_mm_s, float) * 1e-3, np.zeros(3)]),
                               accel_mm_s2 * 1e-3)
        self.speeding = True

    def stop(self) -> int | None:
        """Stop now: speedStop while the speed command runs, stopL otherwise. Returns the stop
        pipe's sequence number (None when the stop went as a call)."""
        speed_stop, self.speeding = self.speeding, False
        decel_m_s2 = self.stop_decel_mm_s2 * 1e-3
        if self.direct_stop:
            return self.link.stop_now(not speed_stop, decel_m_s2)
        if speed_stop:
            self.link.speed_stop(decel_m_s2)
        else:
            self.link.stop_linear(decel_m_s2)
        return None

    def program_restarted(self) -> None:
        """A new control program (a recovery, the link's restart): no speed thread runs."""
        self.speeding = False


__all__ = ["URPrimitives"]
