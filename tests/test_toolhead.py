"""The toolhead's primitives on the scripted arm (no physics simulator): what a probe and a
calibration routine are built from — validated moves, contact search, force regulation,
retract, trips surfacing as faults."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from elastoprobe.controller.core.clock import VirtualClock
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.safety import SafetyLimits
from elastoprobe.controller.drivers.scripted import ScriptedArm
from elastoprobe.controller.toolhead import MotionSettings, ProbeFault, Toolhead

from test_sim_helpers import Fence

LIMITS = SafetyLimits(max_force_n=45.0, max_torque_nm=4.0, max_lateral_force_n=45.0, max_force_rate_n_s=1500.0,
                      ft_stale_ms=30.0, ft_frozen_ms=60.0, slip_mm=6.0)
DOWN = np.array([0.0, 0.0, -1.0])
SETTINGS = MotionSettings(contact_force_n=0.4, contact_speed_mm_s=2.0, free_speed_mm_s=50.0, free_accel_mm_s2=500.0)


@dataclass
class _Cell:
    """The parts of a Cell the toolhead uses, on the scripted arm (base = TCP = sensor frames)."""

    clock: VirtualClock
    arm: ScriptedArm
    ft: object = None
    scanner: object = None
    tcp_to_sensor: Pose = field(default_factory=Pose.identity)
    base_to_object: Pose = field(default_factory=Pose.identity)

    def __post_init__(self) -> None:
        self.ft = self.arm.ft


def head_over(surface_z_mm: float, stiffness_n_mm: float = 2.0, start_z_mm: float = 5.0) -> tuple[Toolhead, Fence]:
    def force_of(p: np.ndarray) -> np.ndarray:
        return np.array([0.0, 0.0, stiffness_n_mm * max(surface_z_mm - p[2], 0.0)])

    clock = VirtualClock()
    arm = ScriptedArm(clock, force_of, limits=LIMITS, start_mm=np.array([0.0, 0.0, start_z_mm]))
    fence = Fence(100.0)
    return Toolhead(_Cell(clock, arm), SETTINGS, fence, travel_z_mm=40.0), fence


def test_contact_regulate_and_retract() -> None:
    head, fence = head_over(0.0)
    assert head.seek_contact(DOWN, 20.0)
    assert fence.checked[-1][2]                                   # the search path: contact allowed
    assert abs(head.pose().position_mm[2]) < 0.3                  # 0.4 N at 2 N/mm: 0.2 mm in
    t_command, t_done = head.regulate_force(DOWN, 5.0, 10.0)
    assert t_done - t_command >= 0.5 - 1e-9                       # 5 N at 10 N/s
    head.hold(0.5)
    f = head.forces_at([head.cell.clock.now_s() - 0.1])[0]
    assert abs(f[2] - 5.0) < 0.25 and abs(f[0]) < 1e-9
    assert not head.retract(-DOWN, 10.0).shortened
    head.hold(0.1)
    assert head.pose().position_mm[2] > 7.0
    assert np.linalg.norm(head.recorder.wrench().force_n[-1]) < 1e-9
    head.lift_to_travel()
    assert head.pose().position_mm[2] == pytest.approx(40.0, abs=1e-6)


def test_a_refused_unload_backs_out_as_far_as_the_limits_allow() -> None:
    """Unloading along a tilted normal whose full length ends beyond a fence (a keep-out's
    margin past the approach's checked path) backs out halved, not refused; with no length
    clear down to the least asked for, it is refused with the arm where it was."""
    head, fence = head_over(0.0)
    assert head.seek_contact(DOWN, 20.0)
    head.regulate_force(DOWN, 2.0, 10.0)
    head.hold(0.2)
    normal = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)
    fence.max_x_mm = 0.3 / np.hypot(0.3, 1.0) * 12.0            # 20 mm refused, 10 mm clear
    start = head.pose().position_mm.copy()
    went = head.retract(normal, 20.0, min_distance_mm=5.0)
    assert went.shortened and went.moved_mm == 10.0 and "fence" in went.refused
    head.hold(0.1)
    assert np.allclose(head.pose().position_mm - start, 10.0 * normal, atol=0.05)
    assert np.linalg.norm(head.recorder.wrench().force_n[-1]) < 1e-9
    head2, fence2 = head_over(0.0)
    assert head2.seek_contact(DOWN, 20.0)
    fence2.max_x_mm = 0.3 / np.hypot(0.3, 1.0) * 4.0            # not even 5 mm is clear
    before = head2.pose().position_mm.copy()
    with pytest.raises(MotionRefused):
        head2.retract(normal, 20.0, min_distance_mm=5.0)
    assert [round(float(c[1].position_mm[0] / normal[0]), 6) for c in fence2.checked[-3:]] == [20.0, 10.0, 5.0]
    assert np.allclose(head2.pose().position_mm, before, atol=1e-6)


def test_a_search_that_touches_nothing_says_so() -> None:
    head, _ = head_over(-100.0)
    assert not head.seek_contact(DOWN, 10.0)
    assert head.pose().position_mm[2] == pytest.approx(-5.0, abs=0.5)


def test_a_refused_move_leaves_the_arm_where_it_was() -> None:
    head, _ = head_over(-100.0)
    sent = len(head.cell.arm.commands)
    with pytest.raises(MotionRefused):
        head.move(Pose(np.array([150.0, 0.0, 5.0]), np.eye(3)))
    with pytest.raises(MotionRefused):
        head.travel_to(Pose(np.array([150.0, 0.0, 5.0]), np.eye(3)))
    assert len(head.cell.arm.commands) == sent
    head.travel_to(Pose(np.array([80.0, 0.0, 5.0]), np.eye(3)))   # up to travel height, across, down
    assert np.allclose(head.pose().position_mm, [80.0, 0.0, 5.0], atol=1e-6)
    assert max(c[2][2] for c in head.cell.arm.commands[sent:] if c[1] == "move_linear") == pytest.approx(40.0)


def test_a_trip_while_waiting_is_a_fault_with_the_trip() -> None:
    head, _ = head_over(0.0, stiffness_n_mm=20.0)
    assert head.seek_contact(DOWN, 20.0)
    with pytest.raises(ProbeFault) as caught:
        head.regulate_force(DOWN, 60.0, 100.0)                    # past the cell's 45 N
    assert caught.value.trip is not None and caught.value.kind == caught.value.trip.kind


def _pushed_sideways_through_the_limit() -> tuple[Toolhead, np.ndarray]:
    """A push at 170 degrees on a face tilted 15 degrees: the push ``d`` runs almost along the
    face and points 0.08 up in the base frame; the face resists along ``d`` (a wall for the
    sideways push, 20 N/mm). Regulated towards 60 N, the force trips at the 45 N limit."""
    d = np.array([0.0, -0.9968, 0.08])
    d /= np.linalg.norm(d)
    wall_mm = np.array([0.0, -5.0, 5.0 + 5.0 * 0.08 / 0.9968])

    def force_of(p: np.ndarray) -> np.ndarray:
        return -d * 20.0 * max(float((p - wall_mm) @ d), 0.0)

    clock = VirtualClock()
    arm = ScriptedArm(clock, force_of, limits=LIMITS, start_mm=np.array([0.0, 0.0, 5.0]))
    head = Toolhead(_Cell(clock, arm), SETTINGS, Fence(100.0), travel_z_mm=40.0)
    assert head.seek_contact(d, 20.0)
    with pytest.raises(ProbeFault):
        head.regulate_force(d, 60.0, 50.0)
    assert arm.trip() is not None and arm.trip().kind == "force"
    head.acknowledged_trip = arm.trip()
    return head, d


def test_a_fault_s_retract_unloads_along_the_normal_it_is_given() -> None:
    """Straight up runs 0.08 into a contact pushed at 170 degrees: the latched guard stops it.
    Along the face's normal (tilted 15 degrees) it leaves the contact and goes through."""
    head, d = _pushed_sideways_through_the_limit()
    with pytest.raises(ProbeFault):
        head.safe_retract()
    head, d = _pushed_sideways_through_the_limit()
    normal = np.array([0.0, np.sin(np.radians(15.0)), np.cos(np.radians(15.0))])
    assert float(normal @ -d) > 0.0
    start = head.pose().position_mm
    head.safe_retract(normal)
    end = head.pose().position_mm
    assert end[2] == pytest.approx(40.0, abs=1e-6)
    assert end[1] - start[1] == pytest.approx(20.0 * normal[1], abs=1e-6)   # 20 mm along the normal first
    assert head.cell.arm.rearm()
