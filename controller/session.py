"""One probing session: lock, journal, phases, fault policy, pause and resume (docs/design.md §2, §5, §6).

The session is a sequence of phases. Each phase either is already committed in
the journal (a resumed session reads its outputs back: same cloud, same targets,
same regions) or is computed now and committed in ONE transaction together with
the steps it plans. Steps run through the probe executor and the state machine;
each force step is committed in one transaction. A kill -9 at any moment loses
at most the step in flight; ``resume`` re-runs only what is not done.
"""
from __future__ import annotations

import datetime as _dt
import json
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import phases
from .acquire import SweepResult, SweepSettings, acquire_cloud, line_footprint_mm
from .cellfactory import build_cell, load_object_model
from .core.atomic import json_default
from .core.collision import shapes_from_cell
from .core.config import SessionInputs, effective_motion_limits
from .core.devices import Cell, Trip, same_trip
from .core.errors import BudgetSpent, DeviceError, DiskError, ElastoprobeError, MotionRefused, SessionAborted
from .core.geometry import Pose
from .core.safety import stream_health_guard
from .core.validation import build_validator
from .journal import Journal, JournalCorruption, JournalError, SessionMeta, StepRecord, StepResult
from .locking import CellLock
from .machine import SessionMachine
from .memory import ContactCounter, release_freed_memory
from .notify import DiskWatch, Notifier
from .phases import FOOT_LINK_SPACINGS, SWEEP_STEP_KEY, remove_table_below
from .placement import PlacementMonitor, reregister
from .probe import ForceLevel, ProbeExecutor, ProbeFault, ProbeSettings, ProbeTarget, StepData
from .provenance import calibration_entry, collect_provenance
from .report import write_report
from .signals import OperatorFlags, OperatorInterrupt, deferred_interrupts
from .testing import play_disk_error

EXIT_DONE, EXIT_FAULT, EXIT_PAUSED = 0, 1, 3


class InternalError(ElastoprobeError):
    """An unexpected error inside the controller; the arm was stopped and parked (exit 1)."""


class SessionPaused(Exception):
    """The session stopped cleanly with work left (exit 3)."""


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


class JsonlLog:
    """DIR/log.jsonl: one JSON object per line, flushed per record (readable while running).

    A copy for people and tools; the journal is the record. A full disk must not turn the
    session's own handling of that disk error into a traceback, so a line that cannot be
    written is dropped (and counted)."""

    def __init__(self, path: Path) -> None:
        try:
            self._f = open(path, "a", encoding="utf-8")
        except OSError as exc:
            raise DiskError.from_os_error(exc, str(path)) from None
        self.dropped = 0

    def write(self, event: str, **record: Any) -> None:
        rec = {"t_wall_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
               "event": event, **record}
        try:
            self._f.write(json.dumps(rec, default=_json_default) + "\n")
            self._f.flush()
        except OSError:
            self.dropped += 1

    def close(self) -> None:
        try:
            self._f.close()
        except OSError:
            pass


def _json_default(o: Any) -> Any:
    """Log lines never fail on a value: what JSON cannot hold is written as text."""
    try:
        return json_default(o)
    except TypeError:
        return str(o)


# Faults that are, or may be, a lost connection to the robot (a command's DeviceError):
# their recovery waits for it to come back; for any other fault, the connection lost
# while recovering is a second fault.
CONNECTION_FAULT_KINDS = frozenset({"connection", "device"})
# Faults met during a recovery that always pause, whatever their kind's policy: the operator's
# (an e-stop, a stop at the robot) and a journal that cannot be written (docs/design.md).
NEVER_NESTED = frozenset({"emergency_stop", "operator_stop", "disk_error"})


