"""The hardware process: owns the F/T stream and the arm driver and runs the check-and-stop path.

Why a separate process: the safety path must keep running whatever the
controller does (a long journal fsync, model training, a Python exception, a debugger
stop), and must stop when the controller is gone. So a ``spawn``-ed child — the
hardware process — owns :class:`~.ati_netft.NetFTClient` and :class:`~.ur_link.URLink`
(which itself runs ur_rtde in a supervised grandchild) and has four threads:

- **safety** (:class:`SafetyLoop`): wakes on every RDT datagram (the client's receive
  thread signals it), reads the new samples, runs ``SafetyGuard.check_block`` (vectorised,
  first crossing) and hands the block to the force loop's supervisor
  (:class:`~elastoprobe.controller.core.forceloop.ForceSupervisor`, the same code the simulated
  cell runs): a crossing (unless it belongs to a motion that unloads a latched trip) or a
  contact during a contact search stops the arm AT ONCE (speedStop / stopL), and only
  then is the trip recorded. It also checks for a stale stream. It is the only caller of
  ``URLink.heartbeat()``: the robot's watchdog is kicked only while this loop runs (if it
  hangs, ur_rtde stops kicking and the arm stops).
- **control**: reads the arm's state through the link at ``control_hz`` (121 Hz), follows
  moveL progress and the contact search's distance, and runs the supervisor's force
  regulation once per ``force_loop.period_s`` (the cell's gains), sending its speedL. A
  gate lock orders its speedL against the safety thread's stop: once a motion is marked
  stopped, no later speedL of it can reach the robot.
- **main**: serves the controller's requests (a pipe, one request at a time) and dies
  with its parent: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` plus a parent-pid check.
- the NetFT receive thread (inside the client).

Sample times: the safety path and the controller get the device's sampling instants
(:class:`DeviceTimebase`: sequence number / rate on the client's anchor), not arrival-clamped
ones, so a burst delayed in transit does not fake a force rate.

Threads, not more processes, inside: the stop must be sent by the code that saw the
crossing, without a hop; the GIL switch interval is lowered so a woken safety thread runs
promptly. ur_rtde's own crashes and hangs stay in URLink's grandchild: a crash or a hang
(past the call deadline) kills and restarts it — its new control script replaces the old
program, so the arm stops — and the controller sees a DeviceError once, from ``status()``
or the next command.

The controller side (:class:`HardwareProcess`) gives an :class:`~elastoprobe.controller.core.devices.Arm`
(:class:`HardwareArm`) and a :class:`~elastoprobe.controller.core.devices.ForceTorqueSensor`
(:class:`HardwareFT`: the same blocks the guard checked, forwarded). Every request has a
deadline; if the hardware process dies or hangs it is killed and restarted (bounded) and
the call raises DeviceError.

Units: controller side mm, mm/s, N, base frame (Pose); the link speaks ur_rtde units (m,
rotation vectors); forces in the sensor frame, load ON the tool (WrenchBlock convention).
Times are ``time.monotonic()`` seconds, the same clock in every process (RealClock).
"""
from __future__ import annotations

import atexit
import collections
import multiprocessing as mp
import os
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from ..core.clock import Clock, RealClock
from ..core.devices import ArmStatus, DeviceIdentity, MotionState, Trip, WrenchBlock
from ..core.errors import DeviceError, DeviceTimeout, MotionRefused, ProgramNotRunning
from ..core.forceloop import BlockVerdict, ForceLoopGains, ForceSupervisor, SupervisedMotion
from ..core.geometry import Pose
from ..core.kinematics import inverse, ur5e
from ..core.process import set_parent_death_signal
from ..core.safety import SafetyGuard, SafetyLimits
from .ati_netft import NetFTClient
from .supervised import await_ready, kill_child
from .ur_link import LinkMove, URLink, URLinkConfig, URState
from .ur_primitives import URPrimitives

_ACTIVE = (MotionState.RUNNING,)


