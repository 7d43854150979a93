"""`elastoprobe sim serve`: the simulated world served over the real protocols, in real time.

One process runs, for a cell file:

- the UR emulator (RTDE 30004, script 30001-30003, dashboard 29999) on ``robot.host``
  (a 127.0.0.x), driving the simulated arm (:class:`WorldBackend`);
- the simulated ATI Net F/T (RDT over UDP on ``ft.rdt_port``, READCALINFO over TCP on
  ``ft.calinfo_port``) on ``ft.host``, streaming the world's F/T at ``ft.rate_hz``;
- the simulated line scanner at ``scanner.url``: ``socket://127.0.0.x:PORT`` serves
  serial-over-TCP there; ``pty://`` (or ``sim://``) opens a pseudo-terminal whose path
  is only known once it exists.

Where the controller finds them: a state file ``RUN_DIR/serve.json`` (written atomically
once everything listens) with ``robot_host``, ``ft_host``, ``rdt_port``, ``calinfo_port``,
``scanner_url`` (the actual pty path or socket URL), ``pid`` and ``seed``. Without a run
directory nothing is written (the cell file's fixed addresses apply).

Bounded: every server has a lifetime (``lifetime_s``); SIGINT/SIGTERM (handled in
:func:`main_serve`) or ``stop_event`` end it; every socket is closed and every thread
joined before :func:`serve` returns.
"""
from __future__ import annotations

import json
import math
import os
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from elastoprobe.controller.core.process import set_parent_death_signal

STATE_FILE = "serve.json"
DEFAULT_LIFETIME_S = 4 * 3600.0
SERVE_NICE = -10             # niceness of a loopback cell's served world (best effort)
MIN_RANGE_MM = 40.0          # the simulated scanner's near limit (ScannerSettings.min_range_mm)


@dataclass
class ServedCell:
    """The running servers of one served world (stop() closes them all)."""

    backend: Any
    emulator: Any
    netft: Any
    scanner: Any
    state: dict[str, Any]

    def stop(self) -> None:
        for server in (self.scanner, self.netft, self.emulator):
            try:
                server.stop()
            except Exception:  # noqa: BLE001 — stopping is best effort; the others still stop
                pass


def scanner_transport(url: str) -> tuple[str, str, int]:
    """("tcp", host, port) for ``socket://127.0.0.x:PORT``, else ("pty", "", 0)."""
    m = re.fullmatch(r"socket://(127\.\d+\.\d+\.\d+):(\d+)/?", url.strip())
    if m:
        return "tcp", m.group(1), int(m.group(2))
    if url.startswith("socket://"):
        raise ValueError(f"the simulated scanner serves loopback addresses only, not {url!r}")
    return "pty", "", 0


