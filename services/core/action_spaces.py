"""The paper's three action spaces for pseudo-demonstrations, and their exact inverses.

An action is a 7-vector ``(dp, drot, gripper)``: translation dp (m) and rotation drot
(axis-angle, rad) in the robot base frame, gripper closure in [0, 1]. Rotation composes on the
left in the base frame: ``R_next = Rot(drot) @ R``.

Spaces (paper, "Robot Actions in View-Scaled Imitation Learning"):

- ``base``:   a^v = a                                       (a copy, the same for every view)
- ``eef``:    dp_e = R^T dp,     dr_e = R^T dr              (R: EEF rotation at the step the
                                                             action executes, i.e. the state of
                                                             the same tick)
- ``camera``: dp_v = R_ext dp,   dr_v = R_ext dr            (R_ext: the world-to-camera
                                                             rotation, ``Camera.R_ext``)

The paper writes the rotation parts as matrices, ``R^T dR R`` and ``R_ext dR R_ext^T``; for an
axis-angle vector these are the same thing, because ``Rot(M r) = M Rot(r) M^T`` for any rotation
M. So every space is one rotation M applied to both 3-vector blocks, the gripper is copied, and
the inverse applies M^T. Because M is orthogonal and the normalizer scales each block by one
number with no offset, the same M is the transform in normalised space too.

Robot state inputs (EEF position, rotation, gripper) are expressed in a frame chosen by
``state_frame``: ``base``, or ``camera`` (the EEF pose in the view's optical frame,
``p_c = R_ext (p - position)``, ``R_c = R_ext R``). The EEF pose in its own frame is the identity,
so the EEF space has no state frame of its own and uses ``base``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from services.core.geometry import rot6d, rotvec_to_matrix

ActionSpace = Literal["base", "eef", "camera"]
StateFrame = Literal["base", "camera"]
SPACES: tuple[str, ...] = ("base", "eef", "camera")
STATE_FRAMES: tuple[str, ...] = ("auto", "base", "camera")

ACTION_DIM = 7  # dp (3), drot (3), gripper (1)
STATE_NAMES: tuple[str, ...] = (
    "pos_x",
    "pos_y",
    "pos_z",
    "rot6d_0",
    "rot6d_1",
    "rot6d_2",
    "rot6d_3",
    "rot6d_4",
    "rot6d_5",
    "gripper",
)
STATE_DIM = len(STATE_NAMES)


def check_space(space: str) -> ActionSpace:
    if space not in SPACES:
        raise ValueError(f"unknown action space {space!r}; choose one of {', '.join(SPACES)}")
    return space  # type: ignore[return-value]


def resolve_state_frame(state_frame: str, space: str) -> StateFrame:
    """``auto`` follows the action space: camera space sees the EEF in the camera frame."""
    if state_frame not in STATE_FRAMES:
        raise ValueError(f"unknown state frame {state_frame!r}; choose one of {', '.join(STATE_FRAMES)}")
    if state_frame == "auto":
        return "camera" if check_space(space) == "camera" else "base"
    return state_frame  # type: ignore[return-value]


def needs_calibration(space: str, state_frame: str) -> bool:
    """Whether actions or states are in a camera's frame, so that each camera's extrinsics turn
    them (a dataset needs the calibration; a served policy must be given where its cameras are)."""
    return space == "camera" or state_frame == "camera"


def space_rotation(space: str, *, eef_rot: np.ndarray | None = None, R_ext: np.ndarray | None = None) -> np.ndarray:
    """The rotation M with a^v = (M dp, M dr, g): (3, 3), or (N, 3, 3) for per-step EEF rotations."""
    space = check_space(space)
    if space == "base":
        return np.eye(3)
    if space == "eef":
        if eef_rot is None:
            raise ValueError("the eef action space needs the EEF rotation at each step")
        return np.swapaxes(np.asarray(eef_rot, dtype=np.float64), -1, -2)
    if R_ext is None:
        raise ValueError("the camera action space needs the camera's R_ext (calibration)")
    return np.asarray(R_ext, dtype=np.float64)


def rotate_action(actions: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Apply M to the dp and drot blocks of (..., 7) actions; the gripper is copied.

    M is (3, 3) for all actions or (..., 3, 3) per action.
    """
    a = np.asarray(actions, dtype=np.float64)
    if a.shape[-1] != ACTION_DIM:
        raise ValueError(f"actions must end in {ACTION_DIM} components, got shape {a.shape}")
    out = a.copy()
    out[..., 0:3] = np.einsum("...ij,...j->...i", M, a[..., 0:3])
    out[..., 3:6] = np.einsum("...ij,...j->...i", M, a[..., 3:6])
    return out


def to_space(
    actions: np.ndarray, space: str, *, eef_rot: np.ndarray | None = None, R_ext: np.ndarray | None = None
) -> np.ndarray:
    """Base-frame actions (..., 7) -> actions in ``space`` (the paper's F^v).

    eef_rot: (..., 3, 3) EEF rotation (base frame) at the step each action executes.
    R_ext: (3, 3) world-to-camera rotation of the view.
    """
    return rotate_action(actions, space_rotation(space, eef_rot=eef_rot, R_ext=R_ext))


def from_space(
    actions: np.ndarray, space: str, *, eef_rot: np.ndarray | None = None, R_ext: np.ndarray | None = None
) -> np.ndarray:
    """Actions in ``space`` (..., 7) -> base-frame actions (F^v inverse)."""
    M = space_rotation(space, eef_rot=eef_rot, R_ext=R_ext)
    return rotate_action(actions, np.swapaxes(M, -1, -2))


def eef_chunk_to_base(actions_eef: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """A predicted chunk (T, 7) in EEF space -> base frame, starting from the current rotation R0.

    At inference only the current rotation is known; the rotation at each later step follows
    from the chunk itself: R_{k+1} = Rot(dr_k) R_k with dr_k = R_k dr_e_k, i.e.
    R_{k+1} = R_k Rot(dr_e_k).
    """
    a = np.asarray(actions_eef, dtype=np.float64)
    R = np.asarray(R0, dtype=np.float64)
    out = np.empty_like(a)
    for k in range(a.shape[0]):
        out[k] = rotate_action(a[k], R)
        R = R @ rotvec_to_matrix(a[k, 3:6])
    return out


def state_vector(
    eef_pos: np.ndarray,
    eef_rot: np.ndarray,
    gripper: np.ndarray,
    frame: str,
    *,
    R_ext: np.ndarray | None = None,
    cam_position: np.ndarray | None = None,
) -> np.ndarray:
    """Robot state (N, STATE_DIM): EEF position, rotation (6D), gripper, in ``frame``.

    eef_pos (N, 3) and eef_rot (N, 3, 3) are in the base frame; gripper (N,).
    """
    pos = np.asarray(eef_pos, dtype=np.float64)
    rot = np.asarray(eef_rot, dtype=np.float64)
    if frame == "camera":
        if R_ext is None or cam_position is None:
            raise ValueError("a camera-frame state needs the camera's R_ext and position (calibration)")
        R_ext = np.asarray(R_ext, dtype=np.float64)
        pos = (pos - np.asarray(cam_position, dtype=np.float64)) @ R_ext.T
        rot = R_ext @ rot
    elif frame != "base":
        raise ValueError(f"unknown state frame {frame!r}")
    g = np.asarray(gripper, dtype=np.float64).reshape(-1, 1)
    return np.concatenate([pos, rot6d(rot), g], axis=-1)
