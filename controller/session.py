"""One probing session: lock, journal, cell, registration, then the plan (docs/design.md §2, §5, §6).

The session sets a run up: the cell lock, the journal (created, or opened and checked
against the plan and cell on resume), the cell, the devices' identities, what a
resumed session restores (the object's dents, its registration). It then hands the
plan (:func:`.phases.run_all`, a generator of messages) to the :class:`.engine.Engine`,
which owns the state machine, the contact loop, the fault policy and how the run ends.

Each phase either is already committed in the journal (a resumed session reads its
outputs back: same cloud, same targets, same regions) or is computed now and
committed in ONE transaction together with the steps it plans; each force step is
committed in one transaction. A kill -9 at any moment loses at most the step in
flight; ``resume`` re-runs only what is not done.
"""
from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import phases
from .cellfactory import build_cell, load_object_model
from .core.atomic import json_default
from .core.config import SessionInputs
from .core.devices import Cell
from .core.errors import DiskError
from .core.geometry import Pose
from .engine import EXIT_DONE, EXIT_FAULT, EXIT_PAUSED, LEARN_STEP_KEY, Engine, InternalError, Progress
from .journal import Journal, SessionMeta
from .locking import CellLock
from .messages import SessionPaused
from .provenance import calibration_entry, collect_provenance
from .signals import OperatorFlags

# What callers (the CLI, tests, benches) import from here.
__all__ = ["EXIT_DONE", "EXIT_FAULT", "EXIT_PAUSED", "LEARN_STEP_KEY", "InternalError", "JsonlLog", "Progress",
           "Session", "SessionPaused"]


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
        self.on_progress = on_progress or (lambda p: None)
        self.journal: Journal | None = None
        self.cell: Cell | None = None
        self.log: JsonlLog | None = None
        self.engine: Engine | None = None

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
            self.engine = Engine(self.inputs, self.dir, self.seed, self.journal, self.cell, built, self.flags,
                                 self.log, self._log, self.progress, self.on_progress)
            ctx = phases.PhaseContext(journal=self.journal, inputs=self.inputs, cell=self.cell, seed=self.seed,
                                      session_dir=self.dir, executor=self.engine.executor, log=self._log)
            return self.engine.run(phases.run_all(ctx), resume)
        finally:
            if self.cell is not None:
                self.cell.close()
            if self.journal is not None:
                if self.engine is not None and self.engine.journal_damaged:
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




    def _record_identities(self) -> None:
        assert self.journal is not None and self.cell is not None
        ids = {}
        for name in ("arm", "ft", "scanner"):
            ident = getattr(self.cell, name).identity()
            ids[name] = {"model": ident.model, "serial": ident.serial, "firmware": ident.firmware, **ident.extra}
        self.journal.set_provenance("devices", ids)

    def _log(self, event: str, **record: Any) -> None:
        if self.log is not None:
            self.log.write(event, **record)
        if self.journal is not None:
            t = self.cell.clock.now_s() if self.cell is not None else None
            self.journal.log_event(event, record, t_robot_s=t)


