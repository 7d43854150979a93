"""A scripted arm: the force loop's supervisor on a light fake, without the physics simulator.

In the style of ophyd-async's mock backends: no physics model, no threads, no network. A
test scripts what the F/T sensor reads as a function of where the tool is (``force_of``)
and reads back every primitive the supervisor commanded (``commands``). The arm is a point
(the TCP) that follows its primitives — a straight move at constant speed, a speed command
reached at the commanded acceleration, a stop at ``stop_decel_mm_s2`` — each taking effect
``command_delay_s`` after it was sent, as a real robot's does.

It is driven like the real cell's hardware process drives the supervisor: every F/T sample
block goes through :class:`~elastoprobe.controller.core.safety.SafetyGuard` and
:meth:`ForceSupervisor.on_block` (a stop acts at that sample), and the control path
(:meth:`ForceSupervisor.on_tick`) runs every ``tick_s``; time is the given VirtualClock's.

Frames: the base, the TCP and the sensor frames coincide (the tool does not turn), so
``force_of`` returns the force the environment exerts on the tool in the base frame (N):
pressing down on a surface, it points up. Units: mm, mm/s, mm/s^2, N, s.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..core.clock import VirtualClock
from ..core.devices import ArmStatus, DeviceIdentity, Motion, MotionState, Trip, WrenchBlock
from ..core.errors import MotionRefused
from ..core.forceloop import ForceLoopGains, ForceSupervisor, SupervisedMotion
from ..core.geometry import Pose
from ..core.safety import SafetyGuard, SafetyLimits


@dataclass
class _Primitive:
    """The primitive in force: a move to ``target`` at ``speed``, a ``velocity``, or a stop."""

    kind: str                                  # "hold", "move", "speed", "stop"
    target_mm: np.ndarray | None = None
    speed_mm_s: float = 0.0
    velocity_mm_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_mm_s2: float = 0.0
    motion: SupervisedMotion | None = None


class ScriptedArm:
    """An Arm (and its F/T sensor, ``ft``) whose force readings are scripted.

    ``force_of(position_mm) -> force (3,) N`` on the tool, base frame; ``start_mm``: the TCP's
    start; ``gains``, ``limits``: the cell's force loop and safety limits. ``noise_n``: the
    standard deviation of Gaussian noise added per axis (seeded by ``seed``).
    """

    def __init__(self, clock: VirtualClock, force_of: Callable[[np.ndarray], np.ndarray], *,
                 gains: ForceLoopGains = ForceLoopGains(), limits: SafetyLimits,
                 start_mm: np.ndarray = np.zeros(3), rate_hz: float = 1000.0, tick_s: float = 0.002,
                 command_delay_s: float = 0.0, stop_decel_mm_s2: float = 2500.0, noise_n: float = 0.0,
                 seed: int = 0) -> None:
        self.clock = clock
        self.force_of = force_of
        self.gains = gains
        self.guard = SafetyGuard(limits, rate_hz=rate_hz)
        self.supervisor = ForceSupervisor(gains, limits)
        self.rate_hz = float(rate_hz)
        self.tick_s = float(tick_s)
        self.command_delay_s = float(command_delay_s)
        self.stop_decel_mm_s2 = float(stop_decel_mm_s2)
        self.noise_n = float(noise_n)
        self._rng = np.random.default_rng(seed)
        self.position_mm = np.asarray(start_mm, float).copy()
        self.velocity_mm_s = np.zeros(3)
        self._active = _Primitive("hold")
        self._queued: list[tuple[float, _Primitive]] = []        # (takes effect at, primitive)
        self.commands: list[tuple[float, str, object]] = []      # (sent at, kind, argument)
        self._t_s = clock.now_s()
        self._next_tick_s = self._t_s
        self._seq = 0
        self._silent_until_s = -np.inf
        self._bias = np.zeros(3)
        self._outbox: list[WrenchBlock] = []
        self.ft = _ScriptedFT(self)
        clock.add_listener(self._advance_to)

    # ------------------------------------------------------------------ primitives (the device)
    def _send(self, kind: str, argument: object, primitive: _Primitive) -> None:
        self.commands.append((self._t_s, kind, argument))
        self._queued.append((self._t_s + self.command_delay_s, primitive))

    def _stop_primitive(self) -> None:
        self._send("stop", self.stop_decel_mm_s2, _Primitive("stop", accel_mm_s2=self.stop_decel_mm_s2))

    # ------------------------------------------------------------------ the Arm protocol (the toolhead)
    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("arm", "scripted", "0", "0", {"force_loop": self.supervisor.identity()})

    def status(self) -> ArmStatus:
        speed = float(np.linalg.norm(self.velocity_mm_s))
        return ArmStatus(t_s=self._t_s, tcp_pose=Pose(self.position_mm.copy(), np.eye(3)), joints_rad=np.zeros(6),
                         tcp_speed_mm_s=speed, program_running=True, protective_stop=False, emergency_stop=False,
                         is_moving=speed > 1e-3)

    def inverse_kinematics(self, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
        return np.zeros(6)

    def move_linear(self, target: Pose, speed_mm_s: float, accel_mm_s2: float) -> Motion:
        if speed_mm_s <= 0:
            raise MotionRefused("move speed must be positive")
        motion = self.supervisor.begin_move(self.position_mm, target.position_mm)
        self._send("move_linear", target.position_mm.copy(),
                   _Primitive("move", target_mm=target.position_mm.copy(), speed_mm_s=float(speed_mm_s),
                              motion=motion))
        return motion

    def seek_contact(self, direction: np.ndarray, speed_mm_s: float, contact_force_n: float,
                     max_distance_mm: float) -> Motion:
        motion = self.supervisor.begin_seek(direction, speed_mm_s, contact_force_n, max_distance_mm, self.position_mm,
                                            self._t_s)
        search = self.supervisor.search
        assert search is not None
        self._send("speed_linear", search.velocity_mm_s(),
                   _Primitive("speed", velocity_mm_s=search.velocity_mm_s(), accel_mm_s2=self.gains.seek_accel_mm_s2))
        return motion

    def regulate_force(self, direction: np.ndarray, target_force_n: float, rate_n_s: float) -> Motion:
        return self.supervisor.begin_regulation(direction, target_force_n, rate_n_s, self._t_s,
                                                self.supervisor.force_now_n())

    def stop(self) -> None:
        self.supervisor.stopped()
        self._stop_primitive()

    def trip(self) -> Trip | None:
        return self.guard.tripped

    def rearm(self) -> bool:
        if not self.guard.rearm():
            return False
        self.supervisor.rearmed()
        return True

    def recover_protective_stop(self) -> bool:
        return True

    # ------------------------------------------------------------------ virtual time
    def _advance_to(self, t_s: float) -> None:
        dt = 1.0 / self.rate_hz
        while self._t_s + dt <= t_s + 1e-12:
            self._t_s += dt
            self._step_motion(dt)
            self._sample()
            if self._t_s >= self._next_tick_s - 1e-12:
                self._next_tick_s += self.tick_s
                self._control_tick()

    def _step_motion(self, dt: float) -> None:
        while self._queued and self._queued[0][0] <= self._t_s + 1e-12:
            self._active = self._queued.pop(0)[1]
        p = self._active
        if p.kind == "move":
            assert p.target_mm is not None
            step = p.target_mm - self.position_mm
            dist = float(np.linalg.norm(step))
            if dist <= p.speed_mm_s * dt:
                self.position_mm = p.target_mm.copy()
                self.velocity_mm_s = np.zeros(3)
                if p.motion is not None and p.motion is self.supervisor.motion:
                    p.motion.finish(MotionState.DONE)
                self._active = _Primitive("hold")
            else:
                self.velocity_mm_s = step / dist * p.speed_mm_s
                self.position_mm = self.position_mm + self.velocity_mm_s * dt
            return
        target = p.velocity_mm_s if p.kind == "speed" else np.zeros(3)
        change = target - self.velocity_mm_s
        limit = p.accel_mm_s2 * dt
        norm = float(np.linalg.norm(change))
        self.velocity_mm_s = target.copy() if norm <= limit else self.velocity_mm_s + change * (limit / norm)
        self.position_mm = self.position_mm + self.velocity_mm_s * dt

    def stall_ft(self, duration_s: float) -> None:
        """The F/T stream delivers nothing for ``duration_s`` from now (a network hiccup)."""
        self._silent_until_s = self._t_s + float(duration_s)

    def _sample(self) -> None:
        if self._t_s < self._silent_until_s:
            trip = self.guard.check_stale(self._t_s)
            if trip is not None and self.supervisor.on_block(WrenchBlock.empty(), trip).stop:
                self._stop_primitive()
                self.supervisor.tripped(trip, 0.0, None)
            return
        force = np.asarray(self.force_of(self.position_mm), float).reshape(3)
        if self.noise_n > 0:
            force = force + self._rng.normal(0.0, self.noise_n, 3)
        force = force - self._bias
        self._seq += 1
        torque = np.zeros((1, 3)) + self._rng.normal(0.0, 1e-6, (1, 3))      # a live sensor is never frozen
        block = WrenchBlock(np.array([self._t_s]), np.array([self._seq]), force[None, :], torque,
                            np.zeros(1, dtype=np.uint32))
        self._outbox.append(block)
        # Where the data arrives: the guard and the supervisor, the stop before anything else.
        trip = self.guard.check_block(block)
        verdict = self.supervisor.on_block(block, trip)
        if verdict.stop:
            self._stop_primitive()
            if verdict.trip is not None:
                self.supervisor.tripped(verdict.trip, verdict.peak_force_n, force)

    def _control_tick(self) -> None:
        m = self.supervisor.motion
        cmd = self.supervisor.on_tick(self._t_s, self.position_mm)
        if cmd.stop:
            self._stop_primitive()
        elif cmd.velocity_mm_s is not None and m is not None and m.active:
            self._send("speed_linear", cmd.velocity_mm_s.copy(),
                       _Primitive("speed", velocity_mm_s=cmd.velocity_mm_s.copy(), accel_mm_s2=cmd.accel_mm_s2))


class _ScriptedFT:
    """The scripted arm's F/T sensor: the blocks its guard checked, and a software tare."""

    def __init__(self, arm: ScriptedArm) -> None:
        self._arm = arm

    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("ft", "scripted", "0", "0")

    @property
    def rate_hz(self) -> float:
        return self._arm.rate_hz

    def read_block(self) -> WrenchBlock:
        blocks, self._arm._outbox = self._arm._outbox, []
        return WrenchBlock.concat(blocks)

    def tare(self) -> None:
        arm = self._arm
        arm._bias = np.asarray(arm.force_of(arm.position_mm), float).reshape(3)
        arm.guard.note_stream_restart()
        arm.supervisor.forget_samples()


__all__ = ["ScriptedArm"]
