"""Scripted experts finish their tasks within the horizon on a few seeds (the 50-seed rates are
in bench/expert_success.py), seeing only the snapshot and the object poses."""

import math

import numpy as np
import pytest

from services.core.geometry import matrix_to_rotvec as rot_log
from services.core.geometry import nearest_yaw, rot_z
from services.core.geometry import quat_wxyz_to_matrix as quat_to_mat
from services.core.rig import load_rig
from services.core.robot_types import ObjectPose, RobotSnapshot
from sim.experts import make_expert
from sim.world import SimWorld


@pytest.mark.parametrize("task", ["lift", "can", "square"])
def test_expert_succeeds_within_the_horizon(task):
    expert = make_expert(task)
    with SimWorld(task, load_rig("front")) as world:
        for seed in (11, 12, 13):
            world.reset(seed)
            expert.reset()
            assert not world.success()
            for _ in range(world.horizon):
                robot, objects = world.robot(), world.objects()
                # What the wire carries: frozen snapshots of plain arrays.
                assert isinstance(robot, RobotSnapshot) and all(isinstance(o, ObjectPose) for o in objects.values())
                dp, drot, gripper = expert.act(robot, objects)
                assert dp.shape == (3,) and drot.shape == (3,) and 0.0 <= gripper <= 1.0
                world.step(dp, drot, gripper)
                if world.success():
                    break
            assert world.success(), f"{task} seed {seed}: stuck in phase {expert.phase}"


def test_holding_still_solves_no_task():
    # Success needs the expert: holding still leaves every task unsolved.
    for task in ("lift", "can", "square"):
        with SimWorld(task, load_rig("front")) as world:
            world.reset(5)
            for _ in range(20):
                world.step(np.zeros(3), np.zeros(3), 0.0)
            assert not world.success()


def test_geometry_helpers():
    assert nearest_yaw(math.radians(80), 0.0, math.pi / 2) == pytest.approx(math.radians(-10))
    assert nearest_yaw(math.radians(100), 0.0, math.pi) == pytest.approx(math.radians(-80))
    R = rot_z(0.3) @ quat_to_mat(np.array([0.0, 1.0, 0.0, 0.0]))
    assert np.allclose(quat_to_mat(np.array([0.0, 1.0, 0.0, 0.0])), np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(rot_log(R @ quat_to_mat(np.array([0.0, 1.0, 0.0, 0.0])).T), [0.0, 0.0, 0.3])
    half_turn = rot_log(np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(np.abs(half_turn), [math.pi, 0.0, 0.0])
