"""Action spaces against the paper's math: inverses, matrix forms, camera geometry, EEF timing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from services.core.action_spaces import (
    eef_chunk_to_base,
    from_space,
    resolve_state_frame,
    state_vector,
    to_space,
)
from services.core.geometry import rot6d, rot6d_to_matrix
from services.core.normalizer import Normalizer
from services.core.rig import Camera, load_rig

FAST = settings(max_examples=60, deadline=None)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
# Rotation vectors with angle < pi, so the axis-angle log is unique.
rotvec = arrays(np.float64, 3, elements=st.floats(-1.7, 1.7, allow_nan=False))
actions = arrays(np.float64, (5, 7), elements=finite)


def rot(rv: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rv).as_matrix()


@st.composite
def rotations(draw, n: int | None = None) -> np.ndarray:
    seed = draw(st.integers(0, 2**32 - 1))
    return Rotation.random(n, random_state=seed).as_matrix()


def log(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


@FAST
@given(a=actions, R_ext=rotations(), R_eef=rotations(5))
def test_forward_then_inverse_is_identity_in_every_space(a, R_ext, R_eef):
    for space in ("base", "eef", "camera"):
        back = from_space(to_space(a, space, eef_rot=R_eef, R_ext=R_ext), space, eef_rot=R_eef, R_ext=R_ext)
        np.testing.assert_allclose(back, a, atol=1e-12)


@FAST
@given(a=actions)
def test_camera_space_with_identity_extrinsic_is_base_space(a):
    np.testing.assert_allclose(to_space(a, "camera", R_ext=np.eye(3)), to_space(a, "base"), atol=0)
    np.testing.assert_array_equal(to_space(a, "base"), a)


@FAST
@given(a=actions, R1=rotations(), R2=rotations())
def test_two_views_differ_by_their_relative_rotation(a, R1, R2):
    a1 = to_space(a, "camera", R_ext=R1)
    a2 = to_space(a, "camera", R_ext=R2)
    R_rel = R2 @ R1.T  # view 1 optical frame -> view 2 optical frame
    np.testing.assert_allclose(a2[:, 0:3], a1[:, 0:3] @ R_rel.T, atol=1e-12)
    np.testing.assert_allclose(a2[:, 3:6], a1[:, 3:6] @ R_rel.T, atol=1e-12)
    np.testing.assert_array_equal(a2[:, 6], a[:, 6])


@FAST
@given(dr=rotvec, R_ext=rotations(), R_eef=rotations())
def test_vector_forms_equal_the_papers_matrix_forms(dr, R_ext, R_eef):
    a = np.concatenate([np.zeros(3), dr, [0.5]])
    # camera: Delta R^v = R_ext Delta R R_ext^T
    a_v = to_space(a, "camera", R_ext=R_ext)
    np.testing.assert_allclose(rot(a_v[3:6]), R_ext @ rot(dr) @ R_ext.T, atol=1e-9)
    # EEF: Delta R^EEF = R^T Delta R R
    a_e = to_space(a[None], "eef", eef_rot=R_eef[None])[0]
    np.testing.assert_allclose(rot(a_e[3:6]), R_eef.T @ rot(dr) @ R_eef, atol=1e-9)


def test_camera_space_matches_point_motion_seen_by_a_rig_camera():
    """A world displacement dp moves the point's optical-frame coordinates by exactly dp_v."""
    rig = load_rig("five15")
    rng = np.random.default_rng(0)
    for cam in rig.cameras.values():
        # The camera as rebuilt from its published messages, as the dataset sees it.
        cam2, _ = Camera.from_msgs(cam.calibration_msg(64, 48, 0), cam.pose_msg(0))
        p = np.array([0.5, 0.1, 0.2])
        dp = rng.normal(size=3) * 0.01
        a_v = to_space(np.concatenate([dp, np.zeros(3), [0.0]]), "camera", R_ext=cam2.R_ext)
        moved = cam.to_camera(p + dp) - cam.to_camera(p)
        np.testing.assert_allclose(a_v[0:3], moved, atol=1e-12)
        # And a rotation about the world z axis appears about the camera's image of that axis.
        a_r = to_space(np.array([0, 0, 0, 0, 0, 0.3, 0.0]), "camera", R_ext=cam2.R_ext)
        z_in_cam = cam.to_camera(cam.position + np.array([0.0, 0.0, 1.0]))
        np.testing.assert_allclose(a_r[3:6], 0.3 * z_in_cam, atol=1e-12)
    # The front camera stands on +x looking back along -x: world +y is image right, +z image up.
    F = rig.cameras["F"]
    a = to_space(np.array([0, 0.01, 0.01, 0, 0, 0, 0.0]), "camera", R_ext=F.R_ext)
    assert a[0] > 0 and a[1] < 0


