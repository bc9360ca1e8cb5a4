"""UR poses ``[x, y, z, rx, ry, rz]`` (a rotation vector) <-> this project's position + w-first
quaternion, and the EEF delta on a target pose: hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.robot_types import EefDelta
from services.robot.ur import apply_delta, pos_matrix_to_ur_pose, ur_pose_to_pos_matrix, ur_pose_to_pos_quat

S = math.sqrt(0.5)
PI = math.pi


@pytest.mark.parametrize(
    "rotvec, quat_wxyz, matrix",
    [
        ([0, 0, 0], [1, 0, 0, 0], np.eye(3)),
        ([0, 0, PI / 2], [S, 0, 0, S], [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # 90 deg about z
        ([0, PI, 0], [0, 0, 1, 0], np.diag([-1, 1, -1])),  # tool pointing down, UR's usual pose
        ([PI, 0, 0], [0, 1, 0, 0], np.diag([1, -1, -1])),
        ([0, 0, 3 * PI / 2], [S, 0, 0, -S], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]),  # 270 deg = -90 deg
        # 120 deg about (1, 1, 1)/sqrt(3): x -> y -> z -> x; the quaternion is (cos 60, sin 60 / sqrt 3 (1, 1, 1))
        ([2 * PI / 3 / math.sqrt(3)] * 3, [0.5, 0.5, 0.5, 0.5], [[0, 0, 1], [1, 0, 0], [0, 1, 0]]),
    ],
)
def test_ur_rotation_vectors_to_quaternions_and_matrices(rotvec, quat_wxyz, matrix):
    p, q = ur_pose_to_pos_quat([0.1, -0.2, 0.3, *rotvec])
    assert np.allclose(p, [0.1, -0.2, 0.3]) and np.allclose(q, quat_wxyz, atol=1e-12)
    p, R = ur_pose_to_pos_matrix([0.1, -0.2, 0.3, *rotvec])
    assert np.allclose(R, matrix, atol=1e-12)
    back = pos_matrix_to_ur_pose(p, R)
    assert np.allclose(back[:3], [0.1, -0.2, 0.3])
    assert np.linalg.norm(back[3:]) <= PI + 1e-12  # the angle comes back in [0, pi]
    assert np.allclose(ur_pose_to_pos_matrix(back)[1], matrix, atol=1e-12)  # the same rotation


def test_a_delta_composes_on_the_left_in_the_base_frame():
    # Tool down, turned 90 deg about base z: Rz(90) @ diag(-1, 1, -1) = [[0, -1, 0], [-1, 0, 0], [0, 0, -1]],
    # a half turn about (1, -1, 0)/sqrt(2): UR pose rotation vector +-pi (1, -1, 0)/sqrt(2).
    p, R = ur_pose_to_pos_matrix([0.4, 0.0, 0.2, 0, PI, 0])
    p2, R2 = apply_delta(p, R, EefDelta(np.array([0.01, -0.02, 0.03]), np.array([0, 0, PI / 2]), 0.0))
    assert np.allclose(p2, [0.41, -0.02, 0.23])
    assert np.allclose(R2, [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-12)
    pose = pos_matrix_to_ur_pose(p2, R2)
    axis = np.array([1.0, -1.0, 0.0]) * PI * S
    assert np.allclose(pose[3:], axis, atol=1e-9) or np.allclose(pose[3:], -axis, atol=1e-9)
    # About base x, not the tool's x: the tool's z axis (pointing down) turns to base +y.
    _, R3 = apply_delta(p, R, EefDelta(np.zeros(3), np.array([PI / 2, 0, 0]), 0.0))
    assert np.allclose(R3 @ [0, 0, 1], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize("pose", [[0, 0, 0, 0, 0], [0, 0, 0, 0, 0, float("nan")], [0] * 7])
def test_a_malformed_ur_pose_is_refused(pose):
    with pytest.raises(ValueError, match="6 finite numbers"):
        ur_pose_to_pos_matrix(pose)
