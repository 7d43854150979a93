"""The one place the controller builds a cell from its YAML (DESIGN §1).

``controller`` reaches ``sim`` (and later the real drivers' hardware process) only
through here, imported lazily, so the CLI starts fast and the dependency points
one way. A dry run of a real cell keeps that cell's limits, workspace, tool
geometry and object placement, with simulated devices behind them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import SessionInputs
from .devices import Cell
from .errors import InputError


@dataclass
class BuiltCell:
    """A cell and what the controller knows of the object's shape (object frame, mm)."""

    cell: Cell
    object_mesh: Any                 # trimesh.Trimesh: the nominal surface for planning and collision checks
    # Why the controller's geometry may not be the cell's (calibration missing, partial,
    # stale or unusable): for the session's log and report. Empty: nothing to say.
    warnings: list[str] = field(default_factory=list)

    def restore_history(self, presses: list[tuple[Any, Any, float]]) -> None:
        """Simulated cells rebuild object state (permanent dents) on resume; real cells have it."""
        restore = getattr(self.cell, "restore_history", None)
        if restore is not None:
            restore(presses)


def build_cell(inputs: SessionInputs, seed: int, dry_run: bool = False) -> BuiltCell:
    """Build the cell a session runs on."""
    kind = inputs.cell.kind
    if kind == "simulated" or dry_run:
        return _simulated(inputs, seed)
    # The real drivers: ur_rtde in a supervised child, the Net F/T stream and the
    # check-and-stop path in the hardware process, the serial scanner. A loopback cell
    # first starts the simulated servers that speak those protocols.
    from .drivers.real_cell import build_real_cell

    return build_real_cell(inputs, seed)


def _simulated(inputs: SessionInputs, seed: int) -> BuiltCell:
    from elastoprobe.sim.cell import SimCell, params_from_cell

    obj = inputs.object_file()
    if obj.suffix.lower() not in (".yaml", ".yml"):
        raise InputError("a dry run needs a simulated object (an objects/*.yaml with materials): set the plan's "
                         "simulated_object", path=str(inputs.plan_path))
    # The world is built from the cell FILE (its miscalibration, drawn from the cell's own
    # seed, included); the controller's side from ``inputs.cell``, the file corrected by
    # its calibration file (config.load_session_inputs).
    cell_file = inputs.cell_file if inputs.cell_file is not None else inputs.cell
    cell = SimCell(params_from_cell(cell_file, obj, seed=seed, believed=inputs.cell))
    problems = cell.validity_report(max(max(inputs.plan.phases.survey.forces_n),
                                        max(inputs.plan.phases.characterize.forces_n)))
    if problems:
        raise InputError("the simulated object's physics is not valid at this plan's largest force: "
                         + "; ".join(problems), path=str(inputs.plan_path))
    return BuiltCell(cell=cell, object_mesh=cell.world.obj.mesh, warnings=calibration_warnings(inputs))


def calibration_warnings(inputs: SessionInputs) -> list[str]:
    """Why the controller's believed geometry may be off (empty when the calibration is
    current, or when a simulated cell is calibrated by construction)."""
    from elastoprobe.calibration.calfile import believed_cell

    cell_file = inputs.cell_file if inputs.cell_file is not None else inputs.cell
    _, state = believed_cell(cell_file, inputs.cell_path)
    return list(state.problems)


def ground_truth_for(inputs: SessionInputs, seed: int) -> Any:
    """The simulator's ground truth of a simulated session's object (object frame)."""
    if inputs.cell.kind == "ur" and inputs.object_file().suffix.lower() not in (".yaml", ".yml"):
        raise InputError("ground truth exists only for simulated objects", path=str(inputs.cell_path))
    from elastoprobe.sim.cell import SimGroundTruth
    from elastoprobe.sim.objects import load_object

    return SimGroundTruth(load_object(inputs.object_file()), inputs.cell.tool.tip_radius_mm)


def object_mesh_for(object_file: Path) -> Any:
    """The nominal surface (trimesh.Trimesh, object frame, mm) of a simulated object file: what a
    plan is sized from (controller/planrule.py)."""
    from elastoprobe.sim.objects import load_object

    return load_object(object_file).mesh


def check_real_cell_ready(inputs: SessionInputs, allow_stale_calibration: bool = False) -> None:
    """A real cell refuses to run without a current calibration (every section present, none
    older than the cell allows), unless the operator explicitly overrides it."""
    from elastoprobe.calibration.calfile import check_calibration

    problems = check_calibration(inputs.cell, inputs.cell_path)
    if problems and not allow_stale_calibration:
        raise InputError("calibration is not current: " + "; ".join(problems)
                         + " (run elastoprobe calibrate ..., or pass --allow-stale-calibration)",
                         path=str(inputs.cell_path))
