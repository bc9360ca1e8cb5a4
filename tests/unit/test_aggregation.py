"""Multi-view composition (services/policy/aggregation.py) on hand-computed cases and a tiny real model."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from services.core.rig import load_rig
from services.policy.aggregation import (
    CompositionError,
    check_orthogonal,
    compose,
    compose_with_unconditional,
    relative_transforms,
    renormalise,
    to_view,
    view_transform,
    weighted_sum,
)
from services.policy.model import DiffusionPolicy, ModelConfig, make_inference_scheduler, sample

torch.set_num_threads(1)
RIG = load_rig("five15")


def tiny_policy(seed: int = 0) -> DiffusionPolicy:
    torch.manual_seed(seed)
    cfg = ModelConfig(
        image_size=(32, 32),
        state_dim=10,
        down_dims=(16, 32),
        diffusion_step_embed_dim=16,
        encoder={"width": 8, "stage_strides": (1, 2, 1, 1), "num_keypoints": 4, "feature_dim": 8},
    )
    return DiffusionPolicy(cfg).eval()


def composed_sample(policy, obs: dict[str, tuple], transforms, gammas, order, noise, total=None):
    """The composed DDIM loop written out from the docstring's algorithm, on torch tensors."""
    sched = make_inference_scheduler(policy.cfg.noise)
    with torch.no_grad():
        cond = {v: policy.encode(o, s) for v, (o, s) in obs.items()}
    _, G = relative_transforms(transforms, order)
    x = noise.clone()
    with torch.no_grad():
        for k in sched.timesteps.tolist():
            eps = {v: policy.denoise_step_eps(to_view(x, G[v]), k, cond[v]) for v in obs}
            e = weighted_sum(eps, G, gammas, order, total) if total is not None else compose(eps, G, gammas, order)
            x = sched.step(e, k, x).prev_sample
    return x


def observation(seed: int):
    g = torch.Generator().manual_seed(seed)
    return torch.rand((1, 2, 3, 32, 32), generator=g) * 2 - 1, torch.rand((1, 2, 10), generator=g) * 2 - 1