def start_servers(cell_spec: Any, cell_path: str | Path, seed: int, *, object_path: str | Path | None = None,
                  lifetime_s: float = DEFAULT_LIFETIME_S, ft_records_per_datagram: int = 1,
                  unlock_delay_s: float = 5.0, reference_sphere_radius_mm: float | None = None) -> ServedCell:
    """Build the simulated world of ``cell_spec`` and start its three servers (real time).

    ``reference_sphere_radius_mm``: calibration's rigid reference sphere (that radius, mm) on
    the table in the object's place instead of the object."""
    from elastoprobe.sim.cell import SimCell, params_from_cell
    from elastoprobe.sim.objects import reference_sphere

    from .netft_server import NetFTServer
    from .scanner_serial import ScannerPtyServer
    from .ur_emulator import UREmulator
    from .world_backend import WorldBackend, untrippable_params

    cell_path = Path(cell_path)
    obj = Path(object_path) if object_path is not None else cell_path.parent / cell_spec.object.file
    if not cell_spec.robot.host.startswith("127.") or not cell_spec.ft.host.startswith("127."):
        raise ValueError("sim serve runs on loopback only: robot.host and ft.host must be 127.0.0.x")
    params = params_from_cell(cell_spec, obj, seed=seed)
    if reference_sphere_radius_mm is not None:
        params.object = reference_sphere(reference_sphere_radius_mm)
    cell = SimCell(untrippable_params(params))
    backend = WorldBackend(cell)
    ft_spec, sc_spec = cell_spec.ft, cell_spec.scanner
    emulator = netft = scanner = None
    try:
        emulator = UREmulator(cell_spec.robot.host, backend, unlock_delay_s=unlock_delay_s,
                              lifetime_s=lifetime_s).start()
        netft = NetFTServer(ft_spec.host, ft_spec.rdt_port, ft_spec.calinfo_port, source=backend.ft_source,
                            rate_hz=ft_spec.rate_hz, records_per_datagram=ft_records_per_datagram,
                            counts_per_force=backend.counts_per_force, counts_per_torque=backend.counts_per_torque,
                            seed=seed, max_lifetime_s=lifetime_s).start()
        transport, host, port = scanner_transport(sc_spec.url)
        # The fixed x grid spans the laser fan out to the maximum range (the table seen from a
        # sweep is far); z is quantised over [MIN_RANGE_MM, max_range_mm] (int16: ~6 um at
        # 400 mm, below the simulated depth noise of >= 10 um).
        far_mm = float(sc_spec.max_range_mm)
        span_mm = 2.0 * far_mm * math.tan(math.radians(sc_spec.field_of_view_deg) / 2.0)
        z_mid_mm = (MIN_RANGE_MM + far_mm) / 2.0
        z_scale_mm = (far_mm - MIN_RANGE_MM) / 65000.0
        holder: dict[str, Any] = {}

        def profile(counter: int, device_t_s: float) -> np.ndarray:
            return holder["source"](counter, device_t_s)

        kwargs: dict[str, Any] = {"transport": transport}
        if transport == "tcp":
            kwargs.update(host=host, port=port)
        # Frames carry the world scanner's own samples with explicit x (5 um steps): the
        # controller gets the points the in-process scanner gives. (A fixed x grid over the
        # fan at the maximum range put half as many samples on the object and interpolated
        # across silhouettes: a different cloud, different probe targets than in process.)
        scanner = ScannerPtyServer(profile, n_points=backend.scanner_samples, x_span_mm=span_mm,
                                   z_scale_mm=z_scale_mm, z_offset_mm=z_mid_mm, rate_hz=sc_spec.rate_hz,
                                   serial=f"SIM-LLS-{seed:04d}", seed=seed, max_lifetime_s=lifetime_s, **kwargs)
        holder["source"] = backend.native_profile_source()
        scanner.start()
    except BaseException:
        for server in (scanner, netft, emulator):
            if server is not None:
                server.stop()
        raise
    served_object = str(obj) if reference_sphere_radius_mm is None else \
        f"reference sphere, radius {reference_sphere_radius_mm:g} mm"
    state = {"pid": os.getpid(), "seed": int(seed), "cell": str(cell_path), "object": served_object,
             "robot_host": cell_spec.robot.host, "ft_host": ft_spec.host, "rdt_port": netft.rdt_port,
             "calinfo_port": netft.calinfo_port, "scanner_url": scanner.url, "started_wall_s": time.time()}
    return ServedCell(backend, emulator, netft, scanner, state)


