"""The engine: runs a session's plan on a cell (docs/design.md §4, §5, §6).

One object owns what happens while a plan runs: the state machine (the session's
lifecycle and the probe's steps), the contact loop with its checkpoints (the
operator's requests, the budget, the disk, answered between contacts), the fault
policy (:mod:`.faultpolicy`, handed the faults it meets), and how a run ends (done,
paused, aborted, fault: the exit codes). The plan (:mod:`.phases`) yields messages
(:mod:`.messages`); the engine carries each out and sends the reply back, or throws
what it met into the plan.

The session (:mod:`.session`) sets the run up (lock, journal, cell, registration)
and hands the plan to the engine.
"""
from __future__ import annotations

import datetime as _dt
import sqlite3
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from .acquire import SweepResult, SweepSettings, acquire_cloud, line_footprint_mm
from .core.collision import shapes_from_cell
from .core.config import SessionInputs, effective_motion_limits
from .core.devices import Cell
from .core.errors import BudgetSpent, DeviceError, DiskError, ElastoprobeError, MotionRefused, SessionAborted
from .core.validation import build_validator
from .documents import Document, Publisher, TransitionDoc
from .faultpolicy import FaultPolicy
from .journal import Journal, JournalCorruption, JournalError, StepRecord, StepResult
from .machine import SessionMachine
from .memory import ContactCounter, release_freed_memory
from .messages import LIFECYCLE_STATES, Lifecycle, Message, Plan, ProbeRound, SessionPaused, Sweep, operator_pause
from .notify import DiskWatch, Notifier
from .phases import FOOT_LINK_SPACINGS, SWEEP_STEP_KEY, measure_step_data, plan_grid, remove_table_below
from .placement import PlacementMonitor, reregister
from .probe import ForceLevel, ProbeExecutor, ProbeFault, ProbeSettings, ProbeTarget, StepData
from .report import write_report
from .signals import OperatorFlags, OperatorInterrupt, deferred_interrupts
from .testing import play_disk_error

EXIT_DONE, EXIT_FAULT, EXIT_PAUSED = 0, 1, 3

# The simulator key of a learning phase (minus the models round): below the sweep keys
# (phases.SWEEP_STEP_KEY = 2**32 - 2, re-registration sweeps just under it), far above
# every planned step id.
LEARN_STEP_KEY = 2**32 - 1002


class InternalError(ElastoprobeError):
    """An unexpected error inside the controller; the arm was stopped and parked (exit 1)."""


@dataclass
class Progress:
    """What the progress display and ``status`` show."""

    phase: str = ""
    state: str = "idle"
    target: int | None = None
    steps_done: int = 0
    steps_total: int = 0
    robot_s: float = 0.0
    started_wall_s: float = field(default_factory=time.monotonic)

    def eta_robot_s(self) -> float | None:
        if self.steps_done == 0:
            return None
        return self.robot_s / self.steps_done * max(self.steps_total - self.steps_done, 0)


class RawLog(Protocol):
    """DIR/log.jsonl (session.JsonlLog): written when the journal cannot take a record."""

    def write(self, event: str, **record: Any) -> None: ...


