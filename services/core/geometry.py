"""The one rotation vocabulary of the project: scipy's ``Rotation`` behind a few named helpers.

Conventions (the ones every message and file uses):
- quaternions are (w, x, y, z), scalar first, as ``RobotState.eef_quat_wxyz`` publishes them;
  foxglove's ``FrameTransform`` is the one place with (x, y, z, w) fields, and says so by name;
- a rotation vector (axis-angle) ``r`` has the rotation angle as its length: ``Rot(r)``;
- rotations compose on the left in the base frame: ``R_next = Rot(drot) @ R``;
- ``rot6d`` is the first two columns of a rotation matrix (Zhou et al.), continuous everywhere.
Everything takes a single value or a leading batch dimension and is numpy only. Matrices handed
in are rotations (up to rounding), so scipy's orthogonality check is skipped (``assume_valid``): it
costs 6x the conversion itself, and the IK calls ``rotation_error`` every iteration.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def quat_wxyz_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) w-first quaternions -> (..., 3, 3) rotation matrices."""
    return Rotation.from_quat(np.asarray(q_wxyz, dtype=np.float64), scalar_first=True).as_matrix()


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) unit w-first quaternions (either sign: q and -q are one rotation)."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64), assume_valid=True).as_quat(scalar_first=True)


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle vectors -> (..., 3, 3)."""
    return Rotation.from_rotvec(np.asarray(r, dtype=np.float64)).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) axis-angle vectors (angle in [0, pi])."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64), assume_valid=True).as_rotvec()


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """A product of many rotations, back through a unit quaternion: stops drift from orthonormality."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64), assume_valid=True).as_matrix()


def rotation_error(R_target: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (base frame) of ``R_target @ R.T``: the rotation that takes R to R_target."""
    return matrix_to_rotvec(np.asarray(R_target) @ np.swapaxes(np.asarray(R), -1, -2))


def clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    """``v`` scaled down to length ``limit`` if it is longer."""
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


def rot6d(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns, a continuous rotation representation."""
    R = np.asarray(R)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def rot6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (exact inverse of ``rot6d`` on rotations)."""
    d6 = np.asarray(d6, dtype=np.float64)
    a, b = d6[..., 0:3], d6[..., 3:6]
    x = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - np.sum(x * b, axis=-1, keepdims=True) * x
    y = b / np.linalg.norm(b, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


# -- yaw: rotations about the world z axis (object headings, the gripper's turn) --------------


def rot_z(yaw: float) -> np.ndarray:
    """(3, 3) rotation by ``yaw`` about world z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_quat(yaw: float) -> np.ndarray:
    """(w, x, y, z) quaternion of a rotation by ``yaw`` about world z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def matrix_yaw(R: np.ndarray) -> float:
    """Heading of a frame's x axis in the xy plane (rad)."""
    return math.atan2(R[1, 0], R[0, 0])


def quat_yaw(q_wxyz: np.ndarray) -> float:
    """Heading of a body's x axis in the xy plane (rad), from its (w, x, y, z) quaternion."""
    w, x, y, z = q_wxyz
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def nearest_yaw(target: float, current: float, period: float) -> float:
    """The angle equal to ``target`` modulo ``period`` closest to ``current``."""
    return current + (target - current + period / 2) % period - period / 2
