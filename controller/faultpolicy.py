"""The fault policy, carried out (docs/design.md §5): stop, journal, recover, then the plan's action.

A fault met by a contact or a sweep stops the arm first, is journaled with its raw F/T
data and then follows the plan's ``fault_policy`` for its kind: retry (up to
``retries``), skip the target, pause, or abort. Recovery makes the arm movable again:
it clears a protective stop (never an emergency stop), waits for the connection and for
a fresh F/T stream, retracts and re-arms. A fault met during a recovery is journaled as
its own; when its kind's policy is retry it gets one nested recovery, never two, and the
operator's stops and a failing disk always pause (``NEVER_NESTED``).

The engine (:mod:`.engine`) owns one :class:`FaultPolicy` and hands it the faults it meets.
"""
from __future__ import annotations

from typing import Any, Callable

from .core.config import SessionInputs
from .core.devices import Cell, Trip, same_trip
from .core.errors import DeviceError, ElastoprobeError, SessionAborted
from .core.safety import stream_health_guard
from .journal import Journal, StepRecord
from .machine import SessionMachine
from .messages import SessionPaused, operator_pause
from .probe import ProbeExecutor, ProbeFault
from .signals import OperatorFlags

# Faults that are, or may be, a lost connection to the robot (a command's DeviceError):
# their recovery waits for it to come back; for any other fault, the connection lost
# while recovering is a second fault.
CONNECTION_FAULT_KINDS = frozenset({"connection", "device"})
# Faults met during a recovery that always pause, whatever their kind's policy: the operator's
# (an e-stop, a stop at the robot) and a journal that cannot be written (docs/design.md).
NEVER_NESTED = frozenset({"emergency_stop", "operator_stop", "disk_error"})
# How a sweep's faults are told apart in the journal (they have no step).
SWEEP_FAULT_PREFIX = "during a sweep of the object"


