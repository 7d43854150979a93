"""The low-level UR link: the real ur_rtde 1.6.5 in a supervised child process.

Why a child process (docs/ur_emulation.md, "Behaviour of ur_rtde 1.6.5"): ur_rtde 1.6.5 can crash its process (segfault)
while reconnecting after a dropped connection, its constructors hold the GIL while they
block on the network, and a blocking call starves the RTDE watchdog. So the library
runs in a ``spawn``-ed child that

- dies with its parent (``prctl(PR_SET_PDEATHSIG, SIGKILL)`` plus a parent-pid check),
- refuses to run unless ``ur_rtde`` is exactly 1.6.5 (its register protocol changes
  between versions),
- connects the dashboard, receive and control interfaces with bounded retries
  (constructor flags passed by keyword: ``flags=``),
- sets the robot-side watchdog (``setWatchdog(min_hz)``) and kicks it ONLY while the
  parent's safety heartbeat (:meth:`URLink.heartbeat`, a shared timestamp) is fresh —
  if the parent dies or hangs, the kicks stop and the control script stops the arm,
- sends only asynchronous or real-time commands (moveL async, stopL async, speedL,
  forceMode), so nothing in it blocks for long,
- reports a lost connection or an unexpected program stop and exits (it never lets
  ur_rtde's own reconnect path run on for long).

The parent side (:class:`URLink`) talks to it over a pipe with a deadline per call.
If the child dies, hangs past the deadline or loses the robot, the parent kills it,
starts a new one (bounded by ``max_restarts``) — whose control script upload replaces
the old program, so the arm is stopped — and reports a :class:`DeviceError`.

Units: ur_rtde's — poses ``[x, y, z, rx, ry, rz]`` in m and rad (rotation vector),
speeds m/s, accelerations m/s^2, base frame. Convert with ``Pose.from_ur``/``to_ur``.
"""
from __future__ import annotations

import collections
import importlib.metadata
import math
import multiprocessing as mp
import multiprocessing.connection
import os
import re
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import DeviceError, DeviceTimeout, ProgramNotRunning
from ..core.process import set_parent_death_signal
from .supervised import await_ready, kill_child

UR_RTDE_VERSION = "1.6.5"

# Safety status bits (RTDE safety_status_bits).
SAFETY_BIT_PROTECTIVE_STOPPED = 2
SAFETY_BIT_EMERGENCY_STOPPED = 7
ROBOT_STATUS_BIT_PROGRAM_RUNNING = 1

# How long a program stop may stay unexplained by the safety bits before it is a fault.
UNEXPLAINED_STOP_GRACE_S = 0.2
# A program stop this soon after the child's kick loop came late is the watchdog's (the link's
# own failure: restarted), not an operator's: the late turn, the watchdog's period and the grace.
LATE_KICK_MEMORY_S = 1.0

# Child operations that write input_int_register_0 (and so also feed the watchdog).
_REGISTER_WRITING_OPS = frozenset({"move_linear", "stop_linear", "speed_linear", "speed_stop", "force_mode",
                                   "force_mode_stop", "zero_ft_sensor", "recover"})

# Child operations on the stop path: their answers carry the child's timestamps (a latency
# breakdown for bench/safety_latency.py; the same monotonic clock in every process).
_STOP_OPS = frozenset({"stop_linear", "speed_stop"})

# The direct stop channel (URLink.stop_now): kind b"L" stopL / b"S" speedStop, a sequence
# number, the deceleration in m/s^2. Raw bytes on a pipe of its own: no pickling, no call
# lock, and the child serves it before any request. The child answers on the same pipe once
# ur_rtde has sent it: the sequence number, a status (1 sent, 0 no program running, -1 the
# library raised) and its timestamps (wait began, woke, read, library called, returned).
_STOP_MESSAGE = struct.Struct(">cId")
_STOP_REPORT = struct.Struct(">Ib5d")
_STOP_REPORT_KEYS = ("child_wait_s", "child_woke_s", "child_recv_s", "child_lib_call_s", "child_lib_return_s")

# What the receive interface streams (few variables keep the 500 Hz stream cheap).
RECEIVE_VARIABLES = ["timestamp", "actual_q", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force",
                     "robot_status_bits", "safety_status_bits", "runtime_state", "robot_mode", "safety_mode"]


