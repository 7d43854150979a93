"""A UR e-Series controller emulator that the real ur_rtde 1.6.5 connects to on loopback.

One :class:`UREmulator` serves, on one loopback address (127.0.0.x):

- RTDE (30004): protocol versions 1 and 2, output recipes streamed at their
  frequency (500 Hz for ur_rtde on e-Series), input recipes written into the
  controller's input variables; control, receive and IO sessions at once.
- script upload (30001, 30002, 30003): a received program replaces the running one.
  The ur_rtde control script is recognised and *emulated*: the register protocol
  of docs/ur_emulation.md (command in input_int_register_0, arguments in the input
  registers, output_int_register_0 = 1 ready / 2 done, async progress word in
  output_int_register_2), including rtde_set_watchdog.
- dashboard (29999): the text commands ur_rtde's DashboardClient sends.

It drives an :class:`~elastoprobe.sim.servers.ur_backend.ArmBackend` (the simulated
world's arm, or :class:`KinematicBackend` in tests) from a 500 Hz tick thread in wall
time (ur_rtde waits on the wall clock). Faults can be injected: protective stop (the
dashboard refuses to unlock it for ``unlock_delay_s`` = 5 s, as a real controller
does), emergency stop (only :meth:`release_emergency_stop` clears it, never the
dashboard), dropped RTDE connections (optionally refusing reconnects for a while).

TCP: like a real controller, the emulator takes and reports TCP poses for the active TCP
offset — ``actual_TCP_pose`` = flange pose ∘ offset, and a moveL target is where that TCP
goes. A control script starts with the installation's TCP (``installation_tcp_ur``,
default the flange itself) and ``setTcp`` replaces it until the program ends (a new script
starts from the installation's again). speedL velocities are passed on as they are: the
controller commands no rotation with them, and without rotation the TCP and the flange move
alike.

Everything is bounded: sockets use short timeouts, each server has a lifetime
(``lifetime_s``), and :meth:`stop` closes every socket and joins every thread.
"""
from __future__ import annotations

import logging
import math
import re
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from elastoprobe.controller.core.geometry import Pose

from .ur_backend import ArmBackend, KinematicBackend  # noqa: F401  (re-exported)
from .ur_rtde_protocol import (
    CMD_DATA_PACKAGE, CMD_GET_URCONTROL_VERSION, CMD_PAUSE, CMD_REQUEST_PROTOCOL_VERSION,
    CMD_SETUP_INPUTS, CMD_SETUP_OUTPUTS, CMD_START, HEADER, INPUT_VARIABLES, N_REGISTERS,
    OUTPUT_VARIABLES, Recipe, frame, parse_names,
)

__all__ = ["UREmulator", "ArmBackend", "KinematicBackend", "DEFAULT_PORTS", "Cmd"]

log = logging.getLogger(__name__)

DEFAULT_PORTS: dict[str, int] = {"rtde": 30004, "dashboard": 29999, "primary": 30001,
                                 "secondary": 30002, "realtime": 30003}


class Cmd:
    """Command ids of the ur_rtde 1.6.5 control script (input_int_register_0).

    Checked against the script embedded in librtde 1.6.5 and against what the real
    library sends (tests/test_ur_emulator.py records them).
    """

    NO_CMD = 0
    MOVEJ = 1
    MOVEJ_IK = 2
    MOVEL = 3
    MOVEL_FK = 4
    FORCE_MODE = 6
    FORCE_MODE_STOP = 7
    ZERO_FT_SENSOR = 8
    SPEEDJ = 9
    SPEEDL = 10
    SERVOJ = 11
    SPEED_STOP = 15
    SERVO_STOP = 16
    SET_PAYLOAD = 17
    SET_TCP = 29
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    SET_WATCHDOG = 35
    GET_TCP_OFFSET = 40
    GET_FORWARD_KINEMATICS_DEFAULT = 43
    IS_STEADY = 47
    STOP_SCRIPT = 255
    # The script treats these as real-time: process and stay "ready", no "done".
    REALTIME = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
    # Motion commands the script runs in its main thread or its async move thread (not the
    # speed thread): while the speed thread runs, each is a second thread controlling the robot
    # (moveJ/moveJ_IK/moveL/moveL_FK, stopL/stopJ, and forceModeStop, which ends with stopl(10)).
    MOTION_IN_MAIN_OR_MOVE_THREAD = frozenset({1, 2, 3, 4, 7, 33, 34})


READY = 1
DONE = 2

# Robot / safety state words (UR's RTDE guide).
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODE_ROBOT_EMERGENCY_STOP = 7
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2

_DASHBOARD_GREETING = b"Connected: Universal Robots Dashboard Server\n"
_UNLOCK_REFUSED = ("Cannot unlock protective stop until 5s after occurrence. "
                   "Always inspect cause of protective stop before unlocking")


@dataclass
class _RtdeSession:
    """One RTDE client connection and what it negotiated."""

    sock: socket.socket
    peer: str
    protocol_version: int = 1
    outputs: list[Recipe] = field(default_factory=list)
    inputs: dict[int, Recipe] = field(default_factory=dict)
    started: bool = False
    closed: bool = False
    next_due_s: dict[int, float] = field(default_factory=dict)
    send_lock: threading.Lock = field(default_factory=threading.Lock)


@dataclass
class Event:
    """Something the emulator did or saw (for tests and diagnostics)."""

    t_s: float
    kind: str
    detail: str = ""