@FAST
@given(
    rvs=arrays(np.float64, (6, 3), elements=st.floats(-0.4, 0.4)),
    dps=arrays(np.float64, (6, 3), elements=finite),
    R0=rotations(),
)
def test_eef_space_uses_the_rotation_at_execution_time(rvs, dps, R0):
    """Roll out base actions (R_{t+1} = Rot(dr_t) R_t, p_{t+1} = p_t + dp_t); the EEF-space
    action of step t must be the step expressed in the EEF frame of its own tick t."""
    T = len(rvs)
    R = [R0]
    p = [np.zeros(3)]
    for t in range(T):
        R.append(rot(rvs[t]) @ R[t])
        p.append(p[t] + dps[t])
    a = np.concatenate([dps, rvs, np.full((T, 1), 0.3)], axis=1)
    a_e = to_space(a, "eef", eef_rot=np.stack(R[:T]))
    for t in range(T):
        np.testing.assert_allclose(a_e[t, 0:3], R[t].T @ (p[t + 1] - p[t]), atol=1e-9)
        np.testing.assert_allclose(rot(a_e[t, 3:6]), R[t].T @ R[t + 1], atol=1e-9)
    # The chunk inverse recovers the base actions from the first rotation alone.
    np.testing.assert_allclose(eef_chunk_to_base(a_e, R0), a, atol=1e-9)


def test_eef_space_with_the_next_ticks_rotation_would_be_wrong():
    """Guards the timing: with a turning EEF, rotation at t and at t+1 give different answers."""
    R0 = np.eye(3)
    dr = np.array([0.0, 0.0, np.pi / 2])
    R1 = rot(dr) @ R0
    a = np.array([[0.1, 0, 0, *dr, 0.0]])
    at_t = to_space(a, "eef", eef_rot=R0[None])[0]
    at_next = to_space(a, "eef", eef_rot=R1[None])[0]
    np.testing.assert_allclose(at_t[0:3], [0.1, 0, 0], atol=1e-12)  # still along the EEF x axis
    assert np.linalg.norm(at_next[0:3] - at_t[0:3]) > 0.1


@FAST
@given(R_ext=rotations(), a=actions, data=arrays(np.float64, (40, 7), elements=finite))
def test_normalised_camera_transform_is_orthogonal(R_ext, a, data):
    """The map a_n -> norm(F^v(unnorm(a_n))) on each 3-vector block is the rotation R_ext itself."""
    norm = Normalizer.fit([data], [np.zeros((1, 10))])

    def F_n(x: np.ndarray) -> np.ndarray:
        return norm.normalize_action(to_space(norm.unnormalize_action(x), "camera", R_ext=R_ext))

    for block in (slice(0, 3), slice(3, 6)):
        M = np.zeros((3, 3))
        for i in range(3):
            e = np.zeros(7)
            e[block.start + i] = 1.0
            zero = np.zeros(7)
            M[:, i] = (F_n(e) - F_n(zero))[block]
            np.testing.assert_allclose(F_n(zero)[block], 0.0, atol=1e-12)  # no offset
        np.testing.assert_allclose(M.T @ M, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(M, R_ext, atol=1e-9)
    # Linear on the blocks: it holds for any normalised action, not just basis vectors.
    a_n = norm.normalize_action(a)
    out = F_n(a_n)
    np.testing.assert_allclose(out[:, 0:3], a_n[:, 0:3] @ R_ext.T, atol=1e-9)
    np.testing.assert_allclose(out[:, 6], a_n[:, 6], atol=1e-12)


def test_camera_frame_state_is_the_eef_pose_seen_by_the_camera():
    cam = load_rig("five15").cameras["FL"]
    rng = np.random.default_rng(1)
    p = rng.normal(size=(4, 3)) * 0.2 + np.array([0.5, 0.0, 0.2])
    R = Rotation.random(4, random_state=2).as_matrix()
    g = np.array([0.0, 0.2, 0.9, 1.0])
    s = state_vector(p, R, g, "camera", R_ext=cam.R_ext, cam_position=cam.position)
    np.testing.assert_allclose(s[:, 0:3], cam.to_camera(p), atol=1e-12)
    np.testing.assert_allclose(rot6d_to_matrix(s[:, 3:9]), cam.R_ext @ R, atol=1e-12)
    np.testing.assert_array_equal(s[:, 9], g)
    base = state_vector(p, R, g, "base")
    np.testing.assert_allclose(base[:, 0:3], p)
    np.testing.assert_allclose(rot6d_to_matrix(base[:, 3:9]), R, atol=1e-12)
    assert rot6d(R).shape == (4, 6)


def test_state_frame_follows_the_action_space_unless_chosen():
    assert resolve_state_frame("auto", "camera") == "camera"
    assert resolve_state_frame("auto", "eef") == "base"
    assert resolve_state_frame("auto", "base") == "base"
    assert resolve_state_frame("base", "camera") == "base"
    with pytest.raises(ValueError, match="unknown action space"):
        resolve_state_frame("auto", "world")
    with pytest.raises(ValueError, match="needs the camera"):
        to_space(np.zeros(7), "camera")
