"""Normalizer: bounds, isotropy (rotations commute with it), exact inverse, JSON round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from services.core.normalizer import Normalizer, NormalizerStats

FAST = settings(max_examples=60, deadline=None)
acts = arrays(np.float64, (30, 7), elements=st.floats(-2.0, 2.0, allow_nan=False)).map(
    lambda a: np.concatenate([a[:, :6], np.abs(a[:, 6:]) / 2.0], axis=1)  # gripper in [0, 1]
)
states = arrays(np.float64, (30, 4), elements=st.floats(-5.0, 5.0, allow_nan=False))


@FAST
@given(a=acts, s=states, seed=st.integers(0, 2**32 - 1))
def test_no_normalised_component_exceeds_one_in_any_frame(a, s, seed):
    """Fitted on base-frame data, the bound still holds after any rotation of the blocks, which is
    what a held-out camera view does to the actions."""
    n = Normalizer.fit([a], [s])
    R = Rotation.random(random_state=seed).as_matrix()
    for x in (a, np.concatenate([a[:, :3] @ R.T, a[:, 3:6] @ R.T, a[:, 6:]], axis=1)):
        assert np.abs(n.normalize_action(x)).max() <= 1.0 + 1e-12


@FAST
@given(a=acts, s=states)
def test_block_scale_is_tight_and_isotropic(a, s):
    n = Normalizer.fit([a[:10], a[10:]], [s])
    a_n = n.normalize_action(a)
    for block in (slice(0, 3), slice(3, 6)):
        norms = np.linalg.norm(a[:, block], axis=1)
        if norms.max() > 1e-6:
            # the largest vector lands exactly on the unit sphere
            assert np.linalg.norm(a_n[:, block], axis=1).max() == pytest.approx(1.0)
        sc = n.action_scale[block]
        assert sc[0] == sc[1] == sc[2]
    np.testing.assert_array_equal(n.action_offset[:6], 0.0)


@FAST
@given(a=acts, s=states, seed=st.integers(0, 2**32 - 1))
def test_rotations_commute_with_normalisation(a, s, seed):
    n = Normalizer.fit([a], [s])
    R = Rotation.random(random_state=seed).as_matrix()

    def rotate(x):
        return np.concatenate([x[:, :3] @ R.T, x[:, 3:6] @ R.T, x[:, 6:]], axis=1)

    np.testing.assert_allclose(n.normalize_action(rotate(a)), rotate(n.normalize_action(a)), atol=1e-12)


@FAST
@given(a=acts, s=states)
def test_round_trips(a, s):
    n = Normalizer.fit([a], [s])
    np.testing.assert_allclose(n.unnormalize_action(n.normalize_action(a)), a, atol=1e-12)
    np.testing.assert_allclose(n.unnormalize_state(n.normalize_state(s)), s, atol=1e-12)
    back = Normalizer.from_dict(json.loads(json.dumps(n.to_dict())))
    np.testing.assert_array_equal(back.normalize_action(a), n.normalize_action(a))
    np.testing.assert_array_equal(back.normalize_state(s), n.normalize_state(s))


def test_state_min_max_maps_to_minus_one_one_and_constant_components_to_zero():
    s = np.array([[0.0, 10.0, 3.0], [2.0, 20.0, 3.0], [1.0, 15.0, 3.0]])
    n = Normalizer.fit([np.zeros((1, 7))], [s])
    s_n = n.normalize_state(s)
    np.testing.assert_allclose(s_n[:, 0], [-1, 1, 0])
    np.testing.assert_allclose(s_n[:, 1], [-1, 1, 0])
    np.testing.assert_allclose(s_n[:, 2], [0, 0, 0])


def test_gripper_and_images_map_to_minus_one_one():
    a = np.array([[0.01, 0, 0, 0, 0.1, 0, 0.0], [0, 0.02, 0, 0, 0, 0, 1.0]])
    n = Normalizer.fit([a], [np.zeros((2, 1))])
    np.testing.assert_allclose(n.normalize_action(a)[:, 6], [-1.0, 1.0])
    img = np.array([0, 255, 127.5])
    np.testing.assert_allclose(n.normalize_image(img), [-1.0, 1.0, 0.0])
    assert n.normalize_image(np.zeros((2, 2), np.uint8)).dtype == np.float32


def test_a_block_that_never_moves_keeps_a_unit_scale():
    a = np.zeros((5, 7))
    n = Normalizer.fit([a], [np.ones((5, 2))])
    assert n.pos_scale == 1.0 and n.rot_scale == 1.0
    np.testing.assert_array_equal(n.normalize_action(a)[:, :6], 0.0)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="NaN"):
        NormalizerStats().add_actions(np.full((1, 7), np.nan))
    with pytest.raises(ValueError, match="no robot states"):
        NormalizerStats().normalizer()
    with pytest.raises(ValueError, match="version"):
        Normalizer.from_dict({"version": 99})