class Session:
    """Runs (or resumes) one session in ``session_dir``."""

    def __init__(self, inputs: SessionInputs, session_dir: Path, seed: int, dry_run: bool = False,
                 on_progress: Callable[[Progress], None] | None = None, object_model: Any = None) -> None:
        self.inputs = inputs
        self.object_model = object_model          # cellfactory.ObjectModel; loaded in run() when None
        self.dir = Path(session_dir)
        self.seed = int(seed)
        self.dry_run = dry_run
        self.flags = OperatorFlags()
        self.progress = Progress()
        self._memory = ContactCounter()      # resident memory stays what is live, all night
        self.on_progress = on_progress or (lambda p: None)
        self.journal: Journal | None = None
        self._journal_damaged = False
        self.cell: Cell | None = None
        self.log: JsonlLog | None = None
        self._current_step: int | None = None

    # ------------------------------------------------------------------ entry points
    def run(self, resume: bool = False) -> int:

        self.flags.install()
        # The cell lock guards real hardware; an in-process simulated cell (or a dry run)
        # is private to this controller, so parallel dry runs need no lock.
        real = self.inputs.cell.kind != "simulated" and not self.dry_run
        cell_lock = CellLock(self.inputs.cell.name) if real else None
        try:
            if cell_lock is not None:
                cell_lock.acquire()
            # Every input problem (object, mesh) is found before anything is written.
            model = self.object_model if self.object_model is not None else load_object_model(self.inputs)
            self.journal = self._open_journal(resume)
            self.log = JsonlLog(self.dir / "log.jsonl")
            self.log.write("session_start", resume=resume, seed=self.seed, plan=self.inputs.plan.name)
            built = build_cell(self.inputs, self.seed, dry_run=self.dry_run, model=model)
            self.cell = built.cell
            self.world = built
            for warning in built.warnings:
                self._log("calibration_warning", message=warning)
            for warning in model.warnings:
                self._log("object_warning", message=warning)
            self._record_identities()
            if resume:
                self._note_calibration_change()
            if resume:
                self._restore_object_history()
                self._restore_registration()
            code = self._run_phases(resume)
            return code
        finally:
            if self.cell is not None:
                self.cell.close()
            if self.journal is not None:
                if self._journal_damaged:
                    self.journal.abandon()       # nothing more is written to a damaged journal
                else:
                    self.journal.close()
            if self.log is not None:
                self.log.close()
            if cell_lock is not None:
                cell_lock.release()
            self.flags.restore()

    # ------------------------------------------------------------------ journal
    def _open_journal(self, resume: bool) -> Journal:

        plan_text = self.inputs.plan_path.read_bytes()
        cell_text = self.inputs.cell_path.read_bytes()
        if resume:
            journal = Journal.open(self.dir)
            journal.verify_inputs(plan_text, cell_text)
            return journal
        prov = collect_provenance(self.inputs.plan_path, self.inputs.cell_path, self._calibration_path())
        prov["seed"] = self.seed
        prov["dry_run"] = self.dry_run
        prov["object_file"] = str(self.inputs.object_file())
        return Journal.create(self.dir, SessionMeta(plan_name=self.inputs.plan.name, seed=self.seed,
                                                    provenance=prov))

    def _calibration_path(self) -> Path | None:
        c = self.inputs.cell.calibration_file
        return self.inputs.resolve(self.inputs.cell_path, c) if c else None

    def _restore_object_history(self) -> None:
        """A simulated object remembers permanent dents: rebuild them from the done steps."""
        assert self.journal is not None
        peak: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
        for rec in self.journal.steps(statuses=["done"]):
            p = rec.plan
            f = max(peak.get(p.target_index, (None, None, 0.0))[2], float(p.force_n))
            peak[p.target_index] = (np.asarray(p.point_mm), np.asarray(p.normal), f)
        self.world.restore_history(list(peak.values()))

    def _note_calibration_change(self) -> None:
        """A calibration redone between run and resume (e.g. after a pause that asked for it)
        changes the believed geometry from here on: allowed, but on the record."""

        assert self.journal is not None
        before = (self.journal.provenance().get("calibration") or {}).get("sha256")
        now = calibration_entry(self.inputs.cell_path, self._calibration_path())
        after = (now or {}).get("sha256")
        if before != after:
            self._log("calibration_changed", sha256_before=before, sha256_after=after,
                      applied_sections=(now or {}).get("applied_sections"))

    def _restore_registration(self) -> None:
        """Where the object was last registered (after it moved): the journal's latest word."""
        assert self.journal is not None and self.cell is not None
        events = self.journal.events(kind="object_registered")
        if events:
            pose = Pose.from_list(events[-1]["record"]["base_to_object"])
            self.cell.base_to_object = pose
            self._log("registration_restored", base_to_object=events[-1]["record"]["base_to_object"])

    def _reregister(self) -> None:
        """The object moved: sweep it again, register the mesh to the new cloud, plan from there.

        Targets live in the object frame, so once the placement is updated every planned
        step maps onto the same material again. A poor fit pauses the session: a person
        has to look at a cell where something moved.
        """

        assert self.journal is not None and self.cell is not None
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

    def sweep_object(self, key_step: int) -> SweepResult:
        """Sweep the scanner over the object where it is believed to be.

        Returns the object-frame points, the robot seconds it took, the sweep lines
        refused or planned another way, and the top surface left unseen. The simulator's
        noise is keyed by ``key_step``; a trip during the sweep follows the fault policy and
        the sweep starts over (a partial sweep is never used).
        """
        assert self.cell is not None
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
        attempt = self._sweep_faults()
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
                        self.handle_sweep_fault(fault, attempt)
                        attempt += 1
                        self.machine.fire("sweep")
                    except MotionRefused as exc:     # every line refused: it would be refused again
                        raise SessionAborted(f"the object cannot be swept: {exc}") from None
        finally:
            self.executor.should_stop = should_stop

    def _key_learning(self) -> None:
        """Key the simulator for a learning phase, as for a sweep or a step: the cell lives on
        while the controller learns (a stop or a lost connection then is met at the next
        motion). Keyed by the models rounds already committed, so a resumed session that
        learns the same round again uses the same key."""
        assert self.journal is not None and self.cell is not None
        rounds = sum(1 for p in self.journal.phases() if p["name"] == "models")
        self.cell.begin_step((self.seed, LEARN_STEP_KEY - rounds, 0))

    def _sweep_faults(self) -> int:
        assert self.journal is not None
        return sum(1 for f in self.journal.faults(with_raw=False)
                   if f.step_id is None and f.message.startswith(SWEEP_FAULT_PREFIX))

    def _record_identities(self) -> None:
        assert self.journal is not None and self.cell is not None
        ids = {}
        for name in ("arm", "ft", "scanner"):
            ident = getattr(self.cell, name).identity()
            ids[name] = {"model": ident.model, "serial": ident.serial, "firmware": ident.firmware, **ident.extra}
        self.journal.set_provenance("devices", ids)

    # ------------------------------------------------------------------ phases
    def _run_phases(self, resume: bool) -> int:

        assert self.journal is not None and self.cell is not None
        j = self.journal
        journal_transition = j.transition_callback(self.cell.clock.now_s, lambda: self._current_step)

        def on_transition(source: str, dest: str, trigger: str) -> None:
            journal_transition(source, dest, trigger)
            if dest == "learning":
                self._key_learning()

        machine = SessionMachine(on_transition)
        self.machine = machine
        self.executor = self._make_executor(machine)
        ctx = phases.PhaseContext(session=self)
        try:
            machine.fire("start")
            if resume:
                self._recover_pose()
            # Computation between the contacts (planning, learning, the map and report)
            # ends at once on a pause or stop; contacts and sweeps end at their own
            # checkpoints (signals.py).
            with self.flags.interruptible():
                phases.run_all(ctx)
            machine.fire("finish")
            j.set_status("done")
            self._log("session_done")
            self._epilogue("finish", "session done")
            return EXIT_DONE
        except (SessionPaused, OperatorInterrupt) as exc:
            self.flags.acknowledge()
            reason = self.flags.reason if isinstance(exc, OperatorInterrupt) else str(exc)
            if self.flags.stop_now:
                self._stop_arm()
            self._park()
            if machine.can("pause"):
                machine.fire("pause")
            j.set_status("paused", reason)
            self._log("session_paused", reason=reason)
            self._epilogue("finish_by" if "finish_by" in reason else "pause", reason)
            if reason.startswith("pause requested") and self.flags.stop_now:
                # The operator's second request came while the pause was being saved: a stop.
                j.set_status("paused", self.flags.reason)
                self._log("session_paused", reason=self.flags.reason)
            return EXIT_PAUSED
        except JournalCorruption as exc:
            # Stored data is damaged: stop and park, and write nothing more to the journal
            # (its status stays what it was); the CLI says what is damaged and how to salvage.
            self._journal_damaged = True
            self._stop_arm()
            self._park(journal=False)
            if self.log is not None:
                self.log.write("session_stopped", reason=f"journal damaged: {exc}")
            raise
        except SessionAborted as exc:
            self._park()
            if machine.can("abort"):
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
            self._stop_arm()
            self._park(journal=False)
            reason = str(exc) if isinstance(exc, DiskError) else f"journal write failed: {type(exc).__name__}: {exc}"
            if self.log is not None:
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
            import traceback

            self._stop_arm()
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
        assert self.cell is not None
        validator = build_validator(inputs, self.cell, self.world.object_mesh)
        top_z = float(self.cell.base_to_object.apply(self.world.object_mesh.vertices)[:, 2].max())
        placement = None
        if pr.object_moved_mm is not None:
            placement = PlacementMonitor(self.world.object_mesh, pr.object_moved_mm, seed=self.seed)
        executor = ProbeExecutor(self.cell, machine, settings, validator, top_z,
                                 should_stop=lambda: self.flags.stop_now, placement=placement)
        executor.on_placement = self._on_placement
        executor.on_regulated = lambda record: self._log("force_regulated", **record)
        return executor

    def _on_placement(self, what: str, estimate: dict[str, Any]) -> None:
        """Log placement checks that come anywhere near the threshold (the rest is noise)."""
        limit = self.inputs.plan.probing.object_moved_mm
        if limit is not None and estimate["horizontal_mm"] > 0.5 * limit:
            self._log("placement_check", what=what, step=self._current_step, **estimate)

    def _recover_pose(self) -> None:
        """Resume starts by reading |F| and the pose, and unloads/retracts before anything else."""
        assert self.cell is not None
        status = self.cell.arm.status()
        block = self.cell.ft.read_block()
        force = float(np.linalg.norm(block.force_n[-1])) if len(block) else 0.0
        self._log("resume_state", force_n=force, tcp_mm=status.tcp_pose.position_mm)
        self.executor.safe_retract()

    def _park(self, journal: bool = True) -> None:
        """Retract to travel height (best effort: the arm is stopped); ``journal=False`` when
        the journal cannot take the record (damaged, or its disk failing)."""
        self.executor.acknowledged_trip = self.cell.arm.trip() if self.cell is not None else None
        try:
            self.executor.safe_retract()
        except (ProbeFault, ElastoprobeError) as exc:
            if journal:
                self._log("park_failed", message=str(exc))
            elif self.log is not None:
                self.log.write("park_failed", message=str(exc))

    # ------------------------------------------------------------------ steps
    def run_steps(self, phase: str, round_: int, targets: dict[int, ProbeTarget]) -> None:
        """Run every pending step of a phase round, contact by contact, with the fault policy."""
        assert self.journal is not None
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
                self._memory.contact_done()
        self._update_progress()

    def _contact_group(self, pending: list[StepRecord]) -> list[StepRecord]:
        """Every step of the first pending contact (same phase round, target and angle), by force.

        A contact interrupted half-way is pressed again from its first level, because
        the force history matters (foam creeps, cardboard dents); levels already done
        are measured but not stored again.
        """
        assert self.journal is not None
        first = pending[0]
        same = self.journal.steps(phase=first.phase, round=first.round)
        group = [r for r in same if r.plan.target_index == first.plan.target_index
                 and abs(r.plan.angle_deg - first.plan.angle_deg) < 1e-9 and r.status != "skipped"]
        return sorted(group, key=lambda r: r.plan.force_n)

    def _retry_index(self, step_id: int) -> int:
        """Faults recorded against a step: its retry number (kills do not count, so a
        resumed session draws the same simulator noise as an uninterrupted one)."""
        assert self.journal is not None
        return len(self.journal.faults(step_id=step_id, with_raw=False))

    def _run_contact(self, target: ProbeTarget, group: list[StepRecord], targets: dict[int, ProbeTarget]) -> None:

        assert self.journal is not None and self.cell is not None
        j = self.journal
        cell = self.cell
        first = group[0].plan
        # Every fault the contact met counts (a later level's fault too): the retry must
        # draw a new key, or it meets the same scheduled fault again.
        retry = sum(self._retry_index(r.step_id) for r in group)
        done_before = {r.step_id for r in group if r.status == "done"}
        self.progress.target = target.index
        t_start = cell.clock.now_s()
        step_time = 0.0

        # Simulator noise (and injected faults) are keyed at the standoff, not before the
        # travel: how long the travel took depends on where the arm came from, which a
        # resumed session does not share with an uninterrupted one. The first level
        # continues under the contact's key (re-keying it would schedule its faults twice).
        def at_standoff() -> None:
            cell.begin_step((self.seed, first.step_id, retry))

        def before_level(level: ForceLevel) -> None:
            if level.step_id != first.step_id:
                cell.begin_step((self.seed, level.step_id, retry))

        def on_done(data: StepData) -> None:
            nonlocal step_time
            if data.step_id in done_before:
                self._log("step_repressed", step=data.step_id)
                return
            self._current_step = data.step_id
            attempt = j.begin_step(data.step_id)
            measured = phases.measure_step_data(self, target, data)
            result = StepResult.from_step_data(data, measured.depth_mm, phases.session_grid(self).x_mm,
                                               summary=measured.facts())
            play_disk_error(cell, j, data.step_id, retry, self._log)
            j.commit_step(data.step_id, attempt, result)
            step_time += data.robot_time_s
            self._current_step = None
            self.progress.steps_done += 1
            self._log("step_done", step=data.step_id, force_n=result.summary["force_measured_n"],
                      angle_deg=data.angle_deg, target=target.index)
            self._update_progress()

        levels = [ForceLevel(r.step_id, r.plan.force_n) for r in group]
        try:
            self.executor.probe(target, first.angle_deg, levels, on_done, before_level, at_standoff)
        except MotionRefused as exc:
            self._handle_fault(ProbeFault("motion_refused", str(exc)), group)
        except ProbeFault as fault:
            self._handle_fault(fault, group)
        except DeviceError as exc:
            # A device call outside a guarded motion (e.g. the arm's status while planning
            # the travel) failed: on the real cell the UR link's child died and was
            # restarted with the arm stopped. A fault of the contact, handled by policy,
            # not an internal error that ends the night.
            self._handle_fault(ProbeFault("device", str(exc)), group)
        finally:
            overhead = cell.clock.now_s() - t_start - step_time
            if overhead > 0:
                j.add_robot_time("travel_and_contact", overhead)
            self.progress.robot_s = j.robot_time_s()["total"]

    def _stop_arm(self) -> None:
        """Stop the arm; with the link down the command cannot reach it (the robot's own
        watchdog stops it when the control link dies), which is said in the log."""
        assert self.cell is not None
        try:
            self.cell.arm.stop()
        except DeviceError as exc:
            self._log("stop_not_sent", message=str(exc))

    def _wait_stopped(self, max_s: float = 2.0) -> dict[str, Any]:
        """Let the arm come to rest after stop() (bounded), and say how it stands."""
        assert self.cell is not None
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

    def _handle_fault(self, fault: ProbeFault, group: list[StepRecord]) -> None:
        """Stop first (the device already did), journal, retract, then follow the policy."""
        assert self.journal is not None and self.cell is not None
        j = self.journal
        self._stop_arm()
        arm_state = self._wait_stopped()
        open_steps = [r for r in group if j.step(r.step_id).status not in ("done", "skipped")]
        step_id = open_steps[0].step_id if open_steps else None
        if fault.kind == "operator_stop":
            self._log("operator_stop", step=step_id, message=fault.message)
            # A request by signal or `elastoprobe pause/stop` says so; a stop at the robot
            # (its program stopped without a safety stop) says what the robot reported.
            raise SessionPaused(self.flags.reason if self.flags.pause_requested
                                else f"stopped by the operator: {fault.message}")
        policy = self.inputs.plan.fault_policy.for_kind(fault.kind)
        retries_so_far = self._retry_index(step_id) if step_id is not None else 0
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
        if self.machine.can("fault"):
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
            self._reregister()

    def _await_connection(self, max_s: float = 10.0) -> Any:
        """The arm's status once it is connected again (bounded wait), else None."""
        assert self.cell is not None
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

    def handle_sweep_fault(self, fault: ProbeFault, attempt: int) -> None:
        """A fault during the cloud sweep (no step is open): stop, journal, recover; the
        caller sweeps again while the policy allows a retry, else the session pauses."""
        assert self.journal is not None and self.cell is not None
        self._stop_arm()
        arm_state = self._wait_stopped()
        if fault.kind == "operator_stop":
            self._log("operator_stop", phase="cloud", arm=arm_state)
            raise SessionPaused(self.flags.reason + " during a sweep (resume sweeps again)")
        policy = self.inputs.plan.fault_policy.for_kind(fault.kind)
        action = policy.action
        if action in ("retry", "skip_target"):
            action = "retry" if attempt < policy.retries else "pause"
        raw = fault.trip.raw if fault.trip is not None else None
        fault_id = self.journal.record_fault(fault.kind, f"{SWEEP_FAULT_PREFIX}: {fault.message}",
                                             t_robot_s=self.cell.clock.now_s(), policy_action=action, raw=raw)
        self._log("fault", kind=fault.kind, message=fault.message, step=None, action=action,
                  fault_id=fault_id, arm=arm_state, phase="cloud")
        if self.machine.can("fault"):
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

    def _recover(self, fault: ProbeFault, step_id: int | None = None, since_generation: int | None = None,
                 root: ProbeFault | None = None) -> str | None:
        """Make the arm movable again: protective-stop recovery, re-arm, retract. Never clears an e-stop.

        None when the arm is movable again, else why not (for the pause reason: the operator
        at the cell reads it first). ``since_generation``: the link generation when the fault
        was met (ArmStatus.link_generation); a higher one afterwards is a connection lost and
        regained inside this recovery. ``root``: the fault whose recovery this one is nested
        in (docs/design.md, fault policy: one nested recovery, never two).
        """
        assert self.cell is not None
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
            self._stop_arm()
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
        assert self.cell is not None
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
        assert self.cell is not None
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
        assert self.journal is not None and self.cell is not None
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
        assert self.cell is not None
        try:
            trip = self.cell.arm.trip()
        except DeviceError as exc:
            return True, self._fault_during_recovery(fault, root, step_id, "device", str(exc), None, when, may_nest)
        if trip is None or same_trip(trip, fault.trip) or (root is not None and same_trip(trip, root.trip)):
            return False, None
        self._stop_arm()
        return True, self._fault_during_recovery(fault, root, step_id, trip.kind, trip.message, trip, when, may_nest)

    # ------------------------------------------------------------------ operator, budget, progress
    def _check_operator(self) -> None:
        if self.flags.pause_requested:
            raise SessionPaused(self.flags.reason)
        finish_by = self.inputs.plan.finish_by
        if finish_by is not None and _dt.datetime.now(_dt.timezone.utc) >= finish_by:
            raise SessionPaused(f"finish_by {finish_by.isoformat()} reached")

    def _check_disk(self) -> None:
        """Pause before the disk fills (a step of raw scans is a few hundred kB)."""

        status = DiskWatch(self.dir).check(next_write_bytes=2_000_000)
        if status.level == "pause":
            raise SessionPaused(f"disk nearly full: {status.message}")
        if status.level == "warn" and not getattr(self, "_disk_warned", False):
            self._disk_warned = True
            self._log("disk_low", message=status.message)

    def _notifier(self) -> object:

        spec = self.inputs.plan.notify or self.inputs.cell.notify
        return Notifier(spec, log=(self.journal.log_event if self.journal is not None else None))

    def _notify(self, event: str, message: str) -> None:
        """Run the operator's notify command (never raises, bounded in time)."""
        counts = self.journal.status_counts() if self.journal is not None else None
        self._notifier().notify(event, self.dir, plan=self.inputs.plan.name,   # type: ignore[attr-defined]
                                counts=counts, message=message,
                                t_robot_s=self.cell.clock.now_s() if self.cell is not None else None)

    def _epilogue(self, event: str, message: str) -> None:
        """The report with the final status, then the notification. Best effort: the
        session's outcome is already journaled."""
        try:
            with self.flags.interruptible():       # a second request skips it: `elastoprobe report` redoes it
                write_report(self.dir)
        except (Exception, OperatorInterrupt) as exc:   # a report problem must not change the exit code
            if self.log is not None:
                self.log.write("report_failed", error=f"{type(exc).__name__}: {exc}")
        self._notify(event, message)

    def _check_budget(self) -> None:
        assert self.journal is not None and self.cell is not None
        budget = self.inputs.plan.budget
        counts = self.journal.status_counts()
        if counts.get("done", 0) >= budget.max_steps:
            raise BudgetSpent(f"step budget of {budget.max_steps} reached")
        if self.journal.robot_time_s()["total"] / 3600.0 >= budget.max_robot_hours:
            raise BudgetSpent(f"robot-time budget of {budget.max_robot_hours} h reached")

    def _update_progress(self) -> None:
        if self.machine is not None:
            self.progress.state = self.machine.state
        self.on_progress(self.progress)

    def _log(self, event: str, **record: Any) -> None:
        if self.log is not None:
            self.log.write(event, **record)
        if self.journal is not None:
            t = self.cell.clock.now_s() if self.cell is not None else None
            self.journal.log_event(event, record, t_robot_s=t)


SWEEP_FAULT_PREFIX = "during a sweep of the object"
# The simulator key of a learning phase (minus the models round): below the sweep keys
# (phases.SWEEP_STEP_KEY = 2**32 - 2, re-registration sweeps just under it), far above
# every planned step id.
LEARN_STEP_KEY = 2**32 - 1002