@dataclass(frozen=True)
class URLinkConfig:
    """Tunables of the link; every wait below is bounded by one of them.

    ``watchdog_min_hz``: the control script stops the program (and the arm) if the
    watchdog variable is not updated at least this often. ``kick_period_s``: the
    child's kick cycle (must be well below 1/watchdog_min_hz). ``heartbeat_timeout_s``:
    the parent's heartbeat is considered dead after this long. ``call_timeout_s``:
    default deadline of one call to the child. ``connect_attempts``/``connect_backoff_s``:
    bounded connection retries in the child. ``start_timeout_s``: how long the parent
    waits for a new child to be ready. ``max_restarts``: child restarts allowed over the
    link's life. ``unlock_wait_s``: wait after a protective stop before unlocking (a
    controller refuses earlier). ``recovery_attempts``: unlock attempts. ``frequency_hz``:
    RTDE frequency for both interfaces (-1: the controller's default, 500 Hz on e-Series);
    ``control_frequency_hz`` overrides it for the control interface: ur_rtde 1.6.5 sends a
    command only between two packages of that stream, so its period bounds the wait of a stop.
    ``child_lifetime_s``: the child exits by itself after this long (bounded loops).
    ``tcp_offset_ur``: the tool the controller believes in, flange -> TCP (m, rotation
    vector): every pose the link sends (moveL targets) and reads (actual_TCP_pose) is this
    TCP's, so the child sets it on the robot (setTcp) whenever a control script starts —
    at connect and after every re-upload, since a new program starts with the
    installation's TCP — and reads it back.
    """

    watchdog_min_hz: float = 10.0
    kick_period_s: float = 0.02
    heartbeat_timeout_s: float = 0.25
    call_timeout_s: float = 5.0
    connect_attempts: int = 3
    connect_backoff_s: float = 0.5
    start_timeout_s: float = 30.0
    max_restarts: int = 3
    unlock_wait_s: float = 5.0
    recovery_attempts: int = 3
    frequency_hz: float = -1.0
    control_frequency_hz: float | None = None
    child_lifetime_s: float = 24 * 3600.0
    tcp_offset_ur: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class URState:
    """One reading of the arm through the link (ur_rtde units, base frame).

    ``async_progress``: getAsyncOperationProgress — -1 when no asynchronous operation
    runs, >= 0 while one does. ``kicking``: the child is kicking the watchdog (the
    parent's heartbeat is fresh and the program runs). ``t_s``: when the controller
    sampled this state, on the parent's monotonic clock (:class:`RobotClock`), not when
    the parent received it.
    """

    t_s: float
    tcp_pose_ur: np.ndarray
    joints_rad: np.ndarray
    tcp_speed_ur: np.ndarray
    tcp_force_ur: np.ndarray
    robot_status_bits: int
    safety_status_bits: int
    program_running: bool
    protective_stopped: bool
    emergency_stopped: bool
    async_progress: int
    connected: bool
    kicking: bool
    operator_stop: bool = False
    stop_reason: str = ""

    @property
    def tcp_speed_m_s(self) -> float:
        return float(np.linalg.norm(self.tcp_speed_ur[:3]))


class RobotClock:
    """The UR controller's package timestamps (s since its boot) on this process's monotonic clock.

    Why: a pose is only useful with the instant it was measured. The receive stream runs
    at up to 500 Hz (125 Hz on loopback), ur_rtde keeps the latest package, and the
    parent reads it through the child's pipe: stamped on arrival, a pose is 0-10 ms older
    than its stamp, and while the scanner sweeps at 250 mm/s that put the profiles of the
    two sweep headings ~1.6 mm apart (measured on the loopback cell: median lag 6.5 ms).

    The offset local - robot is bounded above by every reading (arrival - timestamp: a
    package cannot arrive before it was sent), so the estimate is the smallest such
    difference, allowed to grow by ``max_drift`` (s/s) since it was last lowered, for the
    two clocks' rate difference. A timestamp that goes back (a controller reboot, another
    controller) starts over. The error is the quickest reading's transit, well under a ms
    on a local network.
    """

    def __init__(self, max_drift: float = 2e-4) -> None:
        self.max_drift = float(max_drift)
        self._offset_s: float | None = None
        self._at_local_s = 0.0
        self._last_robot_s = -math.inf
        self._last_local_s: float | None = None

    def to_local_s(self, robot_s: float, arrival_local_s: float) -> float:
        """The local time of controller time ``robot_s``, given a package read at ``arrival_local_s``."""
        sample = arrival_local_s - robot_s
        if self._offset_s is None or robot_s < self._last_robot_s:
            self._offset_s, self._at_local_s = sample, arrival_local_s
        else:
            relaxed = self._offset_s + self.max_drift * max(0.0, arrival_local_s - self._at_local_s)
            if sample <= relaxed:
                self._offset_s, self._at_local_s = sample, arrival_local_s
            else:
                self._offset_s, self._at_local_s = relaxed, arrival_local_s
        # Never back in time for a later package (a quicker reading lowers the offset by a
        # fraction of a ms): the controller interpolates poses over these times.
        if robot_s >= self._last_robot_s and self._last_local_s is not None:
            local = max(robot_s + self._offset_s, self._last_local_s)
        else:
            local = robot_s + self._offset_s
        self._last_robot_s, self._last_local_s = robot_s, local
        return local

    @property
    def offset_s(self) -> float | None:
        """Local minus controller time (s), or None before the first reading."""
        return self._offset_s


@dataclass(frozen=True)
class LinkFault:
    """A failure of the link the parent noticed (the child was killed/restarted after it)."""

    t_s: float
    kind: str        # child_died, call_timeout, connection_lost, program_stopped, start_failed
    message: str


@dataclass
class LinkMove:
    """An asynchronous moveL in flight: fraction done from the measured pose."""

    start_pose_ur: np.ndarray
    target_pose_ur: np.ndarray
    t_start_s: float

    def fraction_done(self, state: URState) -> float:
        total = float(np.linalg.norm(self.target_pose_ur[:3] - self.start_pose_ur[:3]))
        if total < 1e-9:
            return 1.0 if state.async_progress < 0 else 0.0
        left = float(np.linalg.norm(self.target_pose_ur[:3] - state.tcp_pose_ur[:3]))
        return float(np.clip(1.0 - left / total, 0.0, 1.0))

    def is_running(self, state: URState) -> bool:
        """True while the controller still runs this move (its async operation)."""
        return state.async_progress >= 0


# ====================================================================== dashboard replies
_MODEL_RE = re.compile(r"^UR\d{1,2}e?$")
_SERIAL_RE = re.compile(r"^[0-9A-Za-z-]{4,32}$")
# ur_rtde's polyscopeVersion() returns the version it parsed from "URSoftware 5.11.1.108318 (...)".
_POLYSCOPE_RE = re.compile(r"^(?:URSoftware )?(\d+\.\d+\.\d+(?:\.\d+)?)(?: \(.*\))?$")
_PROGRAM_STATE_RE = re.compile(r"^(STOPPED|PLAYING|PAUSED)(?: (.*))?$")


