"""A fixed camera's pose in the robot base (= world) frame, two ways.

Board at a measured pose: the board lies still where its pose in the base frame is known
(``T_base_board``: measured, or touched off with the robot); ``solvePnP`` on every corner of
every image of it gives ``T_cam_board``, and ``T_base_cam = T_base_board @ inv(T_cam_board)``.

Hand-eye, board on the gripper (eye-to-hand): for each image i the robot reports the gripper
pose ``A_i = T_base_gripper`` and ``solvePnP`` gives ``B_i = T_cam_board``; the unknowns are the
camera pose ``X = T_base_cam`` and the board's mount on the gripper ``Y = T_gripper_board``,
with ``X B_i = A_i Y`` for every i. Pairs of images give ``(A_j inv(A_i)) X = X (B_j inv(B_i))``,
the classic AX = XB, solved in closed form (``cv2.calibrateHandEye`` where the installed OpenCV
has it, otherwise Park and Martin's method: rotation by aligning the motions' rotation axes,
translation by linear least squares); X and Y are then refined together by minimising the
corners' reprojection error over all images. The gripper must rotate about at least two
different axes across the poses, or the camera's position along the rotation axis is not
determined.

Poses are 4x4 homogeneous matrices; ``R_wc`` is the camera-to-base rotation with the OpenCV
optical axes as columns (``services/core/rig.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from services.calibration.charuco import (
    BoardSpec,
    CalibrationError,
    Detection,
    Intrinsics,
    describe_skipped,
    detect,
    usable,
)

MIN_BOARD_FRACTION = 0.5  # corners of the board at a measured pose that must be found
MIN_HAND_EYE_POSES = 5  # gripper poses a hand-eye calibration needs


@dataclass
class Extrinsics:
    position: np.ndarray  # (3,) optical centre in the base frame (m)
    R_wc: np.ndarray  # (3, 3) camera -> base
    rms_px: float  # RMS reprojection error of the corners with this pose
    used: list[str]  # images used
    mount: np.ndarray | None = None  # hand-eye: (4, 4) T_gripper_board, the board's mount found


def pose_matrix(position, quat_wxyz) -> np.ndarray:
    q = np.asarray(quat_wxyz, np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise CalibrationError(f"quat_wxyz must be 4 finite numbers, not all zero, got {list(quat_wxyz)}")
    p = np.asarray(position, np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise CalibrationError(f"position must be 3 finite numbers, got {list(position)}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    T[:3, 3] = p
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _rt(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def _pnp(det: Detection, intr: Intrinsics) -> np.ndarray:
    """T_cam_board from one view's corners."""
    ok, rvec, tvec = cv2.solvePnP(det.object_points, det.image_points, intr.K, intr.D, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError(f"solvePnP failed on {det.label}")
    rvec, tvec = cv2.solvePnPRefineLM(det.object_points, det.image_points, intr.K, intr.D, rvec, tvec)
    return _rt(rvec, tvec)


def _project(T_cam_board: np.ndarray, obj: np.ndarray, intr: Intrinsics) -> np.ndarray:
    rvec = cv2.Rodrigues(T_cam_board[:3, :3])[0]
    uv, _ = cv2.projectPoints(obj, rvec, T_cam_board[:3, 3], intr.K, intr.D)
    return uv.reshape(-1, 2)


def _rms(residuals: np.ndarray) -> float:
    r = residuals.reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def from_board_pose(
    camera: str,
    board: BoardSpec,
    intr: Intrinsics,
    images: list[tuple[str, np.ndarray]],
    T_base_board: np.ndarray,
) -> Extrinsics:
    """The camera pose from images of the board lying still at ``T_base_board``."""
    dets, skipped = [], {}
    need = max(int(np.ceil(MIN_BOARD_FRACTION * board.n_corners)), 6)
    for label, image in images:
        if image.shape[:2] != (intr.height, intr.width):
            raise CalibrationError(
                f"camera {camera}: {label} is {image.shape[1]}x{image.shape[0]} but its intrinsics are for "
                f"{intr.width}x{intr.height}"
            )
        det = detect(board, image, label)
        why = usable(board, det, need)
        if why:
            skipped[label] = why
        else:
            dets.append(det)
    if not dets:
        raise CalibrationError(
            f"camera {camera}: the board at its measured pose is not usable in any image: "
            f"{describe_skipped(skipped)}; at least {need} of {board.n_corners} corners must be seen"
        )
    obj = np.concatenate([d.object_points for d in dets])
    img = np.concatenate([d.image_points for d in dets])
    # Board and camera are still: every image is the same view, so one PnP over all corners.
    T_cb = _pnp(Detection("all", np.zeros(0), obj, img), intr)
    rms = _rms(_project(T_cb, obj, intr) - img)
    T = T_base_board @ _inv(T_cb)
    return Extrinsics(T[:3, 3].copy(), T[:3, :3].copy(), rms, [d.label for d in dets])


def _solve_ax_xb(A: list[np.ndarray], B: list[np.ndarray]) -> np.ndarray:
    """X with A_k X = X B_k for motion pairs (Park and Martin 1994)."""
    alpha = np.array([Rotation.from_matrix(a[:3, :3]).as_rotvec() for a in A])
    beta = np.array([Rotation.from_matrix(b[:3, :3]).as_rotvec() for b in B])
    # R_X beta_k = alpha_k: orthogonal Procrustes.
    H = beta.T @ alpha
    u, _, vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    # (R_A - I) t_X = R_X t_B - t_A
    M = np.concatenate([a[:3, :3] - np.eye(3) for a in A])
    v = np.concatenate([R @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    t = np.linalg.lstsq(M, v, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, t
    return X


def _initial_hand_eye(gripper: list[np.ndarray], board_in_cam: list[np.ndarray]) -> np.ndarray:
    """T_base_cam in closed form."""
    if hasattr(cv2, "calibrateHandEye"):
        # Eye-to-hand: hand OpenCV base->gripper as "gripper2base"; it returns cam->base.
        base2gripper = [_inv(g) for g in gripper]
        R, t = cv2.calibrateHandEye(
            [g[:3, :3] for g in base2gripper],
            [g[:3, 3] for g in base2gripper],
            [b[:3, :3] for b in board_in_cam],
            [b[:3, 3] for b in board_in_cam],
            method=cv2.CALIB_HAND_EYE_PARK,
        )
        X = np.eye(4)
        X[:3, :3], X[:3, 3] = R, np.asarray(t).reshape(3)
        return X
    A, B = [], []
    n = len(gripper)
    for i in range(n):
        for j in range(i + 1, n):
            A.append(gripper[j] @ _inv(gripper[i]))
            B.append(board_in_cam[j] @ _inv(board_in_cam[i]))
    return _solve_ax_xb(A, B)


def _pack(T: np.ndarray) -> np.ndarray:
    return np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]


def _unpack(x: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:6]
    return T


def hand_eye(
    camera: str,
    board: BoardSpec,
    intr: Intrinsics,
    images: list[tuple[str, np.ndarray]],
    gripper_poses: dict[str, np.ndarray],
) -> Extrinsics:
    """The fixed camera's pose from images of the board mounted on the gripper at known poses.

    ``gripper_poses``: image file stem -> T_base_gripper (4x4) as the robot reported it.
    """
    dets, poses, skipped = [], [], {}
    for label, image in images:
        stem = label.rsplit(".", 1)[0]
        if stem not in gripper_poses:
            raise CalibrationError(f"camera {camera}: no gripper pose for image {label} in the poses file")
        det = detect(board, image, label)
        why = usable(board, det)
        if why:
            skipped[label] = why
            continue
        dets.append(det)
        poses.append(gripper_poses[stem])
    if len(dets) < MIN_HAND_EYE_POSES:
        raise CalibrationError(
            f"camera {camera}: the board on the gripper is usable in only {len(dets)} of {len(images)} images, "
            f"at least {MIN_HAND_EYE_POSES} needed" + (f" ({describe_skipped(skipped)})" if skipped else "")
        )
    B = [_pnp(d, intr) for d in dets]
    X0 = _initial_hand_eye(poses, B)
    Y0 = np.mean([_inv(a) @ X0 @ b for a, b in zip(poses, B)], axis=0)  # T_gripper_board per view, averaged
    u, _, vt = np.linalg.svd(Y0[:3, :3])
    Y0[:3, :3] = u @ vt
    Y0[3] = [0, 0, 0, 1]

    def residuals(x: np.ndarray) -> np.ndarray:
        X, Y = _unpack(x[:6]), _unpack(x[6:])
        out = [_project(_inv(X) @ a @ Y, d.object_points, intr) - d.image_points for a, d in zip(poses, dets)]
        return np.concatenate(out).reshape(-1)

    fit = least_squares(residuals, np.r_[_pack(X0), _pack(Y0)], method="lm", x_scale="jac")
    X, Y = _unpack(fit.x[:6]), _unpack(fit.x[6:])
    return Extrinsics(X[:3, 3].copy(), X[:3, :3].copy(), _rms(fit.fun), [d.label for d in dets], mount=Y)
