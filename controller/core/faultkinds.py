"""The kinds of fault the simulated cell can inject: one list, read by the cell file's
schema (core/config.py), the injector (sim/faults.py), the soak (bench/soak.py) and the tests.

These are device-side causes (what breaks); the controller journals what it *sees*, under its
fault-policy keys (``force``, ``stale``, ``scanner``, ...), which are another vocabulary.
"""
from __future__ import annotations

from enum import StrEnum


class InjectedFault(StrEnum):
    """A fault the simulator can inject; the value is the name used in cell files and records."""

    FORCE_SPIKE = "force_spike"
    FT_STALL = "ft_stall"
    FT_FROZEN = "ft_frozen"
    SCANNER_TIMEOUT = "scanner_timeout"
    SCANNER_SHORT_BURST = "scanner_short_burst"
    PROTECTIVE_STOP = "protective_stop"
    CONNECTION_LOSS = "connection_loss"
    EMERGENCY_STOP = "emergency_stop"
    OBJECT_MOVED = "object_moved"
    SLIP = "slip"
    DISK_ERROR = "disk_error"


# The names in declaration order (cell files, JSON records and error messages use them).
INJECTED_FAULT_NAMES: tuple[str, ...] = tuple(k.value for k in InjectedFault)