# ====================================================================== configuration
@dataclass(frozen=True)
class HardwareConfig:
    """What the hardware process needs (units in the names, base frame).

    ``probe_axis_sensor``: the probe axis in the sensor frame (for the lateral-force limit);
    ``tcp_to_sensor``: the sensor mount (the supervisor maps forces into the base frame with
    it). ``force_loop``: the cell's gains (the simulated cell runs the same).
    ``flange_to_tcp`` (the believed tool) and ``joint_limits_rad`` give the controller-side
    IK; ``flange_to_tcp`` is also the TCP set on the robot (setTcp), whatever
    ``link.tcp_offset_ur`` says: poses go to and come from the arm as this TCP's.
    """

    robot_host: str
    ft_host: str
    limits: SafetyLimits
    rdt_port: int = 49152
    calinfo_port: int = 49151
    ft_rate_hz: float = 1000.0
    probe_axis_sensor: tuple[float, float, float] = (0.0, 0.0, 1.0)
    flange_to_tcp: Pose = field(default_factory=Pose.identity)
    joint_limits_rad: np.ndarray | None = None
    tcp_to_sensor: Pose = field(default_factory=Pose.identity)
    link: URLinkConfig = field(default_factory=URLinkConfig)
    force_loop: ForceLoopGains = field(default_factory=ForceLoopGains)
    # Not 125 Hz: polling the RTDE stream (125 or 500 Hz) at its own rate would read every
    # package at the same delay after it arrived, and RobotClock (ur_link), which times
    # packages by their quickest reading, would carry that delay into every pose's time.
    control_hz: float = 121.0
    stop_decel_m_s2: float = 4.0          # stopL / speedStop on a trip, a contact, stop()
    move_tolerance_mm: float = 0.5        # a moveL counts as DONE within this of its target
    move_grace_s: float = 0.5             # time for a new moveL to show up in the state
    safety_period_s: float = 0.002        # longest wait for F/T data before a stale check
    # The stop path (bench/safety_latency.py times both): the safety thread reads the Net F/T
    # socket itself (False: the client's receive thread wakes it, one more thread hop), and
    # stops go to the ur_rtde child over a dedicated stop pipe (False: as a call through the
    # link's request pipe, behind its lock, waiting for ur_rtde's acknowledgement).
    ft_read_in_safety_thread: bool = True
    direct_stop: bool = True
    # Niceness of the hardware process (its threads and the ur_rtde child inherit it): on a
    # busy computer the stop path waits for a CPU at every hop, so it asks for more than its
    # share. Best effort (needs CAP_SYS_NICE to go below 0); None leaves it alone.
    nice: int | None = -10
    call_timeout_s: float = 15.0          # controller -> hardware process request deadline
    start_timeout_s: float = 60.0
    max_restarts: int = 2
    lifetime_s: float = 7 * 24 * 3600.0


