"""Diffusion policy: schedulers as specified, the one-step call equals the sampling loop's step,
config checks, and the executed slice of a chunk."""

from __future__ import annotations

import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler

from services.policy.model import (
    DiffusionPolicy,
    EncoderConfig,
    ModelConfig,
    action_steps,
    compute_loss,
    denoise_step,
    make_inference_scheduler,
    make_train_scheduler,
    preset,
    sample,
)

torch.set_num_threads(1)


def tiny_config(**kw) -> ModelConfig:
    base = dict(
        image_size=(24, 24),
        state_dim=3,
        down_dims=(16, 32),
        diffusion_step_embed_dim=16,
        encoder=EncoderConfig(width=8, stage_strides=(1, 2, 1, 1), num_keypoints=4, feature_dim=8),
    )
    return ModelConfig(**{**base, **kw})


def obs_batch(B: int = 2, To: int = 2, H: int = 24):
    g = torch.Generator().manual_seed(0)
    return torch.rand(B, To, 3, H, H, generator=g) * 2 - 1, torch.rand(B, To, 3, generator=g) * 2 - 1


def test_schedulers_match_the_paper_baseline():
    cfg = ModelConfig().noise
    train = make_train_scheduler(cfg)
    assert isinstance(train, DDPMScheduler)
    assert train.config.num_train_timesteps == 100
    assert train.config.beta_schedule == "squaredcos_cap_v2"
    assert train.config.prediction_type == "epsilon" and train.config.clip_sample
    infer = make_inference_scheduler(cfg)
    assert isinstance(infer, DDIMScheduler)
    assert len(infer.timesteps) == 10 and infer.timesteps[0] == 90 and infer.timesteps[-1] == 0
    assert len(make_inference_scheduler(cfg, 2).timesteps) == 2


def test_one_step_with_cached_features_equals_the_loops_step():
    torch.manual_seed(0)
    cfg = tiny_config(noise={"num_inference_steps": 3})
    policy = DiffusionPolicy(cfg).eval()
    obs, state = obs_batch()
    steps = []
    chunk = sample(
        policy,
        obs,
        state,
        generator=torch.Generator().manual_seed(3),
        on_step=lambda k, x, eps, x_prev: steps.append((k, x.clone(), eps.clone(), x_prev.clone())),
    )
    assert [s[0] for s in steps] == [66, 33, 0]
    assert torch.equal(chunk, steps[-1][3])

    # What a worker does: encode once, then one call per step from the cached features.
    cond = policy.encode(obs, state)
    assert cond.shape == (2, cfg.cond_dim) == (2, 2 * (8 + 3))
    sched = make_inference_scheduler(cfg.noise)
    for k, x_k, eps_loop, x_prev_loop in steps:
        with torch.no_grad():
            eps = policy.denoise_step_eps(x_k, k, cond)
            x_prev = denoise_step(policy, sched, x_k, k, cond)
        assert torch.allclose(eps, eps_loop, atol=1e-6)
        assert torch.allclose(x_prev, x_prev_loop, atol=1e-6)
    # the step really moves the sample, so the equality above is not trivial
    assert not torch.allclose(steps[0][1], steps[0][3])


def test_sampling_is_reproducible_clipped_and_depends_on_the_observation():
    torch.manual_seed(0)
    policy = DiffusionPolicy(tiny_config()).eval()
    obs, state = obs_batch()
    a = sample(policy, obs, state, generator=torch.Generator().manual_seed(1))
    b = sample(policy, obs, state, generator=torch.Generator().manual_seed(1))
    assert a.shape == (2, 16, 7) and torch.equal(a, b)
    # The last DDIM step returns the clipped x_0 prediction.
    assert a.abs().max() <= 1.0 + 1e-6
    c = sample(policy, -obs, state, generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(a, c)


def test_compute_loss_is_a_scalar_with_gradients_everywhere():
    torch.manual_seed(0)
    policy = DiffusionPolicy(tiny_config())
    obs, state = obs_batch(4)
    sched = make_train_scheduler(policy.cfg.noise)
    loss = compute_loss(policy, sched, {"obs": obs, "state": state, "action": torch.rand(4, 16, 7) * 2 - 1})
    assert loss.dim() == 0 and loss.item() > 0
    loss.backward()
    missing = [n for n, p in policy.named_parameters() if p.requires_grad and p.grad is None]
    assert missing == []


def test_state_is_required_when_configured():
    policy = DiffusionPolicy(tiny_config())
    obs, _ = obs_batch()
    with pytest.raises(ValueError, match="needs state"):
        policy.encode(obs, None)


def test_action_steps_start_at_the_current_observation():
    chunk = torch.arange(16).float().view(1, 16, 1).expand(1, 16, 7)
    out = action_steps(chunk, obs_horizon=2, n_action_steps=8)
    assert out.shape == (1, 8, 7) and out[0, :, 0].tolist() == list(range(1, 9))


def test_config_rejects_inconsistent_shapes():
    with pytest.raises(ValueError, match="multiple of 4"):
        ModelConfig(pred_horizon=10, down_dims=(8, 16, 32))
    with pytest.raises(ValueError, match="n_action_steps"):
        ModelConfig(obs_horizon=2, n_action_steps=16, pred_horizon=16)
    with pytest.raises(ValueError, match="larger than image_size"):
        tiny_config(encoder=EncoderConfig(crop=(30, 30)))
    with pytest.raises(KeyError, match="unknown preset"):
        preset("huge")


def test_presets_build_valid_configs():
    tiny = ModelConfig.model_validate({**preset("tiny")["model"], "image_size": (32, 32)})
    paper = ModelConfig.model_validate(preset("paper")["model"])
    assert paper.down_dims == (512, 1024, 2048) and paper.diffusion_step_embed_dim == 128
    assert paper.kernel_size == 5 and paper.n_groups == 8
    assert tiny.down_dims == (64, 128)
    assert DiffusionPolicy(tiny).num_parameters() < 2_000_000
