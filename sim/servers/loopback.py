"""A loopback cell's served world: ``sim serve`` in a spawned child process that dies with the
controller, started by the cell registry (controller/cellfactory.py) before the real drivers
connect to it."""
from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from elastoprobe.controller.core.errors import DeviceError

from .serve import read_state, serve_child_main


class LoopbackServers:
    """``sim serve`` in a spawned child process that dies with this one (PR_SET_PDEATHSIG)."""

    def __init__(self, cell_path: Path, object_path: Path | None, seed: int, lifetime_s: float = 4 * 3600.0,
                 reference_sphere_radius_mm: float | None = None) -> None:
        """``reference_sphere_radius_mm``: serve calibration's reference sphere (mm) in the object's place."""
        self.cell_path = Path(cell_path)
        self.object_path = object_path
        self.reference_sphere_radius_mm = reference_sphere_radius_mm
        self.seed = int(seed)
        self.lifetime_s = lifetime_s
        self.run_dir = Path(tempfile.mkdtemp(prefix="elastoprobe-serve-"))
        self.proc: Any = None
        self.state: dict[str, Any] = {}

    def start(self, timeout_s: float = 60.0) -> "LoopbackServers":
        ctx = mp.get_context("spawn")
        self.proc = ctx.Process(target=serve_child_main, name="elastoprobe-sim-serve", daemon=True,
                                args=(str(self.cell_path), None if self.object_path is None else str(self.object_path),
                                      self.seed, str(self.run_dir), self.lifetime_s, os.getpid(),
                                      self.reference_sphere_radius_mm))
        self.proc.start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = read_state(self.run_dir)
            if state is not None:
                self.state = state
                return self
            if not self.proc.is_alive():
                break
            time.sleep(0.05)
        why = ""
        err = self.run_dir / "serve.error"
        if err.exists():
            why = ": " + err.read_text()
        self.stop()
        raise DeviceError(f"the loopback servers for {self.cell_path} did not start{why}")

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout_s)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(2.0)
        shutil.rmtree(self.run_dir, ignore_errors=True)

    def addresses(self) -> dict[str, Any]:
        """Where the served devices listen (the real drivers' overrides of the cell file)."""
        return {key: self.state[key] for key in ("robot_host", "ft_host", "rdt_port", "calinfo_port", "scanner_url")}