def parse_dashboard_identity(key: str, reply: str) -> str:
    """A dashboard identity reply (``polyscope``: "5.11.1.108318" as ur_rtde parses it, or the
    raw "URSoftware 5.11.1.108318 (Mar 22 2021)"; ``serial``; ``model``: "UR5"), checked; DeviceError for anything a UR controller does not
    answer (e.g. "could not understand: 'get robot model'")."""
    patterns = {"polyscope": _POLYSCOPE_RE, "serial": _SERIAL_RE, "model": _MODEL_RE}
    match = patterns[key].match(reply)
    if match is None:
        raise DeviceError(f"the robot's dashboard answered the {key} query with {reply[:120]!r}, which is not "
                          f"what a UR controller answers: is this a UR, and does it run PolyScope 5?")
    return match.group(1) if key == "polyscope" else reply


def parse_program_state(reply: str) -> str:
    """The dashboard's ``programState`` ("PAUSED <name>") as "program state PAUSED (<name>)"."""
    match = _PROGRAM_STATE_RE.match(reply)
    if match is None:
        raise DeviceError(f"the robot's dashboard answered programState with {reply[:120]!r}")
    name = match.group(2)
    return f"program state {match.group(1)}" + (f" ({name})" if name else "")


# ====================================================================== child side
def check_ur_rtde_version() -> str:
    """The installed ur_rtde version; raises DeviceError unless it is exactly 1.6.5."""
    try:
        version = importlib.metadata.version("ur_rtde")
    except importlib.metadata.PackageNotFoundError as exc:
        raise DeviceError("ur_rtde is not installed (ur-rtde==1.6.5 is required)") from exc
    if version != UR_RTDE_VERSION:
        raise DeviceError(f"ur_rtde {version} is installed; the UR link needs exactly {UR_RTDE_VERSION} "
                          "(its register protocol changes between versions)")
    return version