class _Snapshot:
    """The controller's output variables at one tick, computed lazily (joints cost an IK)."""

    def __init__(self, emu: "UREmulator", now_s: float) -> None:
        self._emu = emu
        self._now_s = now_s
        self._cache: dict[str, object] = {}

    def _core(self, key: str) -> object:
        if key not in self._cache:
            if key in _POSE_SAMPLE_NAMES:
                # The timestamp and the TCP pose of one package come from one read of the arm.
                if "_pose_sample" not in self._cache:
                    self._cache["_pose_sample"] = self._emu._pose_sample(self._now_s)
                t_s, pose = self._cache["_pose_sample"]          # type: ignore[misc]
                self._cache[key] = (t_s - self._emu._t_boot_s if key == "timestamp"
                                    else tuple(float(v) for v in pose))
            else:
                self._cache[key] = self._emu._core_value(key, self._now_s)
        return self._cache[key]

    def get(self, name: str, typ: str) -> object:
        emu = self._emu
        if name.startswith("output_int_register_"):
            return int(emu._out_int[int(name.rsplit("_", 1)[1])])
        if name.startswith("output_double_register_"):
            return float(emu._out_double[int(name.rsplit("_", 1)[1])])
        if name.startswith("input_") and name in emu._inputs:
            return emu._inputs[name]
        if name in _CORE_NAMES:
            return self._core(name)
        return _default_value(typ)


# How long after a backend grid instant the emulator ticks (see UREmulator._aligned_tick_s).
_GRID_LEAD_S = 1e-4

_POSE_SAMPLE_NAMES = frozenset({"timestamp", "actual_TCP_pose", "target_TCP_pose"})

_CORE_NAMES = frozenset({
    "timestamp", "actual_q", "target_q", "actual_qd", "target_qd", "actual_TCP_pose", "target_TCP_pose",
    "actual_TCP_speed", "target_TCP_speed", "actual_TCP_force", "robot_mode", "safety_mode", "safety_status",
    "robot_status_bits", "safety_status_bits", "runtime_state", "speed_scaling", "target_speed_fraction",
    "joint_mode", "actual_main_voltage", "actual_robot_voltage", "tcp_force_scalar", "ft_raw_wrench",
    "payload", "joint_temperatures", "actual_execution_time",
})


def _default_value(typ: str) -> object:
    if typ == "VECTOR6D":
        return (0.0,) * 6
    if typ == "VECTOR3D":
        return (0.0,) * 3
    if typ in ("VECTOR6INT32", "VECTOR6UINT32"):
        return (0,) * 6
    if typ == "DOUBLE":
        return 0.0
    if typ == "BOOL":
        return False
    return 0


def _recv_exact(sock: socket.socket, n: int, stop: threading.Event) -> bytes | None:
    """Read exactly ``n`` bytes, or None on EOF/stop. The socket has a short timeout."""
    buf = bytearray()
    while len(buf) < n:
        if stop.is_set():
            return None
        try:
            chunk = sock.recv(n - len(buf))
        except socket.timeout:
            continue
        except OSError:
            return None
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