class FaultPolicy:
    """Carries out the plan's fault policy on the session's cell.

    ``log_event(event, **record)``: the session's event log; ``notify(event, message)``: the
    operator's notification; ``on_object_moved()``: register the object again (after an
    ``object_moved`` fault was recovered from and its policy lets the session go on)."""

    def __init__(self, inputs: SessionInputs, journal: Journal, cell: Cell, executor: ProbeExecutor,
                 machine: SessionMachine, flags: OperatorFlags, log_event: Callable[..., None],
                 notify: Callable[[str, str], None], on_object_moved: Callable[[], None]) -> None:
        self.inputs = inputs
        self.journal = journal
        self.cell = cell
        self.executor = executor
        self.machine = machine
        self.flags = flags
        self._log = log_event
        self._notify = notify
        self._on_object_moved = on_object_moved

    def stop_arm(self) -> None:
        """Stop the arm; with the link down the command cannot reach it (the robot's own
        watchdog stops it when the control link dies), which is said in the log."""
        try:
            self.cell.arm.stop()
        except DeviceError as exc:
            self._log("stop_not_sent", message=str(exc))

    def wait_stopped(self, max_s: float = 2.0) -> dict[str, Any]:
        """Let the arm come to rest after stop() (bounded), and say how it stands."""
        arm, clock = self.cell.arm, self.cell.clock
        status = arm.status()
        waited = 0.0
        while status.is_moving and waited < max_s:
            clock.sleep_s(0.01)
            waited += 0.01
            self.cell.ft.read_block()
            status = arm.status()
        return {"is_moving": bool(status.is_moving), "tcp_speed_mm_s": float(status.tcp_speed_mm_s),
                "protective_stop": bool(status.protective_stop), "emergency_stop": bool(status.emergency_stop),
                "connected": bool(status.connected), "link_generation": int(status.link_generation),
                "t_robot_s": float(status.t_s), "waited_s": round(waited, 3)}

    def retry_index(self, step_id: int) -> int:
        """Faults recorded against a step: its retry number (kills do not count, so a
        resumed session draws the same simulator noise as an uninterrupted one)."""
        return len(self.journal.faults(step_id=step_id, with_raw=False))

    def sweep_faults(self) -> int:
        """Faults the journal holds against sweeps of the object (this run's and earlier ones'):
        the sweep's attempt number, counted across a pause and resume."""
        return sum(1 for f in self.journal.faults(with_raw=False)
                   if f.step_id is None and f.message.startswith(SWEEP_FAULT_PREFIX))

    def handle_contact_fault(self, fault: ProbeFault, group: list[StepRecord]) -> None:
        """Stop first (the device already did), journal, retract, then follow the policy."""
        j = self.journal
        self.stop_arm()
        arm_state = self.wait_stopped()
        open_steps = [r for r in group if j.step(r.step_id).status not in ("done", "skipped")]
        step_id = open_steps[0].step_id if open_steps else None
        if fault.kind == "operator_stop":
            self._log("operator_stop", step=step_id, message=fault.message)
            # A request by signal or `elastoprobe pause/stop` says so; a stop at the robot
            # (its program stopped without a safety stop) says what the robot reported.
            if self.flags.pause_requested:
                raise operator_pause(self.flags)
            raise SessionPaused(f"stopped by the operator: {fault.message}")
        policy = self.inputs.plan.fault_policy.for_kind(fault.kind)
        retries_so_far = self.retry_index(step_id) if step_id is not None else 0
        action = policy.action
        if action == "retry" and (retries_so_far >= policy.retries or fault.kind == "motion_refused"):
            # A refused motion is refused again: retrying it would only spend the budget.
            action = "skip_target"
        raw = fault.trip.raw if fault.trip is not None else None
        fault_id = j.record_fault(fault.kind, fault.message, t_robot_s=self.cell.clock.now_s(),
                                  step_id=step_id, policy_action=action, raw=raw)
        self._log("fault", kind=fault.kind, message=fault.message, step=step_id, action=action,
                  fault_id=fault_id, arm=arm_state)
        self._notify("fault", f"{fault.kind} at step {step_id}: {fault.message} -> {action}")
        self.machine.fire("fault")
        self.machine.fire("recover")
        failed = self._recover(fault, step_id, since_generation=arm_state["link_generation"])
        if failed is not None and action in ("retry", "skip_target"):
            action = "pause"
        if action == "skip_target":
            for rec in open_steps:
                j.skip_step(rec.step_id, f"{fault.kind}: {fault.message}")
        why = f"{fault.kind}: {fault.message}" + (f"; recovery failed: {failed}" if failed is not None else "")
        if action == "pause":
            raise SessionPaused(why)
        if action == "abort":
            raise SessionAborted(why)
        # Back to a known place before the next contact.
        self.machine.fire("retract")
        if fault.kind == "object_moved":
            self._on_object_moved()

    def handle_sweep_fault(self, fault: ProbeFault, attempt: int) -> None:
        """A fault during the cloud sweep (no step is open): stop, journal, recover; the
        caller sweeps again while the policy allows a retry, else the session pauses."""
        self.stop_arm()
        arm_state = self.wait_stopped()
        if fault.kind == "operator_stop":
            self._log("operator_stop", phase="cloud", arm=arm_state)
            raise operator_pause(self.flags, " during a sweep (resume sweeps again)")
        policy = self.inputs.plan.fault_policy.for_kind(fault.kind)
        action = policy.action
        if action in ("retry", "skip_target"):
            action = "retry" if attempt < policy.retries else "pause"
        raw = fault.trip.raw if fault.trip is not None else None
        fault_id = self.journal.record_fault(fault.kind, f"{SWEEP_FAULT_PREFIX}: {fault.message}",
                                             t_robot_s=self.cell.clock.now_s(), policy_action=action, raw=raw)
        self._log("fault", kind=fault.kind, message=fault.message, step=None, action=action,
                  fault_id=fault_id, arm=arm_state, phase="cloud")
        self.machine.fire("fault")
        self.machine.fire("recover")
        failed = self._recover(fault, since_generation=arm_state["link_generation"])
        if failed is not None and action == "retry":
            action = "pause"
        why = (f"{fault.kind} {SWEEP_FAULT_PREFIX}: {fault.message}"
               + (f"; recovery failed: {failed}" if failed is not None else ""))
        if action == "pause":
            raise SessionPaused(why)
        if action == "abort":
            raise SessionAborted(why)
        # The machine has no "sweep" from retracting: the sweep runs again from there.
        self.machine.fire("retract")

    def _await_connection(self, max_s: float = 10.0) -> Any:
        """The arm's status once it is connected again (bounded wait), else None."""
        waited = 0.0
        while True:
            status = self.cell.arm.status()
            if status.connected:
                return status
            if waited >= max_s:
                self._log("connection_not_back", waited_s=waited)
                return None
            self.cell.clock.sleep_s(0.1)
            waited += 0.1
            try:
                self.cell.ft.read_block()
            except DeviceError:
                pass

    def _recover(self, fault: ProbeFault, step_id: int | None = None, since_generation: int | None = None,
                 root: ProbeFault | None = None) -> str | None:
        """Make the arm movable again: protective-stop recovery, re-arm, retract. Never clears an e-stop.

        None when the arm is movable again, else why not (for the pause reason: the operator
        at the cell reads it first). ``since_generation``: the link generation when the fault
        was met (ArmStatus.link_generation); a higher one afterwards is a connection lost and
        regained inside this recovery. ``root``: the fault whose recovery this one is nested
        in (docs/design.md, fault policy: one nested recovery, never two).
        """
        arm = self.cell.arm
        if since_generation is None:
            since_generation = arm.status().link_generation
        if fault.kind not in CONNECTION_FAULT_KINDS and not arm.status().connected:
            # The connection dropped after this fault was seen: a fault of its own.
            return self._fault_during_recovery(fault, root, step_id, "connection",
                                               "lost the connection to the robot", None, "waiting to recover")
        status = self._await_connection()
        if status is None:
            return "the arm did not reconnect within 10 s"
        if fault.kind in CONNECTION_FAULT_KINDS:
            # The loss that is this fault is behind us: only a later one is a fault of its own.
            since_generation = max(since_generation, status.link_generation)
        # A stop this recovery (or the one it is nested in) is about is not a new fault.
        about = {fault.kind} | ({root.kind} if root is not None else set())
        if status.emergency_stop:
            if "emergency_stop" not in about:
                # Pressed while this fault was handled: its own fault, and the operator's.
                failed = self._fault_during_recovery(fault, root, step_id, "emergency_stop",
                                                     "emergency stop is pressed", None, "waiting to recover")
                return f"{failed} (release it at the cell, then resume)"
            return "the emergency stop is still engaged (release it at the cell, then resume)"
        if status.protective_stop and "protective_stop" not in about:
            # The robot stopped itself while this fault was handled: after a lost link (neither
            # the link's restart nor the watchdog makes a protective stop), or the UR's own
            # limit along with a force trip. A fault of its own (no guard trip, so no raw F/T),
            # never unlocked unnamed. A trip the guard latched meanwhile (an F/T spike while
            # the link was down) is one more: journaled too, and named in the pause.
            nests = self._nests("protective_stop", root)
            failed = self._fault_during_recovery(fault, root, step_id, "protective_stop",
                                                 "the robot is in a protective stop", None, "waiting to recover")
            if failed is not None and not nests:
                _, tripped = self._trip_since(fault, root, step_id, "waiting to recover", may_nest=False)
                return failed + (f"; {tripped}" if tripped else "")
            return failed
        if status.protective_stop and not arm.recover_protective_stop():
            if arm.status().emergency_stop and "emergency_stop" not in about:
                # Pressed while the stop was being unlocked (the unlock fails then).
                failed = self._fault_during_recovery(fault, root, step_id, "emergency_stop",
                                                     "emergency stop is pressed", None, "waiting to recover")
                return f"{failed} (release it at the cell, then resume)"
            return "the protective stop could not be cleared from the dashboard"
        # The guard keeps checking while the controller waits for the connection or the
        # dashboard: a trip latched since this fault (a stalled or frozen F/T stream, a
        # spike) is a fault of its own, not part of this one, and is never re-armed unseen.
        met, failed = self._trip_since(fault, root, step_id, "waiting to recover")
        if met:
            return failed
        # A retract started on a stream still frozen or ringing from a spike trips again on
        # the very fault it recovers from: wait (bounded) for fresh samples first.
        self._await_fresh_ft()
        self.executor.acknowledged_trip = arm.trip()
        try:
            self.executor.safe_retract()
        except (ProbeFault, ElastoprobeError) as exc:
            # A second fault while recovering from the first: journaled too, so the pause
            # that follows names both.
            self.stop_arm()
            kind = exc.kind if isinstance(exc, ProbeFault) else "device"
            self.executor.acknowledged_trip = None
            return self._fault_during_recovery(fault, root, step_id, kind, str(exc),
                                               exc.trip if isinstance(exc, ProbeFault) else None, "while retracting")
        finally:
            self.executor.acknowledged_trip = None
        # Re-arm only after the state change (retracted), below the hysteresis level.
        for _ in range(50):
            met, failed = self._trip_since(fault, root, step_id, "after retracting")
            if met:
                return failed
            if arm.rearm():
                return self._lost_link_since(fault, root, step_id, since_generation)
            self.cell.clock.sleep_s(0.1)
            self.cell.ft.read_block()
        return "the force limits could not be re-armed within 5 s of retracting (the F/T still reads over them)"

    def _lost_link_since(self, fault: ProbeFault, root: ProbeFault | None, step_id: int | None,
                         since_generation: int) -> str | None:
        """The recovery is done; if the link was lost and regained inside it (its generation
        rose), that loss is a fault of its own: the robot's watchdog stopped the program
        meanwhile and the arm was moved on a link that had dropped."""
        try:
            status = self.cell.arm.status()
        except DeviceError as exc:
            return self._fault_during_recovery(fault, root, step_id, "device", str(exc), None, "after retracting")
        if status.link_generation <= since_generation:
            return None
        lost = status.link_generation - since_generation
        return self._fault_during_recovery(
            fault, root, step_id, "connection",
            f"lost the connection to the robot and regained it ({lost} time{'s' if lost > 1 else ''})", None,
            "while recovering")

    def _await_fresh_ft(self, clean_for_s: float | None = None, max_s: float = 0.5) -> bool:
        """Wait (bounded, robot time) until the F/T stream has been healthy for ``clean_for_s``
        (default: twice the frozen or rate window, whichever is longer): no frozen run, no
        status word, no force-rate crossing, no gap. True if it was, False at ``max_s``."""
        limits = self.inputs.limits
        ft, clock = self.cell.ft, self.cell.clock
        need_s = clean_for_s if clean_for_s is not None else 2e-3 * max(limits.ft_frozen_ms, limits.rate_window_ms)
        guard = stream_health_guard(limits, ft.rate_hz)
        clean_since: float | None = None
        waited, period_s = 0.0, 0.01
        while waited < max_s:
            clock.sleep_s(period_s)
            waited += period_s
            try:
                block = ft.read_block()
            except DeviceError:
                clean_since = None
                continue
            if not len(block) or guard.check_block(block) is not None or guard.check_stale(clock.now_s()):
                guard.tripped, clean_since = None, None
                continue
            clean_since = float(block.t_s[0]) if clean_since is None else clean_since
            if float(block.t_s[-1]) - clean_since >= need_s:
                return True
        self._log("ft_not_fresh", waited_s=round(waited, 3))
        return False

    def _fault_during_recovery(self, fault: ProbeFault, root: ProbeFault | None, step_id: int | None, kind: str,
                               message: str, trip: Trip | None, when: str, may_nest: bool = True) -> str | None:
        """A fault met while recovering from ``fault``: journaled as its own fault. When its
        kind's policy is retry and this recovery is not nested already, recover from it once
        (a nested recovery; None if that made the arm movable again); else say why recovery
        failed (the session pauses, its reason naming both). E-stops, disk errors and
        operator stops always pause."""
        outer = root if root is not None else fault
        nest = may_nest and self._nests(kind, root)
        note = "" if root is None else f" (while recovering from the {fault.kind} met in that recovery)"
        self.journal.record_fault(kind, f"during recovery from {outer.kind}: {message}{note}",
                                  t_robot_s=self.cell.clock.now_s(), step_id=step_id,
                                  policy_action="retry" if nest else "pause",
                                  raw=trip.raw if trip is not None else None)
        if not nest:
            self._log("recovery_failed", kind=kind, message=message, during=fault.kind, nested=root is not None)
            return f"{kind} {when}: {message}"
        self._log("nested_recovery", kind=kind, message=message, during=fault.kind)
        return self._recover(ProbeFault(kind, message, trip), step_id, root=outer)

    def _nests(self, kind: str, root: ProbeFault | None) -> bool:
        """Whether a fault of ``kind`` met during a recovery gets a nested recovery: its kind's
        policy is retry, it is not the operator's or the disk's, and the recovery it was met
        in is not itself nested (``root`` None)."""
        policy = self.inputs.plan.fault_policy.for_kind(kind)
        return root is None and policy.action == "retry" and policy.retries > 0 and kind not in NEVER_NESTED

    def _trip_since(self, fault: ProbeFault, root: ProbeFault | None, step_id: int | None, when: str,
                    may_nest: bool = True) -> tuple[bool, str | None]:
        """Whether the arm's guard holds a trip other than those of ``fault`` and ``root``
        (latched while recovering from them): a fault of its own, handled by
        :meth:`_fault_during_recovery`; with it, why recovery failed (None: a nested
        recovery made the arm movable again)."""
        try:
            trip = self.cell.arm.trip()
        except DeviceError as exc:
            return True, self._fault_during_recovery(fault, root, step_id, "device", str(exc), None, when, may_nest)
        if trip is None or same_trip(trip, fault.trip) or (root is not None and same_trip(trip, root.trip)):
            return False, None
        self.stop_arm()
        return True, self._fault_during_recovery(fault, root, step_id, trip.kind, trip.message, trip, when, may_nest)
