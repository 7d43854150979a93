"""The cell registry: the one place the controller builds a cell from its YAML (docs/design.md §1).

The controller reaches the simulator (``sim``) and the real drivers only through here, by
cell kind; both backends are imported when a cell is built, so the CLI starts fast. A dry
run of a real cell keeps that cell's limits, workspace, tool geometry and object placement,
with simulated devices behind them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .core.calfile import check_calibration
from .core.config import CellSpec, SessionInputs
from .core.devices import Cell
from .core.errors import InputError
from .core.meshcheck import bounds_problem, mesh_findings, read_mesh
from .core.meshes import sphere_on_table


@dataclass
class ObjectModel:
    """The object a session works on, loaded and checked once (``check`` and ``run`` alike).

    ``mesh``: the nominal surface (object frame, mm) for planning and collision checks;
    ``simulated``: the simulator's object when the file describes one (objects/*.yaml),
    else None; ``warnings``: what the user should know (holes, non-manifold edges)."""

    mesh: Any
    simulated: Any = None
    warnings: list[str] = field(default_factory=list)


def load_object_model(inputs: SessionInputs) -> ObjectModel:
    """Load the plan's object as the session will, and check it against the cell.

    Every problem is an InputError at the file and line that brought it in: a bad object
    file or mesh (sim/objects.py, controller/core/meshcheck.py), an object that does not fit
    the cell's workspace, or simulated physics that is not valid at the plan's largest force.
    """
    path = inputs.object_file()
    where = (inputs.plan_doc, ("simulated_object",)) if inputs.plan.simulated_object and inputs.cell.kind != "ur" \
        else (inputs.cell_doc, ("object", "file"))
    model = read_object_model(path, where[0], where[1])
    problem = placement_problem(model.mesh.vertices, inputs.cell)
    if problem is not None:
        raise where[0].error(where[1], f"{path}: {problem}")
    if model.simulated is not None and inputs.cell.kind != "ur":    # simulated and loopback cells
        check_physics(inputs, model.simulated)
    return model


def read_object_model(path: Path, doc: Any, keys: tuple[str, ...]) -> ObjectModel:
    """An object file as it is: a simulated object (objects/*.yaml, through the simulator's
    loader) or a mesh, checked; a bad one is an InputError at ``keys`` of ``doc`` (the YAML
    that named it)."""
    if path.suffix.lower() in (".yaml", ".yml"):
        from elastoprobe.sim.objects import load_object

        sim_object = load_object(path)
        return ObjectModel(mesh=sim_object.mesh, simulated=sim_object, warnings=list(sim_object.load_warnings))
    try:
        mesh = read_mesh(path)
    except ValueError as exc:
        raise doc.error(keys, f"{path}: {exc}") from None
    findings = mesh_findings(mesh)
    if findings.errors:
        raise doc.error(keys, f"{path}: " + "; ".join(findings.errors))
    return ObjectModel(mesh=mesh, warnings=[f"{path}: {w}" for w in findings.warnings])


def placement_problem(vertices_mm: np.ndarray, cell: CellSpec) -> str | None:
    """Why an object whose mesh has ``vertices_mm`` (object frame, mm), set down where ``cell``
    places it, cannot be probed there: outside the workspace, into a keep-out box, or smaller
    than the probe's tip. None: it fits."""
    limits = cell.limits
    vertices_base = cell.object.base_to_object.pose().apply(vertices_mm)
    problem = bounds_problem(vertices_base, limits.workspace.min_mm, limits.workspace.max_mm)
    if problem is not None:
        return problem + " (check the mesh's scale_mm_per_unit and the cell's object placement)"
    for box in limits.keep_out:
        inside = np.all((vertices_base >= box.min_mm) & (vertices_base <= box.max_mm), axis=1)
        if inside.any():
            return (f"the object reaches into keep-out box {box.name!r} ({int(inside.sum())} mesh vertices "
                    f"inside; check the cell's object placement)")
    size_mm = float(np.ptp(vertices_base, axis=0).max())
    tip_mm = 2.0 * cell.tool.tip_radius_mm
    if size_mm < tip_mm:
        return (f"the object is {size_mm:.3g} mm across, smaller than the probe's tip ({tip_mm:g} mm): "
                f"nothing on it can be probed (a mesh in metres needs scale_mm_per_unit: 1000)")
    return None


def check_physics(inputs: SessionInputs, sim_object: Any) -> None:
    """The simulated object's contact models must be valid at the plan's largest force."""
    plan = inputs.plan
    problems = sim_object.validity_report(max(max(plan.phases.survey.forces_n), max(plan.phases.characterize.forces_n)),
                                          inputs.cell.tool.tip_radius_mm)
    if problems:
        raise InputError("the simulated object's physics is not valid at this plan's largest force: "
                         + "; ".join(problems), path=str(inputs.plan_path))


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


def build_cell(inputs: SessionInputs, seed: int, dry_run: bool = False,
               model: ObjectModel | None = None) -> BuiltCell:
    """Build the cell a session runs on (``model``: the object loaded by :func:`load_object_model`,
    loaded here when not given)."""
    kind = inputs.cell.kind
    model = model or load_object_model(inputs)
    if kind == "simulated" or dry_run:
        return _simulated(inputs, seed, model)
    # The real drivers: ur_rtde in a supervised child, the Net F/T stream and the
    # check-and-stop path in the hardware process, the serial scanner. A loopback cell
    # first starts the simulated servers that speak those protocols.
    from .drivers.real_cell import build_real_cell

    if kind != "loopback":
        return BuiltCell(cell=build_real_cell(inputs.cell, inputs.limits), object_mesh=model.mesh)
    from elastoprobe.sim.servers.loopback import LoopbackServers

    servers = LoopbackServers(inputs.cell_path, inputs.object_file(), seed).start()
    try:
        real = build_real_cell(inputs.cell, inputs.limits, addresses=servers.addresses(),
                               ground_truth=ground_truth_for(inputs, seed, model), servers=servers)
    except BaseException:
        servers.stop()
        raise
    return BuiltCell(cell=real, object_mesh=model.mesh)


def _simulated(inputs: SessionInputs, seed: int, model: ObjectModel) -> BuiltCell:
    """The in-process simulated cell around ``model``, the object already loaded (never again:
    a mesh object's file is read once per run)."""
    from elastoprobe.sim.cell import SimCell, params_from_cell

    if model.simulated is None:
        raise InputError("a dry run needs a simulated object (an objects/*.yaml with materials): set the plan's "
                         "simulated_object", path=str(inputs.plan_path))
    # The world is built from the cell FILE (its miscalibration, drawn from the cell's own
    # seed, included); the controller's side from ``inputs.cell``, the file corrected by
    # its calibration file (config.load_session_inputs).
    if inputs.cell.kind == "ur":              # a dry run of a real cell: its physics was not checked yet
        check_physics(inputs, model.simulated)
    cell_file = inputs.cell_file if inputs.cell_file is not None else inputs.cell
    cell = SimCell(params_from_cell(cell_file, model.simulated, seed=seed, believed=inputs.cell))
    return BuiltCell(cell=cell, object_mesh=cell.world.obj.mesh, warnings=calibration_warnings(inputs))


def calibration_warnings(inputs: SessionInputs) -> list[str]:
    """Why the controller's believed geometry may be off (empty when the calibration is
    current, or when a simulated cell is calibrated by construction): found once, when the
    inputs were loaded (config.load_session_inputs)."""
    return list(inputs.calibration_problems)


def ground_truth_for(inputs: SessionInputs, seed: int, model: ObjectModel | None = None) -> Any:
    """The simulator's ground truth of a simulated session's object (object frame); ``model``:
    the object already loaded, if it was."""
    if inputs.cell.kind == "ur" and inputs.object_file().suffix.lower() not in (".yaml", ".yml"):
        raise InputError("ground truth exists only for simulated objects", path=str(inputs.cell_path))
    from elastoprobe.sim.cell import SimGroundTruth
    from elastoprobe.sim.objects import load_object

    sim_object = model.simulated if model is not None and model.simulated is not None \
        else load_object(inputs.object_file())
    return SimGroundTruth(sim_object, inputs.cell.tool.tip_radius_mm)


def check_real_cell_ready(inputs: SessionInputs, allow_stale_calibration: bool = False) -> None:
    """A real cell refuses to run without a current calibration (every section present, none
    older than the cell allows), unless the operator explicitly overrides it."""
    problems = check_calibration(inputs.cell, inputs.cell_path)
    if problems and not allow_stale_calibration:
        raise InputError("calibration is not current: " + "; ".join(problems)
                         + " (run elastoprobe calibrate ..., or pass --allow-stale-calibration)",
                         path=str(inputs.cell_path))


def build_calibration_cell(cell_spec: Any, cell_doc: Any, cell_path: str | Path, seed: int,
                           reference_sphere_radius_mm: float | None) -> BuiltCell:
    """The cell a calibration routine runs on, built by kind as a session's is, and what is
    on its table (object frame): the rigid reference sphere of ``reference_sphere_radius_mm``
    in the object's place (the ft, tcp and scanner routines), or the cell's own object (None).

    ``cell_spec`` is the cell FILE (calibration measures against its nominal frames), within
    the cell's own safety limits. A simulated cell puts the sphere into its world; a loopback
    cell starts its served world with the sphere in it; on a ``ur`` cell the operator has set
    the sphere down. The last two run the same real drivers (``drivers/real_cell.py``)."""
    kind = cell_spec.kind
    obj_path = Path(cell_path).parent / cell_spec.object.file
    if kind == "simulated":
        from elastoprobe.sim.cell import SimCell, params_from_cell
        from elastoprobe.sim.objects import reference_sphere

        params = params_from_cell(cell_spec, obj_path, seed=seed)
        if reference_sphere_radius_mm is not None:
            params.object = reference_sphere(reference_sphere_radius_mm)
        sim = SimCell(params)
        return BuiltCell(cell=sim, object_mesh=sim.world.obj.mesh)
    if reference_sphere_radius_mm is not None:
        mesh = sphere_on_table(reference_sphere_radius_mm)
    else:
        mesh = read_object_model(obj_path, cell_doc, ("object", "file")).mesh
    from .drivers.real_cell import build_real_cell

    limits = cell_spec.limits.safety()
    if kind != "loopback":
        return BuiltCell(cell=build_real_cell(cell_spec, limits), object_mesh=mesh)
    from elastoprobe.sim.servers.loopback import LoopbackServers

    servers = LoopbackServers(Path(cell_path), None, seed,
                              reference_sphere_radius_mm=reference_sphere_radius_mm).start()
    try:
        real = build_real_cell(cell_spec, limits, addresses=servers.addresses(), servers=servers)
    except BaseException:
        servers.stop()
        raise
    return BuiltCell(cell=real, object_mesh=mesh)
