"""Two vocabularies of faults, one list each.

:class:`InjectedFault`: the kinds of fault the simulated cell can inject (device-side
causes: what breaks), read by the cell file's schema (core/config.py), the injector
(sim/faults.py), the soak (bench/soak.py) and the tests.

:class:`FaultKind`: what the controller *sees* and journals (a trip of the safety guard, a
fault of a step), and the keys of a plan's ``fault_policy``.
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


class FaultKind(StrEnum):
    """A fault as the controller sees it; the value is the journal's ``kind`` and the plan's
    ``fault_policy`` key."""

    # The safety guard's trips (core/safety.py), in the order it checks them.
    FORCE = "force"
    TORQUE = "torque"
    LATERAL_FORCE = "lateral_force"
    FORCE_RATE = "force_rate"
    FROZEN = "frozen"
    FT_STATUS = "ft_status"
    STALE = "stale"
    SLIP = "slip"
    CONNECTION = "connection"
    # The arm and cell.
    WORKSPACE = "workspace"
    PROTECTIVE_STOP = "protective_stop"
    EMERGENCY_STOP = "emergency_stop"
    OPERATOR_STOP = "operator_stop"
    MOTION_REFUSED = "motion_refused"
    DEVICE = "device"
    # A step's own checks.
    NO_CONTACT = "no_contact"
    FORCE_NOT_HELD = "force_not_held"
    OBJECT_MOVED = "object_moved"
    SCANNER = "scanner"


# An operator's stop is the operator's decision, not the plan's: it always pauses.
POLICY_FAULT_KINDS: tuple[str, ...] = tuple(k.value for k in FaultKind if k is not FaultKind.OPERATOR_STOP)