class _ChildLink:
    """Runs inside the child: owns the three ur_rtde interfaces and the kick loop."""

    def __init__(self, conn: Any, host: str, cfg: URLinkConfig, heartbeat: Any, parent_pid: int,
                 stop_conn: Any = None) -> None:
        self.conn = conn
        self.stop_conn = stop_conn
        self.host = host
        self.cfg = cfg
        self.heartbeat = heartbeat
        self.parent_pid = parent_pid
        self.db: Any = None
        self.rcv: Any = None
        self.ctl: Any = None
        self.pstop_seen_s: float | None = None
        self.program_expected = False
        self.unexplained_since_s: float | None = None
        self.kicking = False
        self.stop_reason = ""            # an operator's stop, in the controller's words (op_state)
        self.late_at_s = -math.inf       # when a turn of the kick loop last came late
        self.last_write_s = 0.0
        self.t_lib_call_s = 0.0          # when the last stop op entered ur_rtde
        self.t_wait_s = self.t_woke_s = 0.0   # the loop's last wait for requests began / ended

    # -- setup
    def connect(self) -> None:
        import dashboard_client
        import rtde_control
        import rtde_receive
        last: Exception | None = None
        for attempt in range(self.cfg.connect_attempts):
            try:
                self.db = dashboard_client.DashboardClient(self.host)
                self.db.connect()
                self.rcv = rtde_receive.RTDEReceiveInterface(self.host, frequency=self.cfg.frequency_hz,
                                                             variables=RECEIVE_VARIABLES)
                control_hz = self.cfg.frequency_hz if self.cfg.control_frequency_hz is None \
                    else self.cfg.control_frequency_hz
                self.ctl = rtde_control.RTDEControlInterface(
                    self.host, frequency=control_hz,
                    flags=rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
                break
            except Exception as exc:  # noqa: BLE001 — ur_rtde raises RuntimeError and others
                last = exc
                time.sleep(self.cfg.connect_backoff_s * (attempt + 1))
        else:
            raise DeviceError(f"could not connect to the UR controller at {self.host} after "
                              f"{self.cfg.connect_attempts} attempts: {last}")
        self._arm_watchdog()

    def _arm_watchdog(self) -> None:
        """After a control script starts: the believed TCP, then the watchdog."""
        self._set_tcp()
        if not self.ctl.setWatchdog(self.cfg.watchdog_min_hz):
            raise DeviceError("setWatchdog was refused (control script not running?)")
        self.program_expected = True

    def _set_tcp(self, tolerance: float = 1e-6) -> None:
        """setTcp(the believed tool) and read it back: a robot moving another TCP would put
        the probe tip where the controller never planned it."""
        wanted = [float(v) for v in self.cfg.tcp_offset_ur]
        if not self.ctl.setTcp(wanted):
            raise DeviceError("setTcp was refused (control script not running?)")
        got = [float(v) for v in self.ctl.getTCPOffset()]
        if len(got) != 6 or max(abs(a - b) for a, b in zip(got, wanted)) > tolerance:
            raise DeviceError(f"the robot's TCP offset reads {got} after setTcp({wanted})")

    def identity(self) -> dict[str, str]:
        """Who the robot is, from the dashboard; a reply that is not what a UR answers is a
        DeviceError (it must never be stored as the robot's identity)."""
        out = {"host": self.host, "ur_rtde": UR_RTDE_VERSION}
        for key, call in (("polyscope", "polyscopeVersion"), ("serial", "getSerialNumber"),
                          ("model", "getRobotModel")):
            try:
                reply = str(getattr(self.db, call)()).strip()
            except Exception as exc:  # noqa: BLE001 — ur_rtde raises RuntimeError and others
                raise DeviceError(f"the robot's dashboard did not answer {call}: {exc}") from exc
            out[key] = parse_dashboard_identity(key, reply)
        return out

    # -- loop
    def parent_alive(self) -> bool:
        return os.getppid() == self.parent_pid

    def heartbeat_fresh(self) -> bool:
        return time.monotonic() - float(self.heartbeat.value) <= self.cfg.heartbeat_timeout_s

    def _program_stop_reason(self) -> str:
        """Why the program stopped, as the dashboard tells it (its program state, checked)."""
        try:
            state = parse_program_state(str(self.db.programState()).strip())
        except (DeviceError, RuntimeError) as exc:
            state = f"program state unknown: {exc}"
        return (f"the robot program was stopped at the pendant or the dashboard, or halted on a script "
                f"error (no safety stop; {state})")

    def run(self) -> int:
        end_s = time.monotonic() + self.cfg.child_lifetime_s
        # A loop turn later than this may have let the watchdog's period pass without a kick.
        late_limit_s = 0.5 / self.cfg.watchdog_min_hz
        last_turn_s = time.monotonic()
        while time.monotonic() < end_s:
            now = time.monotonic()
            if now - last_turn_s > late_limit_s:
                self.late_at_s = now
            last_turn_s = now
            if not self.parent_alive():
                return 0
            if not (self.ctl.isConnected() and self.rcv.isConnected()):
                self.conn.send(("fault", "connection_lost", "RTDE connection to the controller lost"))
                return 3
            bits = int(self.rcv.getSafetyStatusBits())
            protective = bool(bits >> SAFETY_BIT_PROTECTIVE_STOPPED & 1)
            emergency = bool(bits >> SAFETY_BIT_EMERGENCY_STOPPED & 1)
            if protective and self.pstop_seen_s is None:
                self.pstop_seen_s = time.monotonic()
            elif not protective:
                self.pstop_seen_s = None
            running = bool(self.ctl.isProgramRunning())
            if self.program_expected and not running:
                now = time.monotonic()
                if protective or emergency:
                    self.program_expected = False          # a safety stop: recover() handles it
                    self.unexplained_since_s = None
                elif self.unexplained_since_s is None:
                    # The receive stream may lag the control stream by a packet or two:
                    # give the safety bits a moment to explain the stop.
                    self.unexplained_since_s = now
                elif now - self.unexplained_since_s > UNEXPLAINED_STOP_GRACE_S:
                    # Neither safety stop explains it. With a stale heartbeat it is our own
                    # watchdog (the hardware process hung); with the link up and the heartbeat
                    # fresh, someone stopped or paused the program at the pendant or the
                    # dashboard (or it halted on a script error): the arm is the operator's
                    # now. Reported, and nothing is re-uploaded until asked (recover()).
                    self.program_expected = False
                    self.unexplained_since_s = None
                    if not self.heartbeat_fresh():
                        self.conn.send(("fault", "program_stopped", "the control program stopped (watchdog: the "
                                        "safety heartbeat was stale)"))
                    elif now - self.late_at_s < LATE_KICK_MEMORY_S:
                        # This process's own kicks came late (it was starved): the watchdog
                        # stopped the program, the link's failure, not an operator's.
                        self.conn.send(("fault", "connection_lost", "the control program stopped (watchdog: the "
                                        "link's kicks came late)"))
                        return 3
                    else:
                        self.stop_reason = self._program_stop_reason()
                        self.conn.send(("fault", "operator_stop", self.stop_reason))
            else:
                self.unexplained_since_s = None
            self.kicking = running and self.heartbeat_fresh()
            # input_int_register_0 is a single mailbox read once per controller cycle: a kick
            # (NO_CMD) right after a real-time command (speedL, forceMode) would overwrite it
            # unread. Commands update the watched register too, so they count as kicks.
            if self.kicking and time.monotonic() - self.last_write_s >= self.cfg.kick_period_s:
                self.ctl.kickWatchdog()
                self.last_write_s = time.monotonic()
            if self.stop_conn is not None:
                waitables = [self.stop_conn, self.conn]
                self.t_wait_s = time.monotonic()
                ready = multiprocessing.connection.wait(waitables, self.cfg.kick_period_s)
                self.t_woke_s = time.monotonic()
                if self.stop_conn in ready and not self._serve_stops():
                    return 0
                request = self.conn in ready and self.conn.poll(0)
            else:
                request = self.conn.poll(self.cfg.kick_period_s)
            if request:
                # A stop written meanwhile goes first: it must not wait behind this request.
                if self.stop_conn is not None and self.stop_conn.poll(0) and not self._serve_stops():
                    return 0
                try:
                    msg = self.conn.recv()
                except EOFError:
                    return 0
                t_recv = time.monotonic()
                if msg[0] == "close":
                    self.close()
                    return 0
                if msg[0] == "call":
                    self._answer(msg[1], msg[2], msg[3], t_recv)
        return 0

    def _serve_stops(self) -> bool:
        """Execute every stop waiting on the stop pipe, each at once; report each with its
        timestamps. False if the parent closed the pipe."""
        while self.stop_conn.poll(0):
            try:
                raw = self.stop_conn.recv_bytes()
            except (EOFError, OSError):
                return False
            t_recv = time.monotonic()
            kind, seq, decel = _STOP_MESSAGE.unpack(raw)
            status = 0
            t_lib = t_recv
            try:
                if self.ctl.isProgramRunning():
                    t_lib = time.monotonic()
                    # Status 1 = the command went out. (ur_rtde 1.6.5's asynchronous stopL
                    # returns False even when the controller took it; the old call path ignored it.)
                    if kind == b"L":
                        self.ctl.stopL(decel, True)
                    else:
                        self.ctl.speedStop(decel)
                    status = 1
            except Exception:  # noqa: BLE001 — reported as -1; the loop notices a lost connection
                status = -1
            self.last_write_s = time.monotonic()
            try:
                self.stop_conn.send_bytes(_STOP_REPORT.pack(seq, status, self.t_wait_s, self.t_woke_s, t_recv, t_lib,
                                                            self.last_write_s))
            except OSError:
                return False
        return True

    def _answer(self, rid: int, name: str, args: tuple[Any, ...], t_recv_s: float = 0.0) -> None:
        try:
            result = getattr(self, "op_" + name)(*args)
            if name in _STOP_OPS:
                stamps = {"child_recv_s": t_recv_s, "child_lib_call_s": self.t_lib_call_s,
                          "child_lib_return_s": time.monotonic()}
                self.conn.send(("ok", rid, result, stamps))
            else:
                self.conn.send(("ok", rid, result))
        except ProgramNotRunning as exc:
            self.conn.send(("not_running", rid, str(exc)))
        except Exception as exc:  # noqa: BLE001 — every failure goes back to the parent
            self.conn.send(("err", rid, f"{type(exc).__name__}: {exc}"))
        finally:
            if name in _REGISTER_WRITING_OPS:
                self.last_write_s = time.monotonic()

    def close(self) -> None:
        for obj, method in ((self.ctl, "stopScript"), (self.ctl, "disconnect"), (self.rcv, "disconnect"),
                            (self.db, "disconnect")):
            try:
                if obj is not None:
                    getattr(obj, method)()
            except Exception:  # noqa: BLE001 — closing is best effort
                pass

    # -- operations (each returns plain data)
    def _require_program(self) -> None:
        if not self.ctl.isProgramRunning():
            raise ProgramNotRunning("the control program is not running (a protective stop, an e-stop, the "
                                    "watchdog or an operator's stop)")

    def op_identity(self) -> dict[str, str]:
        return self.identity()

    def op_state(self) -> dict[str, Any]:
        bits = int(self.rcv.getSafetyStatusBits())
        status = int(self.rcv.getRobotStatus())
        # The controller's timestamp of the package the pose comes from. ur_rtde's getters
        # each read the latest package: a package landing between them would pair a pose with
        # the next package's time, so read the time on both sides and retry (bounded).
        for _ in range(3):
            # Read here, not on the parent's receipt: the reply's trip through the pipe is
            # no part of the package's age (time.monotonic is one clock for all processes).
            read_s = time.monotonic()
            stamp_s = float(self.rcv.getTimestamp())
            pose, q = list(self.rcv.getActualTCPPose()), list(self.rcv.getActualQ())
            speed = list(self.rcv.getActualTCPSpeed())
            if float(self.rcv.getTimestamp()) == stamp_s:
                break
        return {
            "pose": pose, "q": q, "speed": speed, "force": list(self.rcv.getActualTCPForce()),
            "robot_timestamp_s": stamp_s, "read_s": read_s,
            "robot_status_bits": status, "safety_status_bits": bits,
            "program_running": bool(self.ctl.isProgramRunning()),
            "protective": bool(self.rcv.isProtectiveStopped()), "emergency": bool(self.rcv.isEmergencyStopped()),
            "async_progress": int(self.ctl.getAsyncOperationProgress()),
            "connected": bool(self.ctl.isConnected() and self.rcv.isConnected()), "kicking": self.kicking,
            "stop_reason": self.stop_reason,
        }

    def op_move_linear(self, pose_ur: list[float], speed_m_s: float, accel_m_s2: float) -> bool:
        self._require_program()
        if not self.ctl.moveL(list(pose_ur), float(speed_m_s), float(accel_m_s2), True):
            raise DeviceError("moveL was refused by the controller")
        return True

    def op_stop_linear(self, decel_m_s2: float) -> bool:
        if self.ctl.isProgramRunning():
            self.t_lib_call_s = time.monotonic()
            self.ctl.stopL(float(decel_m_s2), True)
        return True

    def op_speed_linear(self, xd: list[float], accel_m_s2: float) -> bool:
        self._require_program()
        return bool(self.ctl.speedL(list(xd), float(accel_m_s2), 0.0))

    def op_speed_stop(self, decel_m_s2: float) -> bool:
        if self.ctl.isProgramRunning():
            self.t_lib_call_s = time.monotonic()
            self.ctl.speedStop(float(decel_m_s2))
        return True

    def op_force_mode(self, task_frame: list[float], selection: list[int], wrench: list[float], mode: int,
                      limits: list[float]) -> bool:
        self._require_program()
        return bool(self.ctl.forceMode(list(task_frame), [int(v) for v in selection], list(wrench), int(mode),
                                       list(limits)))

    def op_force_mode_stop(self) -> bool:
        self._require_program()
        return bool(self.ctl.forceModeStop())

    def op_zero_ft_sensor(self) -> bool:
        self._require_program()
        return bool(self.ctl.zeroFtSensor())

    def op_recover(self) -> dict[str, Any]:
        """Bounded protective-stop recovery; never touches an emergency stop."""
        if self.rcv.isEmergencyStopped():
            return {"ok": False, "reason": "emergency stop: only an operator can release it"}
        attempts = 0
        if self.rcv.isProtectiveStopped():
            seen = self.pstop_seen_s if self.pstop_seen_s is not None else time.monotonic()
            # A controller refuses the unlock for ~5 s after the stop; waiting is bounded.
            while time.monotonic() - seen < self.cfg.unlock_wait_s:
                if not self.parent_alive():
                    return {"ok": False, "reason": "parent died"}
                time.sleep(0.05)
            last = ""
            for attempts in range(1, self.cfg.recovery_attempts + 1):
                try:
                    self.db.unlockProtectiveStop()
                    break
                except Exception as exc:  # noqa: BLE001 — refused: wait and retry
                    last = str(exc)
                    time.sleep(1.0)
            else:
                return {"ok": False, "reason": f"unlock refused {attempts} times: {last}", "attempts": attempts}
            self.db.closeSafetyPopup()
            deadline = time.monotonic() + 2.0
            while self.rcv.isProtectiveStopped() and time.monotonic() < deadline:
                time.sleep(0.01)
            if self.rcv.isProtectiveStopped():
                return {"ok": False, "reason": "still protective-stopped after unlocking", "attempts": attempts}
        if not self.ctl.isProgramRunning():
            # The command register keeps its value across program restarts: a script uploaded
            # now would run the last command again (a speedL replayed drives the arm where the
            # force loop last sent it). ur_rtde clears it before its first upload only; here
            # kickWatchdog writes NO_CMD into it (it is sent with no program running too).
            self.ctl.kickWatchdog()
            self.ctl.reuploadScript()
            deadline = time.monotonic() + 5.0
            while not self.ctl.isProgramRunning() and time.monotonic() < deadline:
                time.sleep(0.01)
            if not self.ctl.isProgramRunning():
                return {"ok": False, "reason": "the control script did not start", "attempts": attempts}
            self._arm_watchdog()
            self.stop_reason = ""
        # Re-seed from where the arm actually is: the caller plans from this pose.
        return {"ok": True, "pose": list(self.rcv.getActualTCPPose()), "q": list(self.rcv.getActualQ()),
                "attempts": attempts}

    def op_debug_sleep(self, seconds: float) -> bool:
        """Block the child (as a hung ur_rtde call would): used to test the call deadline."""
        time.sleep(float(seconds))
        return True


def _child_main(conn: Any, host: str, cfg: URLinkConfig, heartbeat: Any, parent_pid: int,
                stop_conn: Any = None) -> None:
    """Entry point of the child process (spawned)."""
    set_parent_death_signal()
    if os.getppid() != parent_pid:     # the parent died before prctl took effect
        os._exit(0)
    link: _ChildLink | None = None
    try:
        check_ur_rtde_version()
        link = _ChildLink(conn, host, cfg, heartbeat, parent_pid, stop_conn)
        link.connect()
        conn.send(("ready", link.identity()))
    except Exception as exc:  # noqa: BLE001 — report why, then exit
        try:
            # A failed start leaves no control script running (it would run on, unsupervised:
            # e.g. after setTcp read back wrong, a script holding a TCP nobody planned with).
            if link is not None:
                link.close()
            conn.send(("fatal", f"{type(exc).__name__}: {exc}"))
        finally:
            os._exit(2)
    code = link.run()
    conn.close()
    # os._exit: skip ur_rtde's destructors, which may block on a dead connection.
    os._exit(code)


# ====================================================================== parent side
class URLink:
    """The supervised ur_rtde link to one UR controller at ``host``.

    ``start()`` spawns the child and waits until it is connected with the watchdog
    armed. Call :meth:`heartbeat` from the safety path at least every
    ``heartbeat_timeout_s``; the child kicks the robot's watchdog only while it does.
    Every other method is a call to the child with a deadline; a failure raises
    :class:`DeviceError` after the child has been killed and restarted (the restart
    replaces the control program, so the arm stops).
    """

    def __init__(self, host: str, config: URLinkConfig | None = None) -> None:
        self.host = host
        self.cfg = config or URLinkConfig()
        self._ctx = mp.get_context("spawn")
        self._heartbeat = self._ctx.Value("d", time.monotonic(), lock=False)
        self._lock = threading.RLock()
        self._proc: Any = None
        self._conn: Any = None
        self._rid = 0
        self._closing = False
        self._dead_reason: str | None = None
        self._unreported: list[LinkFault] = []
        self.faults: list[LinkFault] = []
        self.restarts = 0
        self.identity_info: dict[str, str] = {}
        self._supervisor: threading.Thread | None = None
        self._stop_supervisor = threading.Event()
        # Monotonic stamps of the last stop call (lock taken, sent, answered, the child's).
        self.last_stop_timing: dict[str, Any] = {}
        # The direct stop channel: its pipe (replaced with every child), a sequence number,
        # and the child's reports of the latest stops (seq -> timestamps, ok, status).
        self._stop_pipe: Any = None
        self._stop_lock = threading.Lock()
        self._stop_seq = 0
        self.last_stop_sent_s = 0.0
        self.stop_reports: collections.OrderedDict[int, dict[str, Any]] = collections.OrderedDict()
        # Maps the controller's package timestamps onto this process's clock (URState.t_s).
        self.robot_clock = RobotClock()

    # -- lifecycle
    def start(self) -> "URLink":
        with self._lock:
            self._spawn()
        self._supervisor = threading.Thread(target=self._supervise, name=f"urlink-supervisor-{self.host}",
                                            daemon=True)
        self._supervisor.start()
        return self

    def close(self, timeout_s: float = 3.0) -> None:
        """Stop the control script, close the child, join the supervisor (bounded)."""
        self._closing = True
        self._stop_supervisor.set()
        with self._lock:
            if self._conn is not None and self._proc is not None and self._proc.is_alive():
                try:
                    self._conn.send(("close",))
                except OSError:
                    pass
                self._proc.join(timeout_s)
            self._kill_child()
        if self._supervisor is not None and self._supervisor is not threading.current_thread():
            self._supervisor.join(timeout_s)

    def __enter__(self) -> "URLink":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def child_pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def alive(self) -> bool:
        return self._dead_reason is None and self._proc is not None and self._proc.is_alive()

    def heartbeat(self) -> None:
        """The parent's safety path is alive (cheap: one shared-memory store)."""
        self._heartbeat.value = time.monotonic()

    # -- commands
    def identity(self) -> dict[str, str]:
        return dict(self.identity_info)

    def state(self) -> URState:
        d = self._call("state")
        t_s = self.robot_clock.to_local_s(float(d["robot_timestamp_s"]), float(d["read_s"]))
        return URState(t_s, np.asarray(d["pose"], dtype=float), np.asarray(d["q"], dtype=float),
                       np.asarray(d["speed"], dtype=float), np.asarray(d["force"], dtype=float),
                       int(d["robot_status_bits"]), int(d["safety_status_bits"]), bool(d["program_running"]),
                       bool(d["protective"]), bool(d["emergency"]), int(d["async_progress"]),
                       bool(d["connected"]), bool(d["kicking"]), bool(d["stop_reason"]), str(d["stop_reason"]))

    def move_linear(self, pose_ur: "np.ndarray | list[float]", speed_m_s: float, accel_m_s2: float) -> LinkMove:
        """Start an asynchronous moveL; returns once the controller has accepted it."""
        start = self.state().tcp_pose_ur
        target = np.asarray(pose_ur, dtype=float).reshape(6)
        self._call("move_linear", [float(v) for v in target], float(speed_m_s), float(accel_m_s2))
        return LinkMove(start, target, time.monotonic())

    def stop_linear(self, decel_m_s2: float = 10.0) -> None:
        """stopL (asynchronous on the controller: returns at once, the arm decelerates)."""
        self._call("stop_linear", float(decel_m_s2))

    def speed_linear(self, xd: "np.ndarray | list[float]", accel_m_s2: float) -> None:
        self._call("speed_linear", [float(v) for v in np.asarray(xd, dtype=float).reshape(6)], float(accel_m_s2))

    def speed_stop(self, decel_m_s2: float = 10.0) -> None:
        self._call("speed_stop", float(decel_m_s2))

    def stop_now(self, linear: bool, decel_m_s2: float, wait_s: float = 0.05) -> int:
        """Stop the arm by the direct channel: stopL (``linear``) or speedStop, written to the
        child's stop pipe without the call lock; the child serves it before any queued request.

        Then waits up to ``wait_s`` for the child's report that ur_rtde has sent it (lands in
        :attr:`stop_reports` under the returned sequence number). Waiting is also what gets
        the stop out fast on a busy computer: this thread gives up its CPU to the child.
        Raises DeviceError if the pipe is gone (the child died: its restart replaces the
        program, which stops the arm).
        """
        with self._stop_lock:
            self._stop_seq = (self._stop_seq + 1) % (1 << 32)
            seq = self._stop_seq
            pipe = self._stop_pipe
            if pipe is None:
                raise DeviceError(f"UR link to {self.host} has no child to stop")
            try:
                pipe.send_bytes(_STOP_MESSAGE.pack(b"L" if linear else b"S", seq, float(decel_m_s2)))
                self.last_stop_sent_s = time.monotonic()
                deadline = time.monotonic() + wait_s
                while True:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or not pipe.poll(remaining):
                        break
                    rseq, status, *stamps = _STOP_REPORT.unpack(pipe.recv_bytes())
                    self.stop_reports[rseq] = dict(zip(_STOP_REPORT_KEYS, stamps), ok=status == 1, status=status)
                    while len(self.stop_reports) > 1000:
                        self.stop_reports.popitem(last=False)
                    if rseq == seq:
                        break
            except (OSError, ValueError, EOFError) as exc:
                raise DeviceError(f"UR link to {self.host}: the stop pipe broke: {exc}") from exc
        return seq

    def force_mode(self, task_frame_ur: "np.ndarray | list[float]", selection: "list[int]",
                   wrench: "np.ndarray | list[float]", mode: int, limits: "np.ndarray | list[float]") -> None:
        self._call("force_mode", [float(v) for v in task_frame_ur], [int(v) for v in selection],
                   [float(v) for v in wrench], int(mode), [float(v) for v in limits])

    def force_mode_stop(self) -> None:
        self._call("force_mode_stop")

    def zero_ft_sensor(self) -> None:
        self._call("zero_ft_sensor")

    def recover_protective_stop(self) -> dict[str, Any]:
        """Bounded recovery: wait >= unlock_wait_s after the stop, unlock, close the popup,
        re-upload the control script, re-arm the watchdog; returns ``{"ok", "pose", ...}``
        with the measured pose to re-seed from. Never clears an emergency stop."""
        timeout = self.cfg.unlock_wait_s + self.cfg.recovery_attempts * 2.0 + 10.0
        return dict(self._call("recover", timeout_s=timeout))

    def take_faults(self) -> list[LinkFault]:
        """Faults noticed since the last call (also raised once by the next command)."""
        with self._lock:
            out, self._unreported = self._unreported, []
        return out

    # -- machinery
    def _spawn(self) -> None:
        parent_conn, child_conn = self._ctx.Pipe(duplex=True)
        stop_child, stop_parent = self._ctx.Pipe(duplex=True)
        self.heartbeat()
        proc = self._ctx.Process(target=_child_main, name=f"urlink-{self.host}",
                                 args=(child_conn, self.host, self.cfg, self._heartbeat, os.getpid(), stop_child),
                                 daemon=True)
        proc.start()
        child_conn.close()
        stop_child.close()
        self._proc, self._conn = proc, parent_conn
        with self._stop_lock:
            self._stop_pipe = stop_parent
        try:
            self.identity_info = await_ready(proc, parent_conn, self.cfg.start_timeout_s, f"UR link to {self.host}")
        except DeviceError:
            self._kill_child()
            raise

    def _kill_child(self) -> None:
        kill_child(self._proc, self._conn, 2.0)
        self._conn = None
        with self._stop_lock:
            writer, self._stop_pipe = self._stop_pipe, None
        if writer is not None:
            try:
                writer.close()
            except OSError:
                pass

    def _fault(self, kind: str, message: str, reported: bool) -> LinkFault:
        """Record a fault, kill the child and start a new one (bounded)."""
        fault = LinkFault(time.monotonic(), kind, message)
        self.faults.append(fault)
        if not reported:
            self._unreported.append(fault)
        self._kill_child()
        if self._closing:
            return fault
        if self.restarts >= self.cfg.max_restarts:
            self._dead_reason = f"{kind}: {message}; gave up after {self.restarts} restarts"
            return fault
        self.restarts += 1
        try:
            self._spawn()
        except DeviceError as exc:
            self._dead_reason = f"restart failed: {exc}"
        return fault

    def _handle_unsolicited(self, msg: tuple[Any, ...]) -> None:
        if msg[0] == "fault":
            # connection_lost: the child exits; program_stopped: it stays, waiting for recover();
            # operator_stop: it stays, and the state says so (no error: the operator has the arm).
            if msg[1] == "operator_stop":
                self.faults.append(LinkFault(time.monotonic(), msg[1], msg[2]))
            elif msg[1] == "program_stopped":
                fault = LinkFault(time.monotonic(), msg[1], msg[2])
                self.faults.append(fault)
                self._unreported.append(fault)
            else:
                self._fault(str(msg[1]), str(msg[2]), reported=False)

    def _raise_unreported(self) -> None:
        if self._unreported:
            faults, self._unreported = self._unreported, []
            raise DeviceError("UR link fault: " + "; ".join(f"{f.kind}: {f.message}" for f in faults))

    def _call(self, name: str, *args: Any, timeout_s: float | None = None) -> Any:
        t_call = time.monotonic()
        with self._lock:
            timing: dict[str, Any] = {"t_call_s": t_call, "t_locked_s": time.monotonic()}
            if name in _STOP_OPS:
                self.last_stop_timing = timing
            self._raise_unreported()
            if self._dead_reason is not None:
                raise DeviceError(f"UR link to {self.host} is down: {self._dead_reason}")
            if self._conn is None:
                raise DeviceError(f"UR link to {self.host} is not started")
            self._rid += 1
            rid = self._rid
            try:
                self._conn.send(("call", rid, name, args))
                timing["t_sent_s"] = time.monotonic()
            except OSError as exc:
                self._fault("child_died", f"pipe to the child broke: {exc}", reported=True)
                raise DeviceError(f"UR link child died during {name}; restarted, arm stopped") from exc
            deadline = time.monotonic() + (self.cfg.call_timeout_s if timeout_s is None else timeout_s)
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._fault("call_timeout", f"{name} did not answer in time", reported=True)
                    raise DeviceTimeout(f"UR link call {name} hung; child killed and restarted, arm stopped")
                try:
                    ready = self._conn.poll(min(remaining, 0.05))
                    msg = self._conn.recv() if ready else None
                except (EOFError, OSError):
                    msg, ready = None, False
                    if self._proc is not None:
                        self._proc.join(0.5)
                if msg is None:
                    if self._proc is None or not self._proc.is_alive():
                        code = None if self._proc is None else self._proc.exitcode
                        self._fault("child_died", f"child exited (code {code}) during {name}", reported=True)
                        raise DeviceError(f"UR link child died during {name} (code {code}); restarted, arm stopped")
                    continue
                if msg[0] == "ok" and msg[1] == rid:
                    timing["t_answer_s"] = time.monotonic()
                    if len(msg) > 3:
                        timing.update(msg[3])
                    return msg[2]
                if msg[0] == "err" and msg[1] == rid:
                    raise DeviceError(f"UR {name} failed: {msg[2]}")
                if msg[0] == "not_running" and msg[1] == rid:
                    raise ProgramNotRunning(f"UR {name}: {msg[2]}")
                self._handle_unsolicited(msg)
                if self._conn is None or (self._proc is not None and not self._proc.is_alive()):
                    self._raise_unreported()
                    raise DeviceError(f"UR link lost during {name}")

    def _supervise(self) -> None:
        """Notice a dead child or an unsolicited fault while no call is in flight."""
        while not self._stop_supervisor.wait(0.05):
            if not self._lock.acquire(timeout=0.01):
                continue
            try:
                if self._closing or self._dead_reason is not None:
                    continue
                # Read what the child said before it went (e.g. "connection_lost").
                proc = self._proc
                try:
                    while self._conn is not None and self._conn.poll(0):
                        self._handle_unsolicited(self._conn.recv())
                except (EOFError, OSError):
                    pass
                if self._proc is proc and proc is not None and not proc.is_alive():
                    self._fault("child_died", f"child exited (code {proc.exitcode})", reported=False)
            finally:
                self._lock.release()