class Engine:
    """Runs one plan on a session's cell; :meth:`run` returns the exit code.

    ``world``: the built cell's model of the object (cellfactory.BuiltCell: its mesh);
    ``log_event``: the session's event log (log.jsonl and the journal's events)."""

    def __init__(self, inputs: SessionInputs, session_dir: Path, seed: int, journal: Journal, cell: Cell,
                 world: Any, flags: OperatorFlags, log: RawLog, log_event: Callable[..., None],
                 progress: Progress, on_progress: Callable[[Progress], None]) -> None:
        self.inputs = inputs
        self.dir = session_dir
        self.seed = seed
        self.journal = journal
        self.cell = cell
        self.world = world
        self.flags = flags
        self.log = log
        self._log = log_event
        self.progress = progress
        self.memory = ContactCounter()          # resident memory stays what is live, all night
        self.on_progress = on_progress
        self.journal_damaged = False          # the session abandons a damaged journal
        self._current_step: int | None = None
        self._disk_warned = False
        # What happens is published; the journal records it, then the simulator is keyed.
        self.documents = Publisher(journal.receive, self._on_document)
        self.machine = SessionMachine(self._emit_transition)
        self.executor = self._make_executor(self.machine)
        self.faults = FaultPolicy(inputs, journal, cell, self.executor, self.machine, flags, log_event,
                                  self._notify, self._reregister)

    # ------------------------------------------------------------------ documents
    def _emit_transition(self, source: str, dest: str, trigger: str) -> None:
        self.documents.emit(TransitionDoc(source, dest, trigger, float(self.cell.clock.now_s()), self._current_step))

    def _on_document(self, doc: Document) -> None:
        if doc.dest == "learning":
            self._key_learning()

    # ------------------------------------------------------------------ the plan
    def _drive(self, plan: Plan) -> None:
        """Carry out the plan's messages in order; what a message met is thrown into the
        plan at its ``yield`` (it handles a spent budget, anything else ends the run)."""
        reply: Any = None
        error: BaseException | None = None
        while True:
            try:
                msg = plan.throw(error) if error is not None else plan.send(reply)
            except StopIteration:
                return
            reply, error = None, None
            try:
                reply = self._carry_out(msg)
            except BaseException as exc:      # OperatorInterrupt too: the plan ends with it
                error = exc

    def _carry_out(self, msg: Message) -> Any:
        if isinstance(msg, Lifecycle):
            # Already there is not a move (planning asked to plan): every other refusal of the
            # machine is a programming error and raises. No path is known to reach the skip
            # (none in the tests or the demo); it is kept because skipping is harmless by
            # construction and an internal error at night would not be.
            if self.machine.state != LIFECYCLE_STATES[msg.trigger]:
                self.machine.fire(msg.trigger)
            return None
        if isinstance(msg, ProbeRound):
            self.progress.steps_total = len(self.journal.steps())
            self.run_steps(msg.phase, msg.round_, msg.targets)
            return None
        if isinstance(msg, Sweep):
            return self.sweep_object(msg.key_step)
        raise TypeError(f"the engine cannot carry out {msg!r}")

    def run(self, plan: Plan, resume: bool = False) -> int:
        """Run ``plan`` to its end; the exit code (done 0, fault or aborted 1, paused 3).

        A resumed session first unloads and retracts from wherever the arm stands."""
        j = self.journal
        machine = self.machine
        try:
            machine.fire("start")
            if resume:
                self._recover_pose()
            # Computation between the contacts (planning, learning, the map and report)
            # ends at once on a pause or stop; contacts and sweeps end at their own
            # checkpoints (signals.py).
            with self.flags.interruptible():
                self._drive(plan)
            machine.fire("finish")
            j.set_status("done")
            self._log("session_done")
            self._epilogue("finish", "session done")
            return EXIT_DONE
        except (SessionPaused, OperatorInterrupt) as exc:
            self.flags.acknowledge()
            paused = exc if isinstance(exc, SessionPaused) else operator_pause(self.flags)
            reason = str(paused)
            if self.flags.stop_now:
                self.faults.stop_arm()
            self._park()
            # pause is declared where the session stops between contacts (and from a fault);
            # a stop in a sweep or mid-contact (the operator's) leaves the machine, and so the
            # journal's last state and `status`, where the session stopped.
            if machine.can("pause"):
                machine.fire("pause")
            j.set_status("paused", reason)
            self._log("session_paused", reason=reason)
            self._epilogue("finish_by" if paused.kind == "finish_by" else "pause", reason)
            if paused.kind == "operator_pause" and self.flags.stop_now:
                # The operator's second request came while the pause was being saved: a stop.
                j.set_status("paused", self.flags.reason)
                self._log("session_paused", reason=self.flags.reason)
            return EXIT_PAUSED
        except JournalCorruption as exc:
            # Stored data is damaged: stop and park, and write nothing more to the journal
            # (its status stays what it was); the CLI says what is damaged and how to salvage.
            self.journal_damaged = True
            self.faults.stop_arm()
            self._park(journal=False)
            self.log.write("session_stopped", reason=f"journal damaged: {exc}")
            raise
        except SessionAborted as exc:
            self._park()
            machine.fire("abort")
            j.set_status("aborted", str(exc))
            self._log("session_aborted", reason=str(exc))
            self._epilogue("fault", f"aborted: {exc}")
            return EXIT_FAULT
        except (JournalError, sqlite3.OperationalError, DiskError) as exc:
            # The journal or a file could not be written (disk full, I/O error, read-only):
            # nothing half-written survives (each write is one transaction or an atomic
            # rename), so stop, park and pause; the session resumes once the disk is fixed.
            # Recording the pause may fail too.
            self.faults.stop_arm()
            self._park(journal=False)
            reason = str(exc) if isinstance(exc, DiskError) else f"journal write failed: {type(exc).__name__}: {exc}"
            self.log.write("session_paused", reason=reason, disk_error=True)
            try:
                j.set_status("paused", reason)
            except (JournalError, sqlite3.Error):
                pass
            return EXIT_PAUSED
        except Exception as exc:
            # A bug or an unplanned device error: stop and park the arm first, keep the
            # journal consistent (the session stays resumable), and leave the traceback
            # in the log for the developers.
            self.faults.stop_arm()
            self._park()
            j.set_status("fault", f"{type(exc).__name__}: {exc}")
            self._log("internal_error", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            raise InternalError(f"{type(exc).__name__}: {exc} (details in {self.dir / 'log.jsonl'}; "
                                f"the session can be resumed)") from exc

    def _make_executor(self, machine: SessionMachine) -> ProbeExecutor:

        inputs = self.inputs
        m = effective_motion_limits(inputs)
        pr = inputs.plan.probing
        settings = ProbeSettings(
            scans_per_step=pr.scans_per_step, settle_s=pr.settle_s, standoff_mm=pr.standoff_mm,
            force_rate_n_s=pr.force_rate_n_s, force_tolerance_n=pr.force_tolerance_n,
            contact_force_n=m["contact_force_n"], contact_speed_mm_s=m["contact_speed_mm_s"],
            free_speed_mm_s=m["free_speed_mm_s"], free_accel_mm_s2=m["free_accel_mm_s2"],
            search_distance_mm=m["search_distance_mm"], tip_radius_mm=inputs.cell.tool.tip_radius_mm)
        validator = build_validator(inputs, self.cell, self.world.object_mesh)
        top_z = float(self.cell.base_to_object.apply(self.world.object_mesh.vertices)[:, 2].max())
        placement = None
        if pr.object_moved_mm is not None:
            placement = PlacementMonitor(self.world.object_mesh, pr.object_moved_mm, seed=self.seed)
        executor = ProbeExecutor(self.cell, machine, settings, validator, top_z,
                                 should_stop=lambda: self.flags.stop_now, placement=placement)
        executor.on_placement = self._on_placement
        executor.on_regulated = lambda record: self._log("force_regulated", **record)
        executor.on_unload_shortened = lambda record: self._log("unload_shortened", step=self._current_step,
                                                                **record)
        return executor

    def _on_placement(self, what: str, estimate: dict[str, Any]) -> None:
        """Log placement checks that come anywhere near the threshold (the rest is noise)."""
        limit = self.inputs.plan.probing.object_moved_mm
        if limit is not None and estimate["horizontal_mm"] > 0.5 * limit:
            self._log("placement_check", what=what, step=self._current_step, **estimate)

    def _recover_pose(self) -> None:
        """Resume starts by reading |F| and the pose, and unloads/retracts before anything else."""
        status = self.cell.arm.status()
        block = self.cell.ft.read_block()
        force = float(np.linalg.norm(block.force_n[-1])) if len(block) else 0.0
        self._log("resume_state", force_n=force, tcp_mm=status.tcp_pose.position_mm)
        self.executor.safe_retract()

    def _park(self, journal: bool = True) -> None:
        """Retract to travel height (best effort: the arm is stopped); ``journal=False`` when
        the journal cannot take the record (damaged, or its disk failing)."""
        self.executor.acknowledged_trip = self.cell.arm.trip()
        try:
            self.executor.safe_retract()
        except (ProbeFault, ElastoprobeError) as exc:
            if journal:
                self._log("park_failed", message=str(exc))
            else:
                self.log.write("park_failed", message=str(exc))

    def _key_learning(self) -> None:
        """Key the simulator for a learning phase, as for a sweep or a step: the cell lives on
        while the controller learns (a stop or a lost connection then is met at the next
        motion). Keyed by the models rounds already committed, so a resumed session that
        learns the same round again uses the same key."""
        rounds = sum(1 for p in self.journal.phases() if p["name"] == "models")
        self.cell.begin_step((self.seed, LEARN_STEP_KEY - rounds, 0))

    def sweep_object(self, key_step: int) -> SweepResult:
        """Sweep the scanner over the object where it is believed to be.

        Returns the object-frame points, the robot seconds it took, the sweep lines
        refused or planned another way, and the top surface left unseen. The simulator's
        noise is keyed by ``key_step``; a trip during the sweep follows the fault policy and
        the sweep starts over (a partial sweep is never used).
        """
        cell, plan = self.cell, self.inputs.plan
        spec = self.inputs.cell
        footprint = line_footprint_mm(cell.tcp_to_scanner, spec.scanner.field_of_view_deg, spec.scanner.max_range_mm,
                                      plan.cloud.sweep_height_mm, shapes_from_cell(spec.tool),
                                      spec.tool.tip_radius_mm, spec.scanner.samples_per_profile)
        settings = SweepSettings(plan.cloud.sweep_spacing_mm, plan.cloud.sweep_height_mm, footprint,
                                 max_tilt_deg=plan.sampling.max_tilt_deg, max_points=plan.cloud.max_points,
                                 seed=self.seed)
        # Counted from the journal, not from zero in each process: a fault that paused a
        # sweep must not be met again by the resumed one.
        attempt = self.faults.sweep_faults()
        # A partial sweep is never used, so a pause need not wait for the sweep's end: the
        # executor's per-tick operator check answers a pause as well as a stop here.
        should_stop = self.executor.should_stop
        self.executor.should_stop = lambda: self.flags.pause_requested
        try:
            with deferred_interrupts():
                self.machine.fire("sweep")
                while True:
                    cell.begin_step((self.seed, key_step, attempt))
                    try:
                        return acquire_cloud(self.executor, self.world.object_mesh, settings)
                    except (ProbeFault, DeviceError) as exc:
                        # A device call outside a guarded motion (the arm's status while planning a
                        # leg) is a fault of the sweep too: on the real cell the UR link's child
                        # died and was restarted with the arm stopped.
                        fault = exc if isinstance(exc, ProbeFault) else ProbeFault("device", str(exc))
                        self.faults.handle_sweep_fault(fault, attempt)
                        attempt += 1
                        self.machine.fire("sweep")
                    except MotionRefused as exc:     # every line refused: it would be refused again
                        raise SessionAborted(f"the object cannot be swept: {exc}") from None
        finally:
            self.executor.should_stop = should_stop

    def _reregister(self) -> None:
        """The object moved: sweep it again, register the mesh to the new cloud, plan from there.

        Targets live in the object frame, so once the placement is updated every planned
        step maps onto the same material again. A poor fit pauses the session: a person
        has to look at a cell where something moved.
        """

        j, cell, plan = self.journal, self.cell, self.inputs.plan
        mesh = self.world.object_mesh
        before = cell.base_to_object
        n_before = len(j.events(kind="object_registered"))
        # Keyed below the cloud sweep's key (every planned step id lies far below both),
        # so a resumed session re-draws the same simulator noise.
        swept = self.sweep_object(SWEEP_STEP_KEY - 1 - n_before)
        pts_obj, robot_s = swept.points_mm, swept.robot_s
        j.add_robot_time("sweep", robot_s)
        self.machine.fire("plan")           # from here the session may also pause
        cloud_base, _ = remove_table_below(before.apply(pts_obj), seed=self.seed,
                                           link_mm=FOOT_LINK_SPACINGS * plan.cloud.sweep_spacing_mm)
        try:
            after, rms = reregister(mesh, cloud_base, before, seed=self.seed)
        except ValueError as exc:
            raise SessionPaused(f"the object moved and could not be registered again: {exc}") from exc
        change = after.position_mm - before.position_mm
        record = {"base_to_object": after.to_list(), "previous": before.to_list(), "rms_mm": round(rms, 3),
                  "shift_mm": np.round(change, 2).tolist(),
                  "robot_s": round(float(robot_s), 3)}
        limit_mm = float(plan.probing.object_moved_mm or 0.0)
        if abs(change[2]) > 2.0 or np.linalg.norm(change[:2]) < 0.5 * limit_mm:
            # An object resting on the table slides; it does not rise or sink. And if the
            # sweep finds it where it was, the probing pose's scans disagree with the
            # sweep's: the scanner's mount (or the tip) is not where the cell file says.
            self._log("registration_rejected", **record)
            raise SessionPaused(f"the probing scans and a fresh sweep disagree about where the object is (the "
                                f"sweep moves it by {np.round(change, 1).tolist()} mm): check the scanner and "
                                f"tip calibration (elastoprobe calibrate scanner|tcp), then resume")
        cell.base_to_object = after
        self.executor.validator = None               # type: ignore[assignment]  # one scene in memory, not two
        self.executor.validator = build_validator(self.inputs, cell, mesh)
        release_freed_memory()
        self._log("object_registered", **record)     # journal event too: resume starts from it

    def run_steps(self, phase: str, round_: int, targets: dict[int, ProbeTarget]) -> None:
        """Run every pending step of a phase round, contact by contact, with the fault policy."""
        j = self.journal
        self.progress.phase = f"{phase}[{round_}]"
        with deferred_interrupts():     # a request is answered between contacts, never inside one
            while True:
                self._check_operator()
                self._check_budget()
                self._check_disk()
                pending = j.pending_steps(phase=phase, round=round_)
                if not pending:
                    break
                group = self._contact_group(pending)
                target = targets[group[0].plan.target_index]
                self._run_contact(target, group, targets)
                self.memory.contact_done()
        self._update_progress()

    def _contact_group(self, pending: list[StepRecord]) -> list[StepRecord]:
        """Every step of the first pending contact (same phase round, target and angle), by force.

        A contact interrupted half-way is pressed again from its first level, because
        the force history matters (foam creeps, cardboard dents); levels already done
        are measured but not stored again.
        """
        first = pending[0]
        same = self.journal.steps(phase=first.phase, round=first.round)
        group = [r for r in same if r.plan.target_index == first.plan.target_index
                 and abs(r.plan.angle_deg - first.plan.angle_deg) < 1e-9 and r.status != "skipped"]
        return sorted(group, key=lambda r: r.plan.force_n)

    def _run_contact(self, target: ProbeTarget, group: list[StepRecord], targets: dict[int, ProbeTarget]) -> None:

        j = self.journal
        cell = self.cell
        first = group[0].plan
        # Every fault the contact met counts (a later level's fault too): the retry must
        # draw a new key, or it meets the same scheduled fault again.
        retry = sum(self.faults.retry_index(r.step_id) for r in group)
        done_before = {r.step_id for r in group if r.status == "done"}
        self.progress.target = target.index
        t_start = cell.clock.now_s()
        step_time = 0.0

        # Simulator noise (and injected faults) are keyed at the standoff, not before the
        # travel: how long the travel took depends on where the arm came from, which a
        # resumed session does not share with an uninterrupted one. The first level
        # continues under the contact's key (re-keying it would schedule its faults twice).
        def at_standoff() -> None:
            # From here the machine's transitions (and a fault's) belong to the step in flight.
            self._current_step = first.step_id
            cell.begin_step((self.seed, first.step_id, retry))

        def before_level(level: ForceLevel) -> None:
            self._current_step = level.step_id
            if level.step_id != first.step_id:
                cell.begin_step((self.seed, level.step_id, retry))

        def on_done(data: StepData) -> None:
            nonlocal step_time
            if data.step_id in done_before:
                self._log("step_repressed", step=data.step_id)
                return
            attempt = j.begin_step(data.step_id)
            measured = measure_step_data(self.inputs, cell, target, data)
            result = StepResult.from_step_data(data, measured.depth_mm, plan_grid(self.inputs).x_mm,
                                               summary=measured.facts())
            play_disk_error(cell, j, data.step_id, retry, self._log)
            j.commit_step(data.step_id, attempt, result)
            step_time += data.robot_time_s
            self.progress.steps_done += 1
            self._log("step_done", step=data.step_id, force_n=result.summary["force_measured_n"],
                      angle_deg=data.angle_deg, target=target.index)
            self._update_progress()

        levels = [ForceLevel(r.step_id, r.plan.force_n) for r in group]
        try:
            self.executor.probe(target, first.angle_deg, levels, on_done, before_level, at_standoff)
        except MotionRefused as exc:
            self.faults.handle_contact_fault(ProbeFault("motion_refused", str(exc)), group)
        except ProbeFault as fault:
            self.faults.handle_contact_fault(fault, group)
        except DeviceError as exc:
            # A device call outside a guarded motion (e.g. the arm's status while planning
            # the travel) failed: on the real cell the UR link's child died and was
            # restarted with the arm stopped. A fault of the contact, handled by policy,
            # not an internal error that ends the night.
            self.faults.handle_contact_fault(ProbeFault("device", str(exc)), group)
        finally:
            self._current_step = None
            overhead = cell.clock.now_s() - t_start - step_time
            if overhead > 0:
                j.add_robot_time("travel_and_contact", overhead)
            self.progress.robot_s = j.robot_time_s()["total"]

    def _check_operator(self) -> None:
        if self.flags.pause_requested:
            raise operator_pause(self.flags)
        finish_by = self.inputs.plan.finish_by
        if finish_by is not None and _dt.datetime.now(_dt.timezone.utc) >= finish_by:
            raise SessionPaused(f"finish_by {finish_by.isoformat()} reached", kind="finish_by")

    def _check_disk(self) -> None:
        """Pause before the disk fills (a step of raw scans is a few hundred kB)."""

        status = DiskWatch(self.dir).check(next_write_bytes=2_000_000)
        if status.level == "pause":
            raise SessionPaused(f"disk nearly full: {status.message}")
        if status.level == "warn" and not self._disk_warned:
            self._disk_warned = True
            self._log("disk_low", message=status.message)

    def _check_budget(self) -> None:
        budget = self.inputs.plan.budget
        counts = self.journal.status_counts()
        if counts.get("done", 0) >= budget.max_steps:
            raise BudgetSpent(f"step budget of {budget.max_steps} reached")
        if self.journal.robot_time_s()["total"] / 3600.0 >= budget.max_robot_hours:
            raise BudgetSpent(f"robot-time budget of {budget.max_robot_hours} h reached")

    def _update_progress(self) -> None:
        self.progress.state = self.machine.state
        self.on_progress(self.progress)

    def _notifier(self) -> object:

        spec = self.inputs.plan.notify or self.inputs.cell.notify
        return Notifier(spec, log=self.journal.log_event)

    def _notify(self, event: str, message: str) -> None:
        """Run the operator's notify command (never raises, bounded in time)."""
        counts = self.journal.status_counts()
        self._notifier().notify(event, self.dir, plan=self.inputs.plan.name,   # type: ignore[attr-defined]
                                counts=counts, message=message,
                                t_robot_s=self.cell.clock.now_s())

    def _epilogue(self, event: str, message: str) -> None:
        """The report with the final status, then the notification. Best effort: the
        session's outcome is already journaled."""
        try:
            with self.flags.interruptible():       # a second request skips it: `elastoprobe report` redoes it
                write_report(self.dir)
        except (Exception, OperatorInterrupt) as exc:   # a report problem must not change the exit code
            self.log.write("report_failed", error=f"{type(exc).__name__}: {exc}")
        self._notify(event, message)
