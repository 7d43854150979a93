"""Start-up handshake of the driver child processes (the UR link, the hardware process).

A child sends ``("ready", identity)`` once its devices answer, or ``("fatal", why)``;
the parent waits for one of them, bounded in time, and notices a child that died.
"""
from __future__ import annotations

import time
from typing import Any

from ..core.errors import DeviceError


def await_ready(proc: Any, conn: Any, timeout_s: float, what: str) -> dict[str, Any]:
    """The child's identity once it reports ready; DeviceError if it fails, dies or is late.

    The caller kills the child when this raises.
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if conn.poll(0.05):
            try:
                msg = conn.recv()
            except EOFError:
                break
            if msg[0] == "ready":
                return dict(msg[1])
            if msg[0] == "fatal":
                raise DeviceError(f"{what} failed to start: {msg[1]}")
        elif not proc.is_alive():
            break
    raise DeviceError(f"{what} did not become ready (exit code {proc.exitcode})")


def kill_child(proc: Any, conn: Any, join_s: float) -> None:
    """Kill a child process (if alive) and close its pipe."""
    if proc is not None and proc.is_alive():
        proc.kill()
        proc.join(join_s)
    if conn is not None:
        try:
            conn.close()
        except OSError:
            pass