# ====================================================================== the safety loop
@dataclass
class LatencyStats:
    """Wall-clock seconds from the arrival of the block holding a crossing to the stop sent."""

    samples_s: collections.deque = field(default_factory=lambda: collections.deque(maxlen=100_000))

    def add(self, seconds: float) -> None:
        self.samples_s.append(float(seconds))

    def summary(self) -> dict[str, float | int | None]:
        if not self.samples_s:
            return {"trips": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
        a = np.asarray(self.samples_s) * 1e3
        return {"trips": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
                "max_ms": float(a.max())}


class StopFirstGuard(SafetyGuard):
    """SafetyGuard whose trips carry their raw F/T history only once the stop has gone out.

    ``SafetyGuard`` snapshots the last seconds of raw data into every Trip as it detects it;
    with one-sample blocks at 1 kHz that is a concatenation of thousands of arrays (over a
    millisecond) standing between the crossing and the stop. The check itself is unchanged
    (``check_block`` is SafetyGuard's); :meth:`attach_raw` adds the history after the stop.
    """

    def _trip(self, kind: str, t_s: float, value: float, limit: float, message: str) -> Trip:
        trip = Trip(kind=kind, t_s=t_s, value=value, limit=limit, message=message, raw=None)
        if self.tripped is None:
            self.tripped = trip
        return trip

    def attach_raw(self, trip: Trip) -> Trip:
        full = replace(trip, raw=self.raw_history())
        if self.tripped is trip:
            self.tripped = full
        return full


class DeviceTimebase:
    """Sample times from the device's sequence numbers: t = offset + seq / rate_hz.

    The Net F/T client stamps records no later than their arrival, so a burst that arrives
    after the network or a starved thread held it back gets compressed times (tens of
    microseconds apart). The force-rate limit divides by these differences: a compressed
    burst turns 0.05 N of noise into thousands of N/s. The device sampled them 1/rate apart,
    so the safety path uses that.

    ``offset``: per block, the smallest ``t - seq/rate`` (the block's least-delayed record;
    for a compressed burst read as one block, its last record), so every time stays at or
    before its arrival. It rises at once (a stalled or restarted stream shows as a gap) and
    falls by at most ``max_fall`` of the sample time elapsed, so times never go backwards and
    spacings shrink by at most that fraction. (It once only rose: one stall of D seconds left
    every later sample D in the future, which delayed the stale check by D and put the scans'
    forces next to the wrong samples.)
    """

    def __init__(self, rate_hz: float, max_fall: float = 0.2) -> None:
        self.period_s = 1.0 / float(rate_hz)
        self.max_fall = float(max_fall)
        self.offset_s: float | None = None
        self._last_seq: int | None = None

    def retime(self, block: WrenchBlock) -> WrenchBlock:
        if not len(block):
            return block
        nominal = block.seq.astype(np.float64) * self.period_s
        candidate = float(np.min(block.t_s - nominal))
        if self.offset_s is None or self._last_seq is None:
            offset = candidate
        else:
            elapsed = max(int(block.seq[0]) - self._last_seq, 1)      # a restarted stream counts from 1
            offset = max(candidate, self.offset_s - self.max_fall * self.period_s * elapsed)
        self.offset_s = offset
        self._last_seq = int(block.seq[-1])
        return WrenchBlock(offset + nominal, block.seq, block.force_n, block.torque_nm, block.status)


class SafetyLoop:
    """The check-and-stop path over an F/T stream (used by the hardware process and the bench).

    ``read_block()`` returns the samples that arrived since the last call; ``wait_data(t)``
    blocks up to t s for new data (True if some arrived); ``arrival_s()`` the wall time the
    newest data arrived; ``on_stop(verdict, arrival_s)`` must stop the arm at once (a trip
    or a contact: what ``supervisor.on_block`` decided for the block the guard checked);
    ``heartbeat()`` tells the robot link the safety path is alive. The guard, its
    carry-over and the supervisor's samples are protected by ``lock`` (a tare must not fall
    between a read and its check).
    """

    def __init__(self, guard: SafetyGuard, supervisor: ForceSupervisor, read_block: Callable[[], WrenchBlock],
                 wait_data: Callable[[float], bool], arrival_s: Callable[[], float],
                 on_stop: Callable[[BlockVerdict, float], None],
                 heartbeat: Callable[[], None] = lambda: None, period_s: float = 0.002,
                 forward: Callable[[WrenchBlock], None] | None = None) -> None:
        self.guard = guard
        self.supervisor = supervisor
        self.read_block = read_block
        self.wait_data = wait_data
        self.arrival_s = arrival_s
        self.on_stop = on_stop
        self.heartbeat = heartbeat
        self.period_s = period_s
        self.forward = forward
        self.lock = threading.Lock()
        self.iterations = 0
        self.blocks = 0
        # Monotonic stamps of the current iteration (woke, block read, guard decided) and the
        # length of its block: the stop callback reads them for the latency breakdown.
        self.t_woke_s = self.t_read_s = self.t_decided_s = 0.0
        self.block_len = 0

    def force_now_n(self) -> float:
        """The force the loop reads now (the supervisor's latest samples, under the lock)."""
        with self.lock:
            return self.supervisor.force_now_n()

    def step(self) -> None:
        """One iteration: wait for data (bounded), check it, act on a crossing or a contact."""
        got = self.wait_data(self.period_s)
        self.t_woke_s = time.monotonic()
        self.heartbeat()
        self.iterations += 1
        with self.lock:
            block = self.read_block() if got else WrenchBlock.empty()
            self.t_read_s = time.monotonic()
            self.block_len = len(block)
            if not len(block):
                arrival = time.monotonic()
                trip = self.guard.check_stale(arrival)
            else:
                self.blocks += 1
                arrival = self.arrival_s()
                trip = self.guard.check_block(block)
            verdict = self.supervisor.on_block(block, trip)
        self.t_decided_s = time.monotonic()
        # Act first, then report: the stop goes out before anything else happens.
        if verdict.stop:
            self.on_stop(verdict, arrival)
            attach = getattr(self.guard, "attach_raw", None)
            if attach is not None and verdict.trip is not None and verdict.trip.raw is None:
                with self.lock:
                    attach(verdict.trip)
        if len(block) and self.forward is not None:
            self.forward(block)

    def run(self, stop: threading.Event, end_s: float) -> None:
        while not stop.is_set() and time.monotonic() < end_s:
            self.step()


# ====================================================================== hardware-process side
class _HardwareServer:
    """Everything that runs inside the hardware process."""

    def __init__(self, conn: Any, cfg: HardwareConfig, parent_pid: int) -> None:
        class _NotifyingNetFT(NetFTClient):
            """The Net F/T client, waking the safety thread on every datagram."""

            def __init__(self, *args: Any, **kwargs: Any) -> None:
                self.data_event = threading.Event()
                self.last_arrival_s = 0.0
                super().__init__(*args, **kwargs)

            def _ingest(self, records: Any, arrival_s: float) -> None:
                super()._ingest(records, arrival_s)
                self.last_arrival_s = arrival_s
                self.data_event.set()

        self.conn = conn
        self.cfg = cfg
        self.parent_pid = parent_pid
        self.stop_event = threading.Event()
        self.ft = _NotifyingNetFT(cfg.ft_host, cfg.rdt_port, cfg.calinfo_port, rate_hz=cfg.ft_rate_hz,
                                  receive_thread=not cfg.ft_read_in_safety_thread)
        # The arm moves the TCP the controller plans with (its IK uses cfg.flange_to_tcp, the
        # believed tool): the link sets that TCP on the robot at every script start.
        link_cfg = replace(cfg.link, tcp_offset_ur=tuple(float(v) for v in cfg.flange_to_tcp.to_ur()))
        self.link = URLink(cfg.robot_host, link_cfg).start()
        self.guard = StopFirstGuard(cfg.limits, np.asarray(cfg.probe_axis_sensor, float), rate_hz=cfg.ft_rate_hz)
        # The force loop: the same supervisor (and the cell's gains) as the simulated cell's.
        self.sup = ForceSupervisor(cfg.force_loop, cfg.limits, cfg.tcp_to_sensor.rotation)
        # Orders commands: speedL (control) against stops (safety) and new motions (main).
        self.gate = threading.Lock()
        self.wake = threading.Event()         # a new regulation: the control thread runs it now
        self.motions: collections.OrderedDict[int, SupervisedMotion] = collections.OrderedDict()
        # The moveL in flight: its motion, the link's handle, its target (ur units).
        self.move: tuple[SupervisedMotion, LinkMove, np.ndarray] | None = None
        # The arm's primitives (moveL, speedL, stops: the supervisor's commands go through them).
        self.arm = URPrimitives(self.link, cfg.stop_decel_m_s2 * 1e3, cfg.direct_stop)
        self.trace: collections.deque = collections.deque(maxlen=2000)   # (t, F, v, k, send s)
        self.state: URState | None = None
        self.pending_errors: list[str] = []
        self.latency = LatencyStats()
        self.stop_timings: collections.deque[dict[str, Any]] = collections.deque(maxlen=10_000)
        self.outbox: collections.deque[WrenchBlock] = collections.deque()
        self.outbox_n = 0
        self.outbox_lock = threading.Lock()
        self.timebase = DeviceTimebase(cfg.ft_rate_hz)
        self.safety = SafetyLoop(self.guard, self.sup, lambda: self.timebase.retime(self.ft.read_block()),
                                 self._wait_ft, lambda: self.ft.last_arrival_s, self._on_stop, self.link.heartbeat,
                                 cfg.safety_period_s, forward=self._forward)
        self.threads = [threading.Thread(target=self._safety_main, name="hw-safety", daemon=True),
                        threading.Thread(target=self._control_main, name="hw-control", daemon=True)]

    # ------------------------------------------------------------------ threads
    def start(self) -> None:
        for th in self.threads:
            th.start()
        deadline = time.monotonic() + 5.0
        while self.state is None and time.monotonic() < deadline:
            time.sleep(0.01)

    def _wait_ft(self, timeout_s: float) -> bool:
        if self.cfg.ft_read_in_safety_thread:
            return self.ft.receive(timeout_s) > 0
        ev = self.ft.data_event
        got = ev.wait(timeout_s)
        ev.clear()
        return got

    def _safety_main(self) -> None:
        try:
            self.safety.run(self.stop_event, time.monotonic() + self.cfg.lifetime_s)
        except BaseException as exc:  # noqa: BLE001 — a dead safety loop stops the heartbeat: the arm stops
            self.pending_errors.append(f"safety loop died: {type(exc).__name__}: {exc}")
            raise

    def _forward(self, block: WrenchBlock) -> None:
        with self.outbox_lock:
            self.outbox.append(block)
            self.outbox_n += len(block)
            limit = int(10.0 * self.cfg.ft_rate_hz)          # 10 s unread: drop the oldest
            while self.outbox_n > limit and len(self.outbox) > 1:
                self.outbox_n -= len(self.outbox.popleft())

    def _control_main(self) -> None:
        poll_s = 1.0 / self.cfg.control_hz
        next_poll = time.monotonic()
        end = next_poll + self.cfg.lifetime_s
        while not self.stop_event.is_set() and time.monotonic() < end:
            try:
                # A local: a recovery (main thread) sets self.state to None at any moment.
                st = self.state = self.link.state()
                self._update_motion(st)
                self._control_tick(st)
            except ProgramNotRunning:
                pass                    # a stop the next state explains (safety, operator, watchdog)
            except DeviceError as exc:
                self._link_failed(str(exc))
            except Exception as exc:  # noqa: BLE001 — keep the loop alive; the controller hears of it
                self._link_failed(f"control loop: {type(exc).__name__}: {exc}")
            now = time.monotonic()
            next_poll += poll_s
            if next_poll < now - 0.1:
                next_poll = now
            # While a regulation runs the state is read for each of its updates (on its own
            # schedule, the loop period); otherwise at control_hz.
            due = self.sup.next_update_s
            wake = due if due is not None else next_poll
            if due is not None:
                next_poll = max(next_poll, due)
            if self.wake.wait(max(0.0, wake - now)):
                self.wake.clear()

    def _control_tick(self, st: URState) -> None:
        """The supervisor's control path on a fresh state: the search's distance, the regulation."""
        with self.gate:
            m = self.sup.motion
            cmd = self.sup.on_tick(time.monotonic(), st.tcp_pose_ur[:3] * 1e3, self.safety.force_now_n())
            if cmd.stop:
                self._send_stop()
            elif cmd.velocity_mm_s is not None and m is not None and m.active and m is self.sup.motion:
                t_call = time.monotonic()
                self.arm.speed_linear(cmd.velocity_mm_s, cmd.accel_mm_s2)
                reg = self.sup.regulation
                if reg is not None and m.kind == "regulate_force":
                    self.trace.append((t_call, reg.last_force_n, float(np.linalg.norm(cmd.velocity_mm_s)),
                                       reg.stiffness_n_mm, time.monotonic() - t_call))

    def _link_failed(self, message: str) -> None:
        self.pending_errors.append(message)
        self.sup.faulted(message)
        self.move = None
        # A failed link restarts its child: the new program runs no speed thread.
        self.arm.program_restarted()
        self.state = None

    # ------------------------------------------------------------------ stops (safety thread)
    def _send_stop(self) -> int | None:
        """Stop the arm now (URPrimitives.stop). Returns the direct channel's sequence number
        (None for a call through the request pipe). The caller holds the gate."""
        try:
            return self.arm.stop()
        except DeviceError as exc:
            # The link restarts its child, whose new program stops the arm anyway.
            self.pending_errors.append(f"stop failed: {exc}")
        return None

    def _on_stop(self, verdict: BlockVerdict, arrival_s: float) -> None:
        """The safety thread's stop: a crossing, or the contact a search was looking for."""
        t_stop_s = time.monotonic()
        with self.gate:
            t_gate_s = time.monotonic()
            seq = self._send_stop()
        now = time.monotonic()
        trip = verdict.trip
        if trip is None:
            return
        self.latency.add(now - arrival_s)
        sl = self.safety
        # Direct stops: no call lock; "sent" = handed to the pipe (the child's stamps are in
        # its report, merged by op_stop_timings).
        link = ({"t_call_s": t_gate_s, "t_locked_s": t_gate_s, "t_sent_s": self.link.last_stop_sent_s}
                if self.cfg.direct_stop else dict(self.link.last_stop_timing))
        self.stop_timings.append({
            "arrival_s": arrival_s, "woke_s": sl.t_woke_s, "read_s": sl.t_read_s, "decided_s": sl.t_decided_s,
            "block_len": sl.block_len, "stop_s": t_stop_s, "gate_s": t_gate_s, "sent_or_acknowledged_s": now,
            "stop_seq": seq, **link})
        # Then the record: the latch, with the direction that unloads the contact.
        st = self.state
        rotation = Pose.from_ur(st.tcp_pose_ur).rotation if st is not None else None
        with sl.lock:
            force_base = self.sup.force_base_n(rotation) if rotation is not None else None
        self.sup.tripped(trip, verdict.peak_force_n, force_base)

    # ------------------------------------------------------------------ motion updates (control thread)
    def _update_motion(self, st: URState) -> None:
        m = self.sup.motion
        if m is None or not m.active:
            return
        if st.protective_stopped or st.emergency_stopped or not st.program_running or not st.connected:
            why = ("emergency stop" if st.emergency_stopped else "protective stop" if st.protective_stopped
                   else st.stop_reason if st.operator_stop
                   else "program not running" if not st.program_running else "connection lost")
            with self.gate:
                self.sup.faulted(why)
                self.move = None
            return
        move = self.move
        if move is None or move[0] is not m:
            return
        _, link_move, target_ur = move
        m.set_progress(link_move.fraction_done(st))
        at_target = float(np.linalg.norm(st.tcp_pose_ur[:3] - target_ur[:3])) * 1e3 <= self.cfg.move_tolerance_mm
        if not link_move.is_running(st) and st.tcp_speed_m_s < 1e-4:
            if at_target:
                m.finish(MotionState.DONE)
                self.move = None
            elif time.monotonic() - link_move.t_start_s > self.cfg.move_grace_s:
                self.sup.faulted("moveL ended away from its target")
                self.move = None

    # ------------------------------------------------------------------ requests (main thread)
    def _publish(self, m: SupervisedMotion) -> None:
        self.motions[m.id] = m
        while len(self.motions) > 256:
            self.motions.popitem(last=False)

    def _raise_pending(self) -> None:
        if self.pending_errors:
            errors, self.pending_errors = self.pending_errors, []
            raise DeviceError("; ".join(dict.fromkeys(errors)))

    def _ready_state(self) -> URState:
        st = self.state
        if st is None:
            st = self.state = self.link.state()
        return st

    def op_status(self) -> dict[str, Any]:
        self._raise_pending()
        st = self._ready_state()
        return {"t_s": st.t_s, "pose_ur": st.tcp_pose_ur.tolist(), "q": st.joints_rad.tolist(),
                "speed_mm_s": st.tcp_speed_m_s * 1e3, "program_running": st.program_running,
                "protective": st.protective_stopped, "emergency": st.emergency_stopped,
                "connected": st.connected and self.link.alive, "operator_stop": st.operator_stop,
                "stop_reason": st.stop_reason,
                # Every lost link restarts the child (URLink._fault): its restarts count the losses.
                "link_generation": self.link.restarts}

    def op_move_linear(self, target_ur: list[float], speed_mm_s: float, accel_mm_s2: float) -> int:
        self._raise_pending()
        target = np.asarray(target_ur, float)
        start = self._ready_state().tcp_pose_ur
        with self.gate:
            m = self.sup.begin_move(start[:3] * 1e3, target[:3] * 1e3)
            self._publish(m)
            self.move = (m, self.arm.move_linear(target, speed_mm_s, accel_mm_s2), target)
        return m.id

    def op_seek_contact(self, direction: list[float], speed_mm_s: float, contact_force_n: float,
                        max_distance_mm: float) -> int:
        self._raise_pending()
        st = self._ready_state()
        with self.gate:
            m = self.sup.begin_seek(np.asarray(direction, float), speed_mm_s, contact_force_n, max_distance_mm,
                                    st.tcp_pose_ur[:3] * 1e3, time.monotonic())
            self._publish(m)
            self.move = None
            search = self.sup.search
            assert search is not None
            self.arm.speed_linear(search.velocity_mm_s(), self.cfg.force_loop.seek_accel_mm_s2)
        return m.id

    def op_regulate_force(self, direction: list[float], target_force_n: float, rate_n_s: float) -> int:
        self._raise_pending()
        with self.gate:
            m = self.sup.begin_regulation(np.asarray(direction, float), target_force_n, rate_n_s, time.monotonic(),
                                          self.safety.force_now_n())
            self._publish(m)
            self.move = None
        self.wake.set()
        return m.id

    def op_stop(self) -> bool:
        with self.gate:
            self.sup.stopped()
            self.move = None
            self._send_stop()
        return True

    def op_motion(self, motion_id: int) -> tuple[str, float, str]:
        m = self.motions.get(motion_id)
        if m is None:
            return MotionState.STOPPED.value, 0.0, "forgotten"
        return m.state().value, m.progress(), m.note

    def op_trip(self) -> Trip | None:
        with self.safety.lock:
            trip = self.guard.tripped
            if trip is not None and trip.raw is None:      # asked between the stop and the snapshot
                trip = self.guard.attach_raw(trip)
            return trip

    def op_rearm(self) -> bool:
        with self.safety.lock:
            if not self.guard.rearm():
                return False
            self.sup.rearmed()
            return True

    def op_recover(self) -> bool:
        with self.gate:
            result = self.link.recover_protective_stop()
            self.arm.program_restarted()
        self.state = None
        return bool(result.get("ok", False))

    def op_read_block(self) -> WrenchBlock:
        with self.outbox_lock:
            blocks = list(self.outbox)
            self.outbox.clear()
            self.outbox_n = 0
        return WrenchBlock.concat(blocks)

    def op_tare(self) -> bool:
        with self.safety.lock:
            self.ft.tare()
            # A deliberate step in the readings is not a force rate, nor a force to regulate from.
            self.guard.note_stream_restart()
            self.sup.forget_samples()
        return True

    def op_identity(self) -> dict[str, Any]:
        ft = self.ft.identity()
        return {"arm": {**self.link.identity(), "force_loop": self.sup.identity()}, "ft": {"model": ft.model, "serial": ft.serial,
                                                          "firmware": ft.firmware, "extra": dict(ft.extra)}}

    def op_stop_timings(self) -> list[dict[str, Any]]:
        """Monotonic stamps of every trip's stop (oldest first; then forgotten): F/T arrival,
        safety thread woke / read / decided, gate taken, link lock taken, pipe sent, the
        child's receipt and ur_rtde call, the answer."""
        out = list(self.stop_timings)
        self.stop_timings.clear()
        reports = self.link.stop_reports
        for t in out:
            if t.get("stop_seq") is not None and t["stop_seq"] in reports:
                t.update(reports[t["stop_seq"]])
        return out

    def op_stats(self) -> dict[str, Any]:
        c = self.ft.counters()
        return {"latency": self.latency.summary(), "safety_iterations": self.safety.iterations,
                "safety_blocks": self.safety.blocks, "link_restarts": self.link.restarts,
                "link_child_pid": self.link.child_pid, "ft_received": c.received, "ft_lost": c.lost,
                "ft_longest_gap_ms": c.longest_gap_s * 1e3,
                "link_faults": [f"{f.kind}: {f.message}" for f in self.link.faults],
                "supervisor": self.sup.describe(), "regulation_trace": list(self.trace)}

    # ------------------------------------------------------------------ serve
    def serve(self) -> int:
        end = time.monotonic() + self.cfg.lifetime_s
        while time.monotonic() < end:
            if os.getppid() != self.parent_pid:
                return 0
            if not self.conn.poll(0.05):
                continue
            try:
                msg = self.conn.recv()
            except EOFError:
                return 0
            if msg[0] == "close":
                return 0
            rid, name, args = msg[1], msg[2], msg[3]
            try:
                result = getattr(self, "op_" + name)(*args)
                self.conn.send(("ok", rid, result))
            except MotionRefused as exc:
                self.conn.send(("refused", rid, str(exc)))
            except ProgramNotRunning as exc:
                self.conn.send(("not_running", rid, str(exc)))
            except DeviceTimeout as exc:
                self.conn.send(("timeout", rid, str(exc)))
            except Exception as exc:  # noqa: BLE001 — every failure goes back to the controller
                self.conn.send(("err", rid, f"{type(exc).__name__}: {exc}"))
        return 0

    def close(self) -> None:
        self.stop_event.set()
        self.wake.set()
        try:
            m = self.sup.motion
            if m is not None and m.active:
                with self.gate:
                    self.sup.stopped("hardware process closing")
                    self._send_stop()
        except Exception:  # noqa: BLE001 — closing is best effort
            pass
        for th in self.threads:
            th.join(1.0)
        self.link.close()
        self.ft.close()


def _hardware_main(conn: Any, cfg: HardwareConfig, parent_pid: int) -> None:
    """Entry point of the hardware process (spawned)."""
    set_parent_death_signal()
    if os.getppid() != parent_pid:        # the parent died before prctl took effect
        os._exit(0)
    sys.setswitchinterval(0.0005)          # a woken safety thread gets the GIL promptly
    if cfg.nice is not None:
        try:
            # Before any thread starts: Linux threads and children inherit the caller's nice.
            os.setpriority(os.PRIO_PROCESS, 0, cfg.nice)
        except OSError:
            pass                            # not permitted: run at the normal priority
    try:
        server = _HardwareServer(conn, cfg, parent_pid)
        server.start()
        conn.send(("ready", server.op_identity()))
    except Exception as exc:  # noqa: BLE001 — tell the controller why, then exit
        try:
            conn.send(("fatal", f"{type(exc).__name__}: {exc}"))
        finally:
            os._exit(2)
    code = 0
    try:
        code = server.serve()
    finally:
        server.close()
        conn.close()
    os._exit(code)


# ====================================================================== controller side
class HardwareProcess:
    """The controller's handle on the hardware process: start, requests with deadlines, restart.

    ``arm`` and ``ft`` are the Arm and ForceTorqueSensor the controller programs against.
    """

    def __init__(self, cfg: HardwareConfig) -> None:
        self.cfg = cfg
        self._ctx = mp.get_context("spawn")
        self._lock = threading.RLock()
        self._proc: Any = None
        self._conn: Any = None
        self._rid = 0
        self.restarts = 0
        self._dead_reason: str | None = None
        self.identity_info: dict[str, Any] = {}
        self.arm = HardwareArm(self)
        self.ft = HardwareFT(self)

    # -- lifecycle
    def start(self) -> "HardwareProcess":
        with self._lock:
            self._spawn()
        ref = weakref.ref(self)
        atexit.register(lambda: ref() is not None and ref().close(1.0))
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        with self._lock:
            if self._proc is not None and self._proc.is_alive() and self._conn is not None:
                try:
                    self._conn.send(("close",))
                except OSError:
                    pass
                self._proc.join(timeout_s)
            self._kill()
            self._dead_reason = "closed"

    def __enter__(self) -> "HardwareProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def _spawn(self) -> None:
        parent_conn, child_conn = self._ctx.Pipe(duplex=True)
        # Not a daemon: it must be allowed to start URLink's ur_rtde child. It still dies
        # with this process (PR_SET_PDEATHSIG), and an exit handler closes it first.
        proc = self._ctx.Process(target=_hardware_main, name="elastoprobe-hardware",
                                 args=(child_conn, self.cfg, os.getpid()), daemon=False)
        proc.start()
        child_conn.close()
        self._proc, self._conn = proc, parent_conn
        try:
            self.identity_info = await_ready(proc, parent_conn, self.cfg.start_timeout_s, "hardware process")
        except DeviceError:
            self._kill()
            raise

    def _kill(self) -> None:
        kill_child(self._proc, self._conn, 3.0)
        self._conn = None

    def _restart(self, why: str) -> None:
        """Kill the hardware process (its link child dies with it: the watchdog stops the arm)
        and start a new one, bounded by ``max_restarts``."""
        self._kill()
        if self.restarts >= self.cfg.max_restarts:
            self._dead_reason = f"{why}; gave up after {self.restarts} restarts"
            return
        self.restarts += 1
        try:
            self._spawn()
        except DeviceError as exc:
            self._dead_reason = f"{why}; restart failed: {exc}"

    # -- requests
    def call(self, name: str, *args: Any, timeout_s: float | None = None) -> Any:
        with self._lock:
            if self._dead_reason is not None:
                raise DeviceError(f"hardware process is down: {self._dead_reason}")
            if self._conn is None:
                raise DeviceError("hardware process is not started")
            self._rid += 1
            rid = self._rid
            try:
                self._conn.send(("call", rid, name, args))
            except OSError as exc:
                self._restart(f"pipe broke during {name}")
                raise DeviceError(f"hardware process died during {name}; restarted") from exc
            deadline = time.monotonic() + (self.cfg.call_timeout_s if timeout_s is None else timeout_s)
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._restart(f"{name} hung")
                    raise DeviceTimeout(f"hardware process did not answer {name} in time; killed and restarted")
                try:
                    msg = self._conn.recv() if self._conn.poll(min(remaining, 0.05)) else None
                except (EOFError, OSError):
                    msg = None
                    if self._proc is not None:
                        self._proc.join(0.5)
                if msg is None:
                    if self._proc is None or not self._proc.is_alive():
                        code = None if self._proc is None else self._proc.exitcode
                        self._restart(f"hardware process exited (code {code}) during {name}")
                        raise DeviceError(f"hardware process died during {name} (code {code}); restarted")
                    continue
                kind, mid, payload = msg
                if mid != rid:
                    continue                       # a stale answer to a call that timed out
                if kind == "ok":
                    return payload
                if kind == "refused":
                    raise MotionRefused(payload)
                if kind == "timeout":
                    raise DeviceTimeout(payload)
                if kind == "not_running":
                    raise ProgramNotRunning(payload)
                raise DeviceError(f"hardware {name}: {payload}")

    def stats(self) -> dict[str, Any]:
        return dict(self.call("stats"))


class HardwareMotion:
    """Handle of a motion running in the hardware process (implements Motion)."""

    def __init__(self, proc: HardwareProcess, motion_id: int, kind: str) -> None:
        self._proc = proc
        self._id = motion_id
        self._kind = kind
        self._final: tuple[MotionState, float] | None = None
        self.note = ""

    @property
    def kind(self) -> str:
        return self._kind

    def _poll(self) -> tuple[MotionState, float]:
        if self._final is not None:
            return self._final
        try:
            state, progress, note = self._proc.call("motion", self._id)
        except DeviceError as exc:
            self.note = str(exc)
            self._final = (MotionState.FAULT, 0.0)
            return self._final
        self.note = note
        result = (MotionState(state), float(progress))
        if result[0] not in (MotionState.RUNNING, MotionState.DONE) or (
                result[0] == MotionState.DONE and self._kind != "regulate_force"):
            self._final = result
        return result

    def state(self) -> MotionState:
        return self._poll()[0]

    def progress(self) -> float:
        return self._poll()[1]


class HardwareArm:
    """The Arm the controller drives; every call goes to the hardware process."""

    def __init__(self, proc: HardwareProcess) -> None:
        self._proc = proc
        self._model: Any = None

    def identity(self) -> DeviceIdentity:
        info = dict(self._proc.identity_info.get("arm", {}))
        return DeviceIdentity("arm", info.pop("model", "UR"), info.pop("serial", "unknown"),
                              info.pop("polyscope", "unknown"), info)

    def status(self) -> ArmStatus:
        d = self._proc.call("status")
        return ArmStatus(t_s=float(d["t_s"]), tcp_pose=Pose.from_ur(d["pose_ur"]),
                         joints_rad=np.asarray(d["q"], float), tcp_speed_mm_s=float(d["speed_mm_s"]),
                         program_running=bool(d["program_running"]), protective_stop=bool(d["protective"]),
                         emergency_stop=bool(d["emergency"]), is_moving=float(d["speed_mm_s"]) > 0.1,
                         connected=bool(d["connected"]), operator_stop=bool(d["operator_stop"]),
                         stop_reason=str(d["stop_reason"]), link_generation=int(d.get("link_generation", 0)))

    def inverse_kinematics(self, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
        if self._model is None:
            self._model = ur5e(self._proc.cfg.flange_to_tcp, self._proc.cfg.joint_limits_rad)
        seed = self.status().joints_rad if seed_joints_rad is None else seed_joints_rad
        return inverse(self._model, tcp_pose, seed)

    def move_linear(self, target: Pose, speed_mm_s: float, accel_mm_s2: float) -> HardwareMotion:
        if not (0.0 < speed_mm_s <= 1000.0) or not (0.0 < accel_mm_s2 <= 5000.0):
            raise MotionRefused(f"moveL speed {speed_mm_s} mm/s or acceleration {accel_mm_s2} mm/s^2 out of range")
        if self.inverse_kinematics(target) is None:
            raise MotionRefused(f"target {np.round(target.position_mm, 1).tolist()} mm is out of reach or joint limits")
        mid = self._proc.call("move_linear", list(target.to_ur()), float(speed_mm_s), float(accel_mm_s2))
        return HardwareMotion(self._proc, mid, "move_linear")

    def seek_contact(self, direction: np.ndarray, speed_mm_s: float, contact_force_n: float,
                     max_distance_mm: float) -> HardwareMotion:
        if speed_mm_s <= 0 or contact_force_n <= 0 or max_distance_mm <= 0:
            raise MotionRefused("seek_contact needs a positive speed, force threshold and distance")
        mid = self._proc.call("seek_contact", [float(v) for v in direction], float(speed_mm_s),
                              float(contact_force_n), float(max_distance_mm))
        return HardwareMotion(self._proc, mid, "seek_contact")

    def regulate_force(self, direction: np.ndarray, target_force_n: float, rate_n_s: float) -> HardwareMotion:
        if target_force_n < 0 or rate_n_s <= 0:
            raise MotionRefused("regulate_force needs a target >= 0 N and a positive rate")
        mid = self._proc.call("regulate_force", [float(v) for v in direction], float(target_force_n),
                              float(rate_n_s))
        return HardwareMotion(self._proc, mid, "regulate_force")

    def stop(self) -> None:
        self._proc.call("stop")

    def trip(self) -> Trip | None:
        return self._proc.call("trip")

    def rearm(self) -> bool:
        return bool(self._proc.call("rearm"))

    def recover_protective_stop(self) -> bool:
        cfg = self._proc.cfg.link
        return bool(self._proc.call("recover", timeout_s=cfg.unlock_wait_s + cfg.recovery_attempts * 2.0 + 30.0))


class HardwareFT:
    """The ForceTorqueSensor the controller reads: blocks forwarded by the safety loop."""

    def __init__(self, proc: HardwareProcess) -> None:
        self._proc = proc

    def identity(self) -> DeviceIdentity:
        info = self._proc.identity_info.get("ft", {})
        return DeviceIdentity("ft", info.get("model", "ATI Net F/T"), info.get("serial", "unknown"),
                              info.get("firmware", "unknown"), dict(info.get("extra", {})))

    @property
    def rate_hz(self) -> float:
        return self._proc.cfg.ft_rate_hz

    def read_block(self) -> WrenchBlock:
        return self._proc.call("read_block")

    def tare(self) -> None:
        self._proc.call("tare")


__all__ = ["HardwareConfig", "HardwareProcess", "HardwareArm", "HardwareFT", "HardwareMotion",
           "SafetyLoop", "LatencyStats", "DeviceTimebase", "StopFirstGuard", "Clock", "RealClock"]
