"""The safety layer every robot driver runs behind: speed caps, the workspace box, the gripper
range and the command timeout, each reported as the limit that changed the command."""

from __future__ import annotations

import time

import numpy as np
import pytest

from services.core.rig import load_rig
from services.core.robot_types import EefDelta, RobotSnapshot
from services.robot.base import RobotDriver
from services.robot.safety import Safety, SafetyConfig
from sim.backends import SimRobot
from sim.world import SimWorld

ZERO = np.zeros(3)


class PointArm(RobotDriver):
    """A kinematic EEF that goes exactly where it is told and keeps no target of its own."""

    def __init__(self, pos=(0.45, 0.0, 0.25), closure=0.0):
        self.pos = np.array(pos, dtype=np.float64)
        self.closure = closure  # what its gripper reports
        self.applied: list[EefDelta] = []
        self.stops = 0

    def read(self) -> RobotSnapshot:
        return RobotSnapshot(self.pos.copy(), np.array([0.0, 1.0, 0.0, 0.0]), np.zeros(6), np.zeros(6), self.closure)

    def apply(self, action: EefDelta) -> None:
        self.applied.append(action)
        self.pos = self.pos + action.dp

    def stop(self) -> None:
        self.stops += 1


@pytest.fixture
def sim_arm():
    with SimWorld("lift", load_rig("front")) as world:
        world.reset(0)
        yield Safety(SimRobot(world), SafetyConfig(), world.control_hz), world


def test_speed_caps_scale_the_vector_and_say_so(sim_arm):
    arm, world = sim_arm
    arm.read()
    ran = arm.apply(EefDelta(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 2.0]), 0.0))
    assert ran.limits == ("speed", "rotation") and not ran.stale
    assert np.allclose(ran.action.dp, [0.0, 0.6 / 20, 0.0]) and np.allclose(ran.action.drot, [0.0, 0.0, 3.0 / 20])
    small = arm.apply(EefDelta(np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.05, 0.0]), 0.0))
    assert small.limits == () and np.array_equal(small.action.dp, [0.01, 0.0, 0.0])


def test_the_workspace_box_cuts_the_translation_per_axis(sim_arm):
    arm, world = sim_arm
    cfg = arm.cfg
    for _ in range(20):  # drive up (into the box top) and sideways (still inside)
        arm.read()
        ran = arm.apply(EefDelta(np.array([0.0, 0.02, 0.02]), ZERO, 0.0))
    target, _ = world.target()
    assert target[2] == pytest.approx(cfg.workspace_hi[2], abs=1e-12)
    assert "workspace" in ran.limits and ran.action.dp[2] == pytest.approx(0.0, abs=1e-12)
    assert ran.action.dp[1] == pytest.approx(0.02)  # the free axis keeps moving
    arm.read()
    assert arm.apply(EefDelta(np.array([0.0, 0.0, -0.01]), ZERO, 0.0)).limits == ()  # back inside: untouched


def test_without_a_driver_target_the_measured_position_is_kept_inside():
    arm = PointArm(pos=(0.79, 0.0, 0.25))
    safe = Safety(arm, SafetyConfig(), 20.0)
    safe.read()
    ran = safe.apply(EefDelta(np.array([0.02, 0.0, 0.0]), ZERO, 0.5))
    assert ran.limits == ("workspace",) and ran.action.dp[0] == pytest.approx(0.01)
    assert arm.pos[0] == pytest.approx(0.8)


def test_an_arm_outside_the_box_is_never_jumped_into_it_only_let_move_towards_it():
    """An arm that starts outside the box (jogged there by hand, a box drawn tighter than where the
    arm rests) moves only towards the box, at the commanded speed. Before, the goal was clipped into
    the box: any command, a zero one too (a deadman hold), jumped the arm into it in one tick, at
    any speed (here 10 cm in 50 ms, 2 m/s against the 0.6 m/s cap)."""
    arm = PointArm(pos=(0.45, 0.0, 0.65))  # 10 cm above the box's top (0.55)
    safe = Safety(arm, SafetyConfig(), 20.0)
    safe.read()
    held = safe.apply(EefDelta(ZERO, ZERO, 0.0))  # a deadman's zero delta: holds still
    assert np.array_equal(held.action.dp, ZERO) and arm.pos[2] == pytest.approx(0.65)
    up = safe.apply(EefDelta(np.array([0.01, 0.0, 0.02]), ZERO, 0.0))  # away from the box: that axis is cut
    assert up.limits == ("workspace",) and np.allclose(up.action.dp, [0.01, 0.0, 0.0])
    down = safe.apply(EefDelta(np.array([0.0, 0.0, -0.02]), ZERO, 0.0))  # towards it: as commanded
    assert down.limits == () and np.allclose(down.action.dp, [0.0, 0.0, -0.02])
    for _ in range(6):  # on into the box, then stopped at its far side as any arm inside is
        ran = safe.apply(EefDelta(np.array([0.0, 0.0, -0.3]), ZERO, 0.0))
        assert abs(ran.action.dp[2]) <= 0.6 / 20 + 1e-12  # never above the speed cap
    assert 0.0 <= arm.pos[2] <= 0.55