class UREmulator:
    """A UR controller on ``host`` (a 127.0.0.x address) driving ``backend``.

    Use as a context manager, or call :meth:`start` and :meth:`stop`. Parameters:
    ``controller_version`` (major, minor, bugfix, build) answered to RTDE ``v``;
    ``polyscope_version``, ``serial_number``, ``robot_model`` for the dashboard;
    ``tick_hz`` controller cycle (500 Hz on e-Series); ``unlock_delay_s`` how long
    after a protective stop the dashboard refuses "unlock protective stop";
    ``program_stop_decel_m_s2`` deceleration when a program stops (watchdog, stop);
    ``protective_stop_decel_m_s2`` deceleration of a protective stop;
    ``script_start_delay_s`` between receiving a program and running it;
    ``lifetime_s`` after which the emulator stops by itself.
    """

    def __init__(self, host: str = "127.0.0.1", backend: ArmBackend | None = None, *,
                 controller_version: tuple[int, int, int, int] = (5, 11, 1, 108318),
                 polyscope_version: str = "5.11.1.108318", serial_number: str = "20235500042",
                 robot_model: str = "UR5", tick_hz: float = 500.0, unlock_delay_s: float = 5.0,
                 program_stop_decel_m_s2: float = 10.0, protective_stop_decel_m_s2: float = 20.0,
                 script_start_delay_s: float = 0.05, lifetime_s: float = 3600.0,
                 ports: dict[str, int] | None = None, max_connections: int = 32,
                 installation_tcp_ur: "np.ndarray | list[float] | None" = None,
                 dashboard_replies: dict[str, str] | None = None) -> None:
        if not host.startswith("127."):
            raise ValueError(f"the UR emulator only serves loopback addresses, not {host!r}")
        self.host = host
        self.backend: ArmBackend = backend if backend is not None else KinematicBackend(t0_s=time.monotonic())
        self.controller_version = tuple(int(v) for v in controller_version)
        self.polyscope_version = polyscope_version
        self.serial_number = serial_number
        self.robot_model = robot_model
        self.tick_hz = float(tick_hz)
        self.unlock_delay_s = float(unlock_delay_s)
        self.program_stop_decel_m_s2 = float(program_stop_decel_m_s2)
        self.protective_stop_decel_m_s2 = float(protective_stop_decel_m_s2)
        self.script_start_delay_s = float(script_start_delay_s)
        self.lifetime_s = float(lifetime_s)
        self.ports = dict(DEFAULT_PORTS if ports is None else ports)
        self.max_connections = int(max_connections)
        # Replies the dashboard gives instead of its own (lower-case command -> reply): a
        # controller that answers something else (tests of the driver's checks).
        self.dashboard_replies = {k.lower(): v for k, v in (dashboard_replies or {}).items()}

        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listeners: list[socket.socket] = []
        self._conns: set[socket.socket] = set()
        self._sessions: list[_RtdeSession] = []
        self._t_boot_s = time.monotonic()

        # Controller variables. RTDE input packages land in ``_inputs`` under their own small
        # lock (a connection thread never waits for a controller tick, which holds ``_lock``
        # while it steps the arm and packs the output streams); each tick reads one copy,
        # ``_cycle_inputs``, as a real controller samples its inputs once per cycle (a
        # command's arguments never mix two packages).
        self._inputs: dict[str, object] = {}
        self._inputs_lock = threading.Lock()
        self._cycle_inputs: dict[str, object] = {}
        self._input_owner: dict[str, _RtdeSession] = {}
        self._out_int = np.zeros(N_REGISTERS, dtype=np.int64)
        self._out_double = np.zeros(N_REGISTERS)

        # Program (emulated control script) state.
        self._program_running = False
        self._program_name = "<unnamed>"
        self._pending_program: tuple[float, str] | None = None
        self._reg_offset = 0
        self._executing_cmd = False
        self._sync_wait: str | None = None           # "move" or "stop" while a blocking command runs
        self._async_running = False
        # ur_rtde's speed thread: started by speedL/speedJ, killed by speedStop or the end of
        # the program. A motion command of the script's main or move thread while it runs is a
        # second thread controlling the robot: URScript halts the program.
        self._speed_thread = False
        self._paused = False
        self._async_op_id = 0
        self._async_wr_count = 0
        self._watchdog: tuple[str, float] | None = None   # (variable, period_s)
        self._watchdog_last_s = 0.0
        # The TCP a program starts with (a real controller's installation TCP), the one in
        # force (set_tcp), and the map from the backend's tool point to it (None: the same).
        self.installation_tcp_ur = np.zeros(6) if installation_tcp_ur is None \
            else np.asarray(installation_tcp_ur, float).reshape(6).copy()
        self._tcp_offset = self.installation_tcp_ur.copy()
        self._tool_to_tcp: Pose | None = None
        self._set_tcp_offset(self._tcp_offset)
        self._payload_kg = 0.0

        # Safety state.
        self._protective_stop_t_s: float | None = None
        self._emergency_stop = False
        self._refuse_rtde_until_s = 0.0

        # Observations.
        self.events: list[Event] = []
        self.commands_seen: list[int] = []
        self.dashboard_log: list[str] = []
        self.programs_received: list[str] = []
        self.recipes_seen: list[tuple[str, tuple[str, ...]]] = []

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "UREmulator":
        """Bind every port on ``host`` and start serving; raises OSError if a port is taken."""
        try:
            for kind, port in self.ports.items():
                srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                srv.bind((self.host, port))
                srv.listen(8)
                srv.settimeout(0.2)
                self._listeners.append(srv)
                self._spawn(self._accept_loop, srv, kind, name=f"ur-emu-accept-{kind}")
        except OSError:
            self.stop()
            raise
        self._spawn(self._tick_loop, name="ur-emu-tick")
        return self

    def stop(self, timeout_s: float = 3.0) -> None:
        """Close every socket and join every thread (bounded by ``timeout_s`` in total)."""
        self._stop.set()
        for srv in self._listeners:
            try:
                srv.close()
            except OSError:
                pass
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            _close_quietly(c)
        deadline = time.monotonic() + timeout_s
        for th in self._threads:
            if th is not threading.current_thread():
                th.join(max(0.0, deadline - time.monotonic()))
        self._listeners.clear()

    def __enter__(self) -> "UREmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive_threads(self) -> int:
        return sum(th.is_alive() for th in self._threads)

    def _spawn(self, target: Callable[..., None], *args: object, name: str) -> None:
        th = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(th)
        th.start()

    def _event(self, kind: str, detail: str = "") -> None:
        self.events.append(Event(time.monotonic(), kind, detail))
        log.debug("ur-emu %s: %s %s", self.host, kind, detail)

    # ------------------------------------------------------------------ injections
    def inject_protective_stop(self, reason: str = "injected") -> None:
        """The arm protective-stops now: motion stops, the program stops."""
        with self._lock:
            self._enter_protective_stop(time.monotonic(), reason)

    def inject_emergency_stop(self) -> None:
        """Someone pressed the e-stop: motion stops, the program stops, until released."""
        with self._lock:
            self._emergency_stop = True
            self.backend.stop(self.protective_stop_decel_m_s2)
            self._end_program("emergency_stop")
            self._event("emergency_stop")

    def release_emergency_stop(self) -> None:
        """The operator released the e-stop button (the only way to clear it)."""
        with self._lock:
            self._emergency_stop = False
            self._event("emergency_stop_released")

    def drop_connections(self, refuse_s: float = 0.0) -> int:
        """Close every RTDE connection now; refuse new ones for ``refuse_s``. Returns the count."""
        with self._lock:
            self._refuse_rtde_until_s = time.monotonic() + refuse_s
            sessions = list(self._sessions)
        for s in sessions:
            self._close_session(s)
        self._event("drop_connections", f"{len(sessions)} sessions, refuse {refuse_s} s")
        return len(sessions)

    # ------------------------------------------------------------------ observations
    @property
    def program_running(self) -> bool:
        return self._program_running

    @property
    def protective_stopped(self) -> bool:
        return self._protective_stop_t_s is not None

    @property
    def emergency_stopped(self) -> bool:
        return self._emergency_stop

    @property
    def rtde_sessions(self) -> int:
        with self._lock:
            return sum(not s.closed for s in self._sessions)

    def tcp_pose_ur(self) -> np.ndarray:
        """The TCP pose as the controller reports it (for the active TCP offset), m + rotation vector."""
        with self._lock:
            return self._reported_pose_ur(np.asarray(self.backend.tcp_pose_ur(), dtype=float))

    @property
    def tcp_offset_ur(self) -> np.ndarray:
        """The active TCP offset (flange -> TCP), m + rotation vector."""
        with self._lock:
            return self._tcp_offset.copy()

    # ------------------------------------------------------------------ TCP offset
    def _set_tcp_offset(self, offset_ur: np.ndarray) -> None:
        """Make ``offset_ur`` (flange -> TCP) the active TCP; poses in and out follow it."""
        self._tcp_offset = np.asarray(offset_ur, float).reshape(6).copy()
        tool = getattr(self.backend, "tool_ur", None)
        tool_ur = np.zeros(6) if tool is None else np.asarray(tool(), float)
        # backend tool point -> active TCP: tool^-1 ∘ offset.
        move = Pose.from_ur(tool_ur).inverse().compose(Pose.from_ur(self._tcp_offset))
        identity = np.allclose(move.position_mm, 0.0, atol=1e-9) and np.allclose(move.rotation, np.eye(3), atol=1e-12)
        self._tool_to_tcp = None if identity else move

    def _reported_pose_ur(self, backend_pose_ur: np.ndarray) -> np.ndarray:
        """A backend pose (its tool point) as the active TCP's pose."""
        if self._tool_to_tcp is None:
            return np.asarray(backend_pose_ur, float)
        return np.asarray(Pose.from_ur(backend_pose_ur).compose(self._tool_to_tcp).to_ur(), float)

    def _backend_target_ur(self, tcp_target_ur: np.ndarray) -> np.ndarray:
        """A TCP target (active TCP) as the pose of the backend's tool point."""
        if self._tool_to_tcp is None:
            return np.asarray(tcp_target_ur, float)
        return np.asarray(Pose.from_ur(tcp_target_ur).compose(self._tool_to_tcp.inverse()).to_ur(), float)

    def _pose_sample(self, now: float) -> tuple[float, np.ndarray]:
        """(controller time of the state (s, monotonic), the active TCP's pose): one read of the
        backend, so the pose and its timestamp belong together (a real controller stamps each
        package with the cycle its values were sampled in)."""
        sample = getattr(self.backend, "pose_sample_ur", None)
        if sample is None:
            t_s, pose = now, np.asarray(self.backend.tcp_pose_ur(), float)
        else:
            t_s, pose = sample()
        return float(t_s), self._reported_pose_ur(pose)

    def is_moving(self) -> bool:
        with self._lock:
            return bool(self.backend.is_moving())

    def events_of(self, kind: str) -> list[Event]:
        return [e for e in list(self.events) if e.kind == kind]

    # ------------------------------------------------------------------ accept
    def _accept_loop(self, srv: socket.socket, kind: str) -> None:
        handler = {"rtde": self._serve_rtde, "dashboard": self._serve_dashboard}.get(kind, self._serve_script)
        while not self._stop.is_set():
            try:
                conn, addr = srv.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            if kind == "rtde" and time.monotonic() < self._refuse_rtde_until_s:
                _close_quietly(conn)
                self._event("rtde_refused")
                continue
            with self._lock:
                if len(self._conns) >= self.max_connections:
                    _close_quietly(conn)
                    continue
                self._conns.add(conn)
            conn.settimeout(0.2)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._threads = [t for t in self._threads if t.is_alive()]
            self._spawn(self._run_connection, handler, conn, f"{addr[0]}:{addr[1]}", name=f"ur-emu-{kind}-conn")

    def _run_connection(self, handler: Callable[[socket.socket, str], None], conn: socket.socket, peer: str) -> None:
        try:
            handler(conn, peer)
        except Exception:  # noqa: BLE001 — one bad client must not take the emulator down
            log.exception("ur-emu %s: connection %s failed", self.host, peer)
        finally:
            with self._lock:
                self._conns.discard(conn)
            _close_quietly(conn)

    # ------------------------------------------------------------------ RTDE
    def _serve_rtde(self, conn: socket.socket, peer: str) -> None:
        session = _RtdeSession(conn, peer)
        with self._lock:
            self._sessions.append(session)
        self._event("rtde_connect", peer)
        try:
            while not self._stop.is_set() and not session.closed:
                header = _recv_exact(conn, HEADER.size, self._stop)
                if header is None:
                    break
                size, command = HEADER.unpack(header)
                if size < HEADER.size or size > 65535:
                    break
                payload = _recv_exact(conn, size - HEADER.size, self._stop) if size > HEADER.size else b""
                if payload is None:
                    break
                self._handle_rtde(session, command, payload)
        finally:
            self._close_session(session)
            self._event("rtde_disconnect", peer)

    def _handle_rtde(self, s: _RtdeSession, command: int, payload: bytes) -> None:
        if command == CMD_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            accepted = version in (1, 2)
            if accepted:
                s.protocol_version = version
            self._send(s, frame(command, bytes([1 if accepted else 0])))
        elif command == CMD_GET_URCONTROL_VERSION:
            self._send(s, frame(command, struct.pack(">IIII", *self.controller_version)))
        elif command == CMD_SETUP_OUTPUTS:
            if s.protocol_version >= 2:
                (freq,) = struct.unpack(">d", payload[:8])
                names = parse_names(payload[8:])
            else:
                freq, names = 125.0, parse_names(payload)
            types = [OUTPUT_VARIABLES.get(n, "NOT_FOUND") for n in names]
            self.recipes_seen.append(("out", tuple(names)))
            if "NOT_FOUND" in types:
                self._event("rtde_output_not_found", ",".join(n for n, t in zip(names, types) if t == "NOT_FOUND"))
                self._send(s, frame(command, bytes([0]) + ",".join(types).encode()))
                return
            recipe_id = len(s.outputs) + 1
            recipe = Recipe.build(recipe_id, names, types, min(float(freq), self.tick_hz) if freq > 0 else self.tick_hz)
            with self._lock:
                s.outputs.append(recipe)
            self._send(s, frame(command, bytes([recipe_id]) + ",".join(types).encode()))
        elif command == CMD_SETUP_INPUTS:
            names = parse_names(payload)
            self.recipes_seen.append(("in", tuple(names)))
            with self._lock:
                types = []
                for n in names:
                    owner = self._input_owner.get(n)
                    if n not in INPUT_VARIABLES:
                        types.append("NOT_FOUND")
                    elif owner is not None and owner is not s and not owner.closed:
                        types.append("IN_USE")
                    else:
                        types.append(INPUT_VARIABLES[n])
                if "NOT_FOUND" in types or "IN_USE" in types:
                    self._event("rtde_input_refused", ",".join(f"{n}:{t}" for n, t in zip(names, types)))
                    self._send(s, frame(command, bytes([0]) + ",".join(types).encode()))
                    return
                recipe_id = len(s.inputs) + 1
                s.inputs[recipe_id] = Recipe.build(recipe_id, names, types)
                for n in names:
                    self._input_owner[n] = s
            self._send(s, frame(command, bytes([recipe_id]) + ",".join(types).encode()))
        elif command == CMD_START:
            with self._lock:
                s.started = True
                s.next_due_s = {r.recipe_id: 0.0 for r in s.outputs}
            self._send(s, frame(command, bytes([1])))
        elif command == CMD_PAUSE:
            s.started = False
            self._send(s, frame(command, bytes([1])))
        elif command == CMD_DATA_PACKAGE:
            if not payload:
                return
            recipe = s.inputs.get(payload[0])
            if recipe is None or len(payload) - 1 != recipe.codec.size:
                self._event("rtde_bad_data", f"recipe {payload[0]} size {len(payload) - 1}")
                return
            values = recipe.unpack(payload[1:])
            now = time.monotonic()
            with self._inputs_lock:
                self._inputs.update(values)
                watchdog = self._watchdog
                if watchdog is not None and watchdog[0] in values:
                    self._watchdog_last_s = now
        else:
            self._event("rtde_unknown_command", str(command))

    def _send(self, s: _RtdeSession, data: bytes) -> bool:
        if s.closed:
            return False
        try:
            with s.send_lock:
                s.sock.sendall(data)
            return True
        except OSError:
            self._close_session(s)
            return False

    def _close_session(self, s: _RtdeSession) -> None:
        with self._lock:
            if s.closed:
                return
            s.closed = True
            s.started = False
            for name in [n for n, owner in self._input_owner.items() if owner is s]:
                del self._input_owner[name]
            self._sessions = [x for x in self._sessions if x is not s]
        try:
            s.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        _close_quietly(s.sock)

    # ------------------------------------------------------------------ dashboard
    def _serve_dashboard(self, conn: socket.socket, peer: str) -> None:
        conn.sendall(_DASHBOARD_GREETING)
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            if len(buf) > 65536:
                return
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                text = line.decode("utf-8", errors="replace").strip()
                if not text:
                    continue
                reply = self._dashboard_reply(text)
                self.dashboard_log.append(text)
                try:
                    conn.sendall((reply + "\n").encode())
                except OSError:
                    return
                if text == "quit":
                    return

    def _dashboard_reply(self, text: str) -> str:
        cmd = text.strip()
        low = cmd.lower()
        now = time.monotonic()
        if low in self.dashboard_replies:
            return self.dashboard_replies[low]
        with self._lock:
            if low == "polyscopeversion":
                return f"URSoftware {self.polyscope_version} (Mar 22 2021)"
            if low == "version":
                return f"Version: {self.polyscope_version}"
            if low == "get serial number":
                return self.serial_number
            if low == "get robot model":
                return self.robot_model
            if low == "is in remote control":
                return "true"
            if low == "running":
                return f"Program running: {'true' if self._program_running else 'false'}"
            if low == "programstate":
                if self._program_running:
                    return f"PLAYING {self._program_name}"
                return f"PAUSED {self._program_name}" if self._paused else f"STOPPED {self._program_name}"
            if low == "robotmode":
                return "Robotmode: " + ("POWER_OFF" if self._emergency_stop else "RUNNING")
            if low in ("safetystatus", "safetymode"):
                label = "Safetystatus: " if low == "safetystatus" else "Safetymode: "
                return label + self._safety_word()
            if low == "unlock protective stop":
                return self._unlock_protective_stop(now)
            if low == "close safety popup":
                return "closing safety popup"
            if low == "close popup":
                return "closing popup"
            if low.startswith("popup"):
                return "showing popup"
            if low == "stop":
                if self._program_running or self._paused:
                    self._paused = False
                    self._end_program("dashboard_stop")
                    return "Stopped"
                return "Failed to execute: stop"
            if low == "pause":
                if self._program_running:
                    # Paused, not ended: its threads and registers stay for "play". The arm stops.
                    self._program_running = False
                    self._paused = True
                    if self.backend.is_moving():
                        self.backend.stop(self.program_stop_decel_m_s2)
                    self._event("program_paused", "dashboard")
                    return "Pausing program"
                return "Failed to execute: pause"
            if low == "play":
                if self._paused and self._protective_stop_t_s is None and not self._emergency_stop:
                    self._paused = False
                    self._program_running = True
                    self._watchdog_last_s = now
                    self._event("program_resumed")
                    return "Starting program"
                return "Failed to execute: play"
            if low == "power on":
                return "Powering on"
            if low == "power off":
                return "Powering off"
            if low == "brake release":
                return "Brake releasing"
            if low == "restart safety":
                return "Restarting safety"
            if low == "get loaded program":
                return "No program loaded"
            if low == "isprogramsaved":
                return "true <unnamed>"
            if low.startswith("addtolog"):
                return "Added log message"
            if low == "get operational mode":
                return "NONE"
            if low.startswith("setuserrole"):
                return "Setting user role: " + cmd.split(" ", 1)[-1]
            if low == "getuserrole":
                return "PROGRAMMER"
            if low == "shutdown":
                return "Shutting down"
            if low == "quit":
                return "Disconnected"
        return f"could not understand: '{cmd}'"

    def _safety_word(self) -> str:
        if self._emergency_stop:
            return "ROBOT_EMERGENCY_STOP"
        if self._protective_stop_t_s is not None:
            return "PROTECTIVE_STOP"
        return "NORMAL"

    def _unlock_protective_stop(self, now: float) -> str:
        if self._emergency_stop:
            self._event("unlock_refused", "emergency stop")
            return "Cannot unlock protective stop, the robot is emergency stopped"
        if self._protective_stop_t_s is None:
            return "Protective stop releasing"
        if now - self._protective_stop_t_s < self.unlock_delay_s:
            self._event("unlock_refused", f"{now - self._protective_stop_t_s:.2f} s after the stop")
            return _UNLOCK_REFUSED
        self._protective_stop_t_s = None
        self._event("protective_stop_unlocked")
        return "Protective stop releasing"

    # ------------------------------------------------------------------ script upload
    def _serve_script(self, conn: socket.socket, peer: str) -> None:
        buf = ""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                break
            if not chunk:
                break
            buf += chunk.decode("utf-8", errors="replace")
            if len(buf) > 4_000_000:
                break
            buf = self._take_programs(buf)
        if buf.strip():
            self._receive_program(buf)

    def _take_programs(self, buf: str) -> str:
        """Run each complete top-level program (``def``/``sec`` ... a column-0 ``end``)."""
        while True:
            start = re.search(r"^(def|sec)\s+\w+\s*\(\s*\)\s*:", buf, flags=re.MULTILINE)
            if start is None:
                return buf if len(buf) < 65536 else ""
            end = re.search(r"^end[ \t]*(\r?\n|$)", buf[start.start():], flags=re.MULTILINE)
            if end is None or (end.end() == len(buf) - start.start() and not end.group(1)):
                return buf
            stop = start.start() + end.end()
            self._receive_program(buf[start.start():stop])
            buf = buf[stop:]

    def _receive_program(self, text: str) -> None:
        now = time.monotonic()
        name_match = re.search(r"^(?:def|sec)\s+(\w+)", text, flags=re.MULTILINE)
        name = name_match.group(1) if name_match else "<unnamed>"
        with self._lock:
            self.programs_received.append(text)
            self._event("program_received", f"{name} ({len(text)} chars)")
            if self._program_running:
                self._end_program("replaced")
            self._pending_program = (now + self.script_start_delay_s, text)

    def _start_program(self, text: str, now: float) -> None:
        if self._protective_stop_t_s is not None or self._emergency_stop:
            self._event("program_refused", self._safety_word())
            return
        is_control_script = "rtde_cmd" in text or "signal_ready" in text or "RTDE Control Script" in text
        name_match = re.search(r"^(?:def|sec)\s+(\w+)", text, flags=re.MULTILINE)
        self._program_name = name_match.group(1) if name_match else "<unnamed>"
        if not is_control_script:
            # A custom program is accepted but not interpreted: it "runs" for no time.
            self._event("program_ignored", self._program_name)
            return
        # ur_rtde injects the value after the marker comment, i.e. on the next line.
        offset = re.search(r"reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text)
        self._reg_offset = int(offset.group(1)) if offset else 0
        self._program_running = True
        self._paused = False
        self._executing_cmd = False
        self._sync_wait = None
        self._watchdog = None
        self._async_running = False
        self._speed_thread = False
        # A program starts with the installation's TCP: a setTcp of an earlier program is gone.
        self._set_tcp_offset(self.installation_tcp_ur)
        self._write_async_progress(-1)
        self._out_int[self._reg_offset] = READY
        # The input registers are the controller's, not the program's: what a client wrote
        # before the upload is what the new program reads first.
        command = self._cycle_inputs.get(f"input_int_register_{self._reg_offset}", 0)
        self._event("program_started", f"{self._program_name} offset {self._reg_offset} command register {command}")

    def _end_program(self, reason: str) -> None:
        """The program stops (stop script, dashboard stop, watchdog, safety): so does the arm."""
        if self._pending_program is not None and reason in ("protective_stop", "emergency_stop"):
            self._pending_program = None
        if not self._program_running and not self._paused:
            return
        self._program_running = False
        self._paused = False
        self._executing_cmd = False
        self._sync_wait = None
        self._watchdog = None
        self._speed_thread = False
        if self._async_running:
            self._async_running = False
            self._write_async_progress(-1)
        self.backend.set_force_mode(False)
        if self.backend.is_moving():
            self.backend.stop(self.program_stop_decel_m_s2)
        self._event("program_stopped", reason)

    # ------------------------------------------------------------------ controller tick
    def _aligned_tick_s(self, after_s: float, period_s: float) -> float:
        """The first tick time at or after ``after_s``: just past one of the backend's own time
        steps when it has a grid of this period (``grid_ur()``), else ``after_s``.

        Why: a backend on a time grid shows, at wall time t, its state at the grid instant
        at or before t. Ticking at a fixed phase to that grid, every package would leave the
        same fraction of a period after the instant it shows; a client that times packages
        by their quickest arrival could never see that part of the delay."""
        grid = getattr(self.backend, "grid_ur", None)
        if grid is None:
            return after_s
        grid_period_s, anchor_s = grid()
        if abs(grid_period_s - period_s) > 1e-9:
            return after_s
        k = math.ceil((after_s - anchor_s - _GRID_LEAD_S) / grid_period_s)
        return anchor_s + k * grid_period_s + _GRID_LEAD_S

    def _tick_loop(self) -> None:
        period = 1.0 / self.tick_hz
        next_t = self._aligned_tick_s(time.monotonic(), period)
        end_t = time.monotonic() + self.lifetime_s
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= end_t:
                self._event("lifetime_expired")
                threading.Thread(target=self.stop, daemon=True).start()
                return
            with self._lock:
                try:
                    self._step(now)
                except Exception:  # noqa: BLE001 — keep the controller alive; the test will see it
                    log.exception("ur-emu %s: controller step failed", self.host)
                snapshot = _Snapshot(self, now)
                due: list[tuple[_RtdeSession, bytes]] = []
                for s in self._sessions:
                    if not s.started or s.closed:
                        continue
                    for r in s.outputs:
                        if now + 1e-4 >= s.next_due_s.get(r.recipe_id, 0.0):
                            s.next_due_s[r.recipe_id] = max(s.next_due_s.get(r.recipe_id, 0.0) + 1.0 / r.frequency_hz,
                                                            now - 0.05)
                            values = {n: snapshot.get(n, t) for n, t in zip(r.names, r.types)}
                            data = r.pack(values)
                            due.append((s, frame(CMD_DATA_PACKAGE, data)))
            for s, data in due:
                self._send(s, data)
            next_t += period
            if next_t < time.monotonic() - 0.1:
                # Fell behind (busy machine): do not burst to catch up.
                next_t = self._aligned_tick_s(time.monotonic(), period)
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def _step(self, now: float) -> None:
        with self._inputs_lock:
            self._cycle_inputs = dict(self._inputs)
        self.backend.advance(now)
        reason = self.backend.protective_stop_requested()
        if reason and self._protective_stop_t_s is None:
            self._enter_protective_stop(now, reason)
        if self._pending_program is not None and now >= self._pending_program[0]:
            text = self._pending_program[1]
            self._pending_program = None
            self._start_program(text, now)
        if not self._program_running:
            return
        if (self._watchdog is not None and now - self._watchdog_last_s > self._watchdog[1]
                and not self._watched_input_waiting()):
            self._event("watchdog_expired", f"{now - self._watchdog_last_s:.3f} s without {self._watchdog[0]}")
            self._end_program("watchdog")
            return
        moving = self.backend.is_moving()
        if self._async_running and not moving:
            self._async_running = False
            self._write_async_progress(-1)
        if self._sync_wait is not None:
            if moving:
                return      # the script's main thread is blocked in movel/stopl
            self._sync_wait = None
            self._out_int[self._reg_offset] = DONE
        self._process_register_command(now)

    def _watched_input_waiting(self) -> bool:
        """True when the connection that writes the watched register has bytes this emulator
        has not read yet: they reached the controller in time, and only this process's own
        threads (sharing one interpreter with the served world) are late to read them. A
        real controller's RTDE server is real-time; its watchdog would have seen them."""
        assert self._watchdog is not None
        owner = self._input_owner.get(self._watchdog[0])
        if owner is None or owner.closed:
            return False
        try:
            readable, _, _ = select.select([owner.sock], [], [], 0.0)
        except (OSError, ValueError):
            return False
        return bool(readable)

    def _process_register_command(self, now: float) -> None:
        off = self._reg_offset
        cmd = int(self._cycle_inputs.get(f"input_int_register_{off}", 0))  # type: ignore[call-overload]
        if cmd in Cmd.REALTIME:
            if not self.commands_seen or self.commands_seen[-1] != cmd:
                self.commands_seen.append(cmd)
            self._execute(cmd, now)
            self._out_int[off] = READY
        elif cmd == Cmd.NO_CMD:
            self._executing_cmd = False
            self._out_int[off] = READY
        elif not self._executing_cmd:
            self._executing_cmd = True
            self.commands_seen.append(cmd)
            self._execute(cmd, now)
            if self._sync_wait is None and self._program_running:
                self._out_int[off] = DONE

    # ------------------------------------------------------------------ register access
    def _in_int(self, index: int) -> int:
        return int(self._cycle_inputs.get(f"input_int_register_{index + self._reg_offset}", 0))  # type: ignore[call-overload]

    def _in_double(self, index: int) -> float:
        return float(self._cycle_inputs.get(f"input_double_register_{index + self._reg_offset}", 0.0))  # type: ignore[arg-type]

    def _in_doubles(self, first: int, count: int) -> np.ndarray:
        return np.array([self._in_double(first + i) for i in range(count)])

    def _write_async_progress(self, value: int) -> None:
        """The async status word: op id (bits 24-30), change count (16-23), running (15), progress (0-14)."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        word = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self._out_int[2 + self._reg_offset] = word

    # ------------------------------------------------------------------ command semantics
    def _execute(self, cmd: int, now: float) -> None:
        b = self.backend
        if self._speed_thread and cmd in Cmd.MOTION_IN_MAIN_OR_MOVE_THREAD:
            # ur_rtde 1.6.5's moveL/moveJ stop only the async move thread (stop_async_move),
            # stopL/stopJ and forceModeStop run stopl/stopj in the main thread: the speed thread still runs
            # speedl, so two threads command the robot.
            self._event("runtime_error", f"command {cmd}: Another thread is already controlling the robot")
            self._end_program("runtime_error")
            return
        if cmd in (Cmd.MOVEL, Cmd.MOVEJ, Cmd.MOVEJ_IK, Cmd.MOVEL_FK):
            target = self._in_doubles(0, 6)
            speed, accel = self._in_double(6), self._in_double(7)
            asynchronous = self._in_int(1) == 1
            if self._async_running:
                self._async_running = False
                self._write_async_progress(-1)
            try:
                if cmd == Cmd.MOVEL:
                    b.move_linear(self._backend_target_ur(target), speed, accel)
                elif cmd == Cmd.MOVEJ:
                    b.move_joint(target, speed, accel)
                else:
                    raise NotImplementedError(f"command {cmd} (IK/FK moves) is not emulated")
            except NotImplementedError as exc:
                self._event("command_unsupported", str(exc))
                return
            if asynchronous:
                self._async_running = True
                self._write_async_progress(0)
            else:
                self._sync_wait = "move"
        elif cmd in (Cmd.STOPL, Cmd.STOPJ):
            decel = self._in_double(0)
            asynchronous = self._in_int(1) == 1
            if self._async_running:
                self._async_running = False
                self._write_async_progress(-1)
            b.stop(decel if decel > 0 else 10.0)
            if asynchronous and b.is_moving():
                self._async_running = True
                self._write_async_progress(0)
            elif b.is_moving():
                self._sync_wait = "stop"
        elif cmd == Cmd.SPEEDL:
            self._speed_thread = True
            b.speed_linear(self._in_doubles(0, 6), self._in_double(6))
        elif cmd == Cmd.SPEED_STOP:
            # kill speed_thrd, then stopl in the main thread: "done" once the arm is at rest.
            self._speed_thread = False
            b.stop(self._in_double(0) if self._in_double(0) > 0 else 10.0)
            if b.is_moving():
                self._sync_wait = "stop"
        elif cmd == Cmd.FORCE_MODE:
            selection = np.array([self._in_int(2 + i) for i in range(6)])
            b.set_force_mode(True, self._in_doubles(0, 6), selection, self._in_doubles(6, 6), self._in_doubles(12, 6))
        elif cmd == Cmd.FORCE_MODE_STOP:
            b.set_force_mode(False)
            b.stop(10.0)
        elif cmd == Cmd.ZERO_FT_SENSOR:
            b.zero_ft_sensor()
        elif cmd == Cmd.SET_WATCHDOG:
            # kickWatchdog() writes NO_CMD into input_int_register_0 (its own recipe): the
            # watchdog watches *updates* of that variable, whatever the value (_handle_rtde).
            min_hz = self._in_double(0)
            if min_hz > 0:
                self._watchdog = (f"input_int_register_{self._reg_offset}", 1.0 / min_hz)
                self._watchdog_last_s = now
                self._event("watchdog_set", f"{min_hz:g} Hz")
        elif cmd == Cmd.PROTECTIVE_STOP:
            self._enter_protective_stop(now, "triggerProtectiveStop")
        elif cmd == Cmd.STOP_SCRIPT:
            self._end_program("stop_script")
        elif cmd == Cmd.SET_TCP:
            self._set_tcp_offset(self._in_doubles(0, 6))
            self._event("tcp_set", " ".join(f"{v:.6g}" for v in self._tcp_offset))
        elif cmd == Cmd.SET_PAYLOAD:
            self._payload_kg = self._in_double(0)
        elif cmd == Cmd.GET_TCP_OFFSET:
            self._out_double[self._reg_offset:self._reg_offset + 6] = self._tcp_offset
        elif cmd == Cmd.IS_STEADY:
            self._out_int[1 + self._reg_offset] = 0 if b.is_moving() else 1
        elif cmd == Cmd.GET_FORWARD_KINEMATICS_DEFAULT:
            self._out_double[self._reg_offset:self._reg_offset + 6] = self._reported_pose_ur(b.tcp_pose_ur())
        elif cmd in Cmd.REALTIME:
            self._event("command_unsupported", f"real-time command {cmd}")
        else:
            self._event("command_unsupported", f"command {cmd}")

    def _enter_protective_stop(self, now: float, reason: str) -> None:
        self.backend.stop(self.protective_stop_decel_m_s2)
        self._protective_stop_t_s = now
        self._end_program("protective_stop")
        self._event("protective_stop", reason)

    # ------------------------------------------------------------------ output values
    def _core_value(self, key: str, now: float) -> object:
        b = self.backend
        if key == "timestamp":
            return self._pose_sample(now)[0] - self._t_boot_s
        if key in ("actual_q", "target_q"):
            return tuple(float(v) for v in b.joints_rad())
        if key in ("actual_TCP_pose", "target_TCP_pose"):
            return tuple(float(v) for v in self._pose_sample(now)[1])
        if key in ("actual_TCP_speed", "target_TCP_speed"):
            return tuple(float(v) for v in b.tcp_speed_ur())
        if key in ("actual_TCP_force", "ft_raw_wrench"):
            return tuple(float(v) for v in b.tcp_force_ur())
        if key == "tcp_force_scalar":
            return float(np.linalg.norm(np.asarray(b.tcp_force_ur())[:3]))
        if key in ("actual_qd", "target_qd"):
            return (0.0,) * 6
        if key == "robot_mode":
            return ROBOT_MODE_POWER_OFF if self._emergency_stop else ROBOT_MODE_RUNNING
        if key in ("safety_mode", "safety_status"):
            if self._emergency_stop:
                return SAFETY_MODE_ROBOT_EMERGENCY_STOP
            return SAFETY_MODE_PROTECTIVE_STOP if self._protective_stop_t_s is not None else SAFETY_MODE_NORMAL
        if key == "robot_status_bits":
            powered = 0 if self._emergency_stop else 1
            return powered | (2 if self._program_running else 0)
        if key == "safety_status_bits":
            if self._emergency_stop:
                return (1 << 6) | (1 << 7)      # robot emergency stopped, emergency stopped
            if self._protective_stop_t_s is not None:
                return 1 << 2
            return 1 << 0                       # normal mode
        if key == "runtime_state":
            return RUNTIME_PLAYING if self._program_running else RUNTIME_STOPPED
        if key in ("speed_scaling", "target_speed_fraction"):
            return 1.0
        if key == "joint_mode":
            return (255,) * 6                   # JOINT_RUNNING_MODE
        if key in ("actual_main_voltage", "actual_robot_voltage"):
            return 48.0
        if key == "payload":
            return self._payload_kg
        if key == "joint_temperatures":
            return (30.0,) * 6
        if key == "actual_execution_time":
            return 0.2
        return 0


def _close_quietly(sock: socket.socket) -> None:
    try:
        sock.close()
    except OSError:
        pass