def test_v_identical_views_are_the_single_view_sampler_exactly():
    policy = tiny_policy()
    obs, state = observation(1)
    noise = torch.randn((1, 16, 7), generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        single = sample(policy, obs, state, generator=torch.Generator().manual_seed(5))
    for V in (1, 3, 5):
        views = [f"v{i}" for i in range(V)]
        eye = {v: view_transform("base") for v in views}
        got = composed_sample(policy, {v: (obs, state) for v in views}, eye, {v: 1.0 / V for v in views}, views, noise)
        assert torch.equal(got, single), V


def test_permuting_views_changes_nothing():
    policy = tiny_policy()
    names = ["F", "FL", "FR"]
    obs = {v: observation(i) for i, v in enumerate(names)}
    transforms = {v: view_transform("camera", RIG.cameras[v].R_ext) for v in names}
    gammas = {"F": 0.5, "FL": 0.3, "FR": 0.2}
    noise = torch.randn((1, 16, 7), generator=torch.Generator().manual_seed(2))
    ref = composed_sample(policy, obs, transforms, gammas, names, noise)
    for perm in (["FR", "F", "FL"], ["FL", "FR", "F"]):
        # the canonical order (the checkpoint's) fixes the frame and the summation order ...
        got = composed_sample(
            policy,
            {v: obs[v] for v in perm},
            {v: transforms[v] for v in perm},
            {v: gammas[v] for v in perm},
            names,
            noise,
        )
        assert torch.equal(got, ref)


def test_camera_space_predictions_are_rotated_into_one_frame_by_hand():
    # Two cameras, the reference F and FL. The shared chunk is in F's frame; FL sees it rotated by
    # R_FL R_F^T, and its noise comes back rotated by the transpose. Written out with matrices.
    R_F, R_FL = RIG.cameras["F"].R_ext, RIG.cameras["FL"].R_ext
    rel = R_FL @ R_F.T
    rng = np.random.default_rng(0)
    x = rng.normal(size=(16, 7))
    e_F, e_FL = rng.normal(size=(16, 7)), rng.normal(size=(16, 7))
    transforms = {"F": view_transform("camera", R_F), "FL": view_transform("camera", R_FL)}
    ref, G = relative_transforms(transforms, ["F", "FL"])
    assert ref == "F" and np.array_equal(G["F"], np.eye(7))
    y_FL = to_view(x, G["FL"])
    assert np.allclose(y_FL[:, 0:3], x[:, 0:3] @ rel.T) and np.allclose(y_FL[:, 3:6], x[:, 3:6] @ rel.T)
    assert np.array_equal(y_FL[:, 6], x[:, 6])  # the gripper is not rotated
    eps = compose({"F": e_F, "FL": e_FL}, G, {"F": 0.25, "FL": 0.75}, ["F", "FL"])
    back = e_FL.copy()
    back[:, 0:3] = e_FL[:, 0:3] @ rel  # rel^T applied to each row vector
    back[:, 3:6] = e_FL[:, 3:6] @ rel
    assert np.allclose(eps, 0.25 * e_F + 0.75 * back, atol=1e-12)
    # A motion seen by both cameras (the same base-frame vector) lands on the same shared vector.
    d_base = np.array([0.01, -0.02, 0.005])
    seen = {"F": R_F @ d_base, "FL": R_FL @ d_base}
    for v, d in seen.items():
        assert np.allclose((G[v].T[0:3, 0:3] @ d), R_F @ d_base, atol=1e-12)


def test_weights_summing_to_v_are_v_times_too_large_and_clipping_hides_it():
    policy = tiny_policy(3)
    names = ["F", "FL", "FR"]
    obs = {v: observation(10 + i) for i, v in enumerate(names)}
    eye = {v: view_transform("base") for v in names}
    noise = torch.randn((1, 16, 7), generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        cond = {v: policy.encode(*obs[v]) for v in names}
    _, G = relative_transforms(eye, names)
    with torch.no_grad():
        eps = {v: policy.denoise_step_eps(noise, 90, cond[v]) for v in names}
    ones = {v: 1.0 for v in names}
    assert torch.allclose(weighted_sum(eps, G, ones, names), 3 * compose(eps, G, ones, names), atol=1e-6)
    right = composed_sample(policy, obs, eye, {v: 1 / 3 for v in names}, names, noise)
    wrong = composed_sample(policy, obs, eye, ones, names, noise, total=3.0)
    # Both end inside the [-1, 1] box the x_0 clipping enforces, so the wrong one looks plausible ...
    assert right.abs().max() <= 1.0 + 1e-6 and wrong.abs().max() <= 1.0 + 1e-6
    # ... but it is not the same chunk: compose() renormalises, so the sum-to-V weights give `right`.
    assert (wrong - right).abs().mean() > 0.05
    assert torch.equal(composed_sample(policy, obs, eye, ones, names, noise), right)


def test_a_dropped_view_renormalises_the_rest():
    assert renormalise({"F": 0.5, "FL": 0.3, "FR": 0.2}, ["F", "FR"]) == pytest.approx({"F": 5 / 7, "FR": 2 / 7})
    with pytest.raises(CompositionError, match="sum to zero"):
        renormalise({"F": 0.0, "FL": 1.0}, ["F"])
    with pytest.raises(CompositionError, match="no weight"):
        renormalise({"F": 1.0}, ["F", "FL"])
    # one rule for the server, a request's gamma and eval's --gamma, naming the view
    for bad in (-0.5, float("nan"), float("inf")):
        with pytest.raises(CompositionError, match=f"^the weight of FL must be finite and non-negative, got {bad}$"):
            renormalise({"F": 1.0, "FL": bad}, ["F", "FL"])
        with pytest.raises(CompositionError, match="the weight of FL must be finite"):
            compose_with_unconditional(
                {v: np.ones((2, 7)) for v in ("F", "FL")}, {}, {}, {"F": 1.0, "FL": bad}, ["F", "FL"]
            )
    e = {"F": np.ones((2, 7)), "FR": 3 * np.ones((2, 7))}
    G = {v: np.eye(7) for v in e}
    assert np.allclose(compose(e, G, {"F": 0.5, "FL": 0.3, "FR": 0.2}, ["F", "FL", "FR"]), 1 * 5 / 7 + 3 * 2 / 7)


def test_unconditional_branch_is_the_composable_diffusion_sum():
    rng = np.random.default_rng(1)
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    G = {"F": np.eye(7), "B": view_transform("camera", R)}
    e = {v: rng.normal(size=(4, 7)) for v in G}
    u = {v: rng.normal(size=(4, 7)) for v in G}
    got = compose_with_unconditional(e, u, G, {"F": 1.0, "B": 1.0}, ["F", "B"])
    want = u["F"] + (e["F"] - u["F"]) + (e["B"] - u["B"]) @ G["B"]  # G^T per row = row @ G
    assert np.allclose(got, want)
    convex = compose_with_unconditional(
        e, {v: u["F"] for v in G}, {v: np.eye(7) for v in G}, {"F": 0.5, "B": 0.5}, ["F", "B"]
    )
    assert np.allclose(convex, 0.5 * e["F"] + 0.5 * e["B"])  # convex weights: the unconditional cancels


@dataclass
class ScaleOnly:
    """A normaliser as a foreign checkpoint might hold it: one scale per component."""

    action_scale: np.ndarray
    action_offset: np.ndarray


def test_a_normaliser_that_breaks_orthogonality_is_refused():
    transforms = {"FL": view_transform("camera", RIG.cameras["FL"].R_ext)}
    good = ScaleOnly(np.array([0.03] * 3 + [0.15] * 3 + [0.5]), np.array([0.0] * 6 + [0.5]))
    check_orthogonal(good, transforms)
    per_axis = ScaleOnly(np.array([0.03, 0.02, 0.03, 0.15, 0.15, 0.15, 0.5]), good.action_offset)
    with pytest.raises(CompositionError, match="one number"):
        check_orthogonal(per_axis, transforms)
    offset = ScaleOnly(good.action_scale, np.array([0.001] + [0.0] * 5 + [0.5]))
    with pytest.raises(CompositionError, match="offset"):
        check_orthogonal(offset, transforms)
    check_orthogonal(per_axis, {"F": view_transform("base")})  # nothing rotates: nothing to break