def test_holding_before_any_command_keeps_the_gripper_as_it_is():
    """The robot service ticks from its start, holding still until a teleop commands. Its holds
    keep the gripper where it is (closed on an object: closed), as the teleop devices take it over.
    Before, they commanded it open: a robot service (re)started while the gripper held an object
    dropped it before anyone touched a control."""
    for closure, kept in ((0.8, 1.0), (0.1, 0.0)):  # closed on an object; (nearly) open
        arm = PointArm(closure=closure)
        safe = Safety(arm, SafetyConfig(), 20.0)
        safe.read()
        held = safe.apply(None)
        assert held.stale and held.action.gripper == kept and arm.applied[-1].gripper == kept
    ran = safe.apply(EefDelta(ZERO, ZERO, 1.0))  # a command sets the gripper, holds keep the last one
    assert ran.action.gripper == 1.0 and safe.apply(None).action.gripper == 1.0


def test_the_gripper_target_is_clamped():
    safe = Safety(PointArm(), SafetyConfig(), 20.0)
    safe.read()
    ran = safe.apply(EefDelta(ZERO, ZERO, 1.7))
    assert ran.action.gripper == 1.0 and ran.limits == ("gripper",)


def test_no_commands_hold_still_then_stop_the_arm_then_resume():
    arm = PointArm()
    safe = Safety(arm, SafetyConfig(command_timeout_s=0.05), 20.0)
    safe.read()
    safe.apply(EefDelta(np.array([0.01, 0.0, 0.0]), ZERO, 0.8))
    held = safe.apply(None)
    assert held.stale and np.array_equal(held.action.dp, ZERO) and held.action.gripper == 0.8
    assert not safe.stopped and arm.stops == 0  # holding, not yet stopped
    deadline = time.monotonic() + 5.0
    while not safe.stopped and time.monotonic() < deadline:
        safe.apply(None)
    assert safe.stopped and arm.stops == 1
    safe.apply(None)
    assert arm.stops == 1  # stopped once, not on every tick
    ran = safe.apply(EefDelta(np.array([0.0, 0.01, 0.0]), ZERO, 0.8))
    assert not safe.stopped and not ran.stale and arm.applied[-1] is ran.action
    safe.begin_episode()
    assert safe.apply(None).action.gripper == 0.0  # a new episode starts open


class FaultyArm(PointArm):
    """A PointArm whose fault the test sets."""

    fault_text = ""

    def fault(self) -> str:
        return self.fault_text


def test_a_driver_fault_stops_the_arm_once_sends_nothing_and_is_reported_until_it_clears():
    arm = FaultyArm()
    safe = Safety(arm, SafetyConfig(), 20.0)
    safe.read()
    safe.apply(EefDelta(np.array([0.01, 0.0, 0.0]), ZERO, 0.6))
    arm.fault_text = "protective stop"
    ran = [safe.apply(EefDelta(np.array([0.01, 0.0, 0.0]), ZERO, 0.0)), safe.apply(None)]
    assert [r.fault for r in ran] == ["protective stop"] * 2 and [r.stale for r in ran] == [False, True]
    assert all(np.array_equal(r.action.dp, ZERO) and r.action.gripper == 0.6 for r in ran)  # a hold
    assert arm.stops == 1 and safe.faults == 1 and len(arm.applied) == 1  # stopped once; nothing sent
    arm.fault_text = "x" * 1000
    assert len(safe.apply(None).fault) == 200 and arm.stops == 2  # bounded on the wire; a new fault stops again
    arm.fault_text = ""
    ran = safe.apply(EefDelta(np.array([0.01, 0.0, 0.0]), ZERO, 0.0))
    assert ran.fault == "" and safe.fault == "" and arm.applied[-1] is ran.action


def test_a_box_that_is_not_a_box_is_refused():
    with pytest.raises(ValueError, match="workspace_lo"):
        SafetyConfig(workspace_lo=(0.5, 0.0, 0.0), workspace_hi=(0.4, 1.0, 1.0))