def write_state(run_dir: str | Path, state: dict[str, Any]) -> Path:
    """Write ``RUN_DIR/serve.json`` atomically (temp name + rename)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / STATE_FILE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(state, indent=2))
    os.replace(tmp, path)
    return path


def read_state(run_dir: str | Path, timeout_s: float = 0.0) -> dict[str, Any] | None:
    """The state file of a running ``serve`` (waits up to ``timeout_s`` for it to appear)."""
    path = Path(run_dir) / STATE_FILE
    deadline = time.monotonic() + timeout_s
    while True:
        if path.exists():
            return json.loads(path.read_text())
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.05)


def serve(cell_spec: Any, cell_path: str | Path, seed: int, stop_event: threading.Event | None = None, *,
          run_dir: str | Path | None = None, object_path: str | Path | None = None,
          lifetime_s: float = DEFAULT_LIFETIME_S, ready: threading.Event | None = None,
          reference_sphere_radius_mm: float | None = None) -> dict[str, Any]:
    """Serve the cell's simulated world until ``stop_event`` is set or ``lifetime_s`` passes.

    Returns the state (addresses) it served. ``ready`` is set once everything listens (and
    the state file, if ``run_dir`` is given, is written)."""
    stop_event = stop_event or threading.Event()
    # Four busy threads share one GIL (emulator tick, Net F/T, scanner, RTDE sessions): a short
    # switch interval keeps the 1 kHz F/T stream from being starved into bursts.
    sys.setswitchinterval(0.0005)
    served = start_servers(cell_spec, cell_path, seed, object_path=object_path, lifetime_s=lifetime_s,
                           reference_sphere_radius_mm=reference_sphere_radius_mm)
    try:
        if run_dir is not None:
            write_state(run_dir, served.state)
        if ready is not None:
            ready.set()
        end = time.monotonic() + lifetime_s
        while not stop_event.wait(0.2) and time.monotonic() < end:
            pass
    finally:
        served.stop()
        if run_dir is not None:
            try:
                (Path(run_dir) / STATE_FILE).unlink()
            except OSError:
                pass
    return served.state


def main_serve(cell_path: str | Path, seed: int, run_dir: str | Path | None = None,
               lifetime_s: float = DEFAULT_LIFETIME_S) -> int:
    """CLI entry: ``elastoprobe sim serve [--cell CELL] [--seed N]``. Exit 0 on a clean stop,
    2 on a bad cell file (``path:line:col: message``)."""
    from elastoprobe.controller.core.config import DEFAULT_CELL, load_cell
    from elastoprobe.controller.core.errors import InputError

    cell_path = Path(cell_path) if cell_path is not None else DEFAULT_CELL
    try:
        spec, _ = load_cell(cell_path)
    except InputError as exc:
        print(exc.format(), file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    ready = threading.Event()
    try:
        printer = threading.Thread(target=_announce, args=(ready, stop, run_dir), daemon=True)
        printer.start()
        state = serve(spec, cell_path, seed, stop, run_dir=run_dir, lifetime_s=lifetime_s, ready=ready)
    except (OSError, ValueError) as exc:
        print(f"{cell_path}: cannot serve: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"stopped serving {state['robot_host']}", file=sys.stderr)
    return 0


def _announce(ready: threading.Event, stop: threading.Event, run_dir: str | Path | None) -> None:
    while not ready.wait(0.2):
        if stop.is_set():
            return
    where = f" (state in {Path(run_dir) / STATE_FILE})" if run_dir is not None else ""
    print(f"serving the simulated cell over loopback{where}; Ctrl-C stops", file=sys.stderr, flush=True)


def serve_child_main(cell_path: str, object_path: str | None, seed: int, run_dir: str, lifetime_s: float,
                     parent_pid: int, reference_sphere_radius_mm: float | None = None) -> None:
    """Entry of a ``spawn``-ed serve process that dies with its parent (the loopback cell)."""
    from elastoprobe.controller.core.config import load_cell

    set_parent_death_signal()
    if os.getppid() != parent_pid:
        os._exit(0)
    try:
        # The served arm, F/T and scanner stand in for real-time hardware: on a busy computer
        # they ask for more than their share (as the hardware process does), so the load is
        # not taken for robot latency. Before any thread starts (threads inherit it).
        os.setpriority(os.PRIO_PROCESS, 0, SERVE_NICE)
    except OSError:
        pass                                           # not permitted: normal priority
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the controller's Ctrl-C is the controller's

    def watch_parent() -> None:
        while not stop.wait(0.2):
            if os.getppid() != parent_pid:
                stop.set()

    threading.Thread(target=watch_parent, daemon=True).start()
    spec, _ = load_cell(cell_path)
    try:
        serve(spec, cell_path, seed, stop, run_dir=run_dir, object_path=object_path, lifetime_s=lifetime_s,
              reference_sphere_radius_mm=reference_sphere_radius_mm)
    except BaseException as exc:  # noqa: BLE001 — leave the reason where the parent looks
        try:
            (Path(run_dir) / "serve.error").write_text(f"{type(exc).__name__}: {exc}")
        except OSError:
            pass
        os._exit(2)
    os._exit(0)
