"""Training loss and sampling of the diffusion policy (DDPM to train, DDIM to sample).

Training (``compute_loss``): pick k ~ U{0, K-1} and eps ~ N(0, I) per chunk, noise the
normalised action chunk a_0 to a_k = sqrt(abar_k) a_0 + sqrt(1 - abar_k) eps (DDPM, K = 100,
squaredcos_cap_v2 betas), and regress eps_theta(a_k, k, cond(o)) on eps with an MSE.

Sampling (``sample``): a_K ~ N(0, I), then for each DDIM timestep k (10 by default)
eps = eps_theta(a_k, k, cond), a_{k-1} = DDIM(eps, k, a_k) with the predicted a_0 clipped to
[-1, 1]. The observation features ``cond`` are computed once; one loop step is exactly
``denoise_step`` (= ``policy.denoise_step_eps`` + the scheduler update), which is what a per-view
worker serves and what multi-view composition calls with eps averaged over views.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from services.policy.model.policy import DiffusionPolicy, NoiseConfig

if TYPE_CHECKING:
    from diffusers import DDIMScheduler, DDPMScheduler

# diffusers is imported where a scheduler is made, not with this module: importing it imports
# torch._dynamo (about 1.5 s of a process's start here), which a denoising worker, that computes
# eps and never steps a scheduler, has no use for.


def make_train_scheduler(cfg: NoiseConfig) -> DDPMScheduler:
    from diffusers import DDPMScheduler

    return DDPMScheduler(
        num_train_timesteps=cfg.num_train_timesteps,
        beta_schedule=cfg.beta_schedule,
        clip_sample=cfg.clip_sample,
        prediction_type=cfg.prediction_type,
    )


def make_inference_scheduler(cfg: NoiseConfig, num_inference_steps: int | None = None) -> DDIMScheduler:
    from diffusers import DDIMScheduler

    sched = DDIMScheduler(
        num_train_timesteps=cfg.num_train_timesteps,
        beta_schedule=cfg.beta_schedule,
        clip_sample=cfg.clip_sample,
        prediction_type=cfg.prediction_type,
        set_alpha_to_one=True,
        steps_offset=0,
    )
    sched.set_timesteps(num_inference_steps or cfg.num_inference_steps)
    return sched


def compute_loss(
    policy: DiffusionPolicy, scheduler: DDPMScheduler, batch: dict[str, torch.Tensor], cond_dropout: float = 0.0
) -> torch.Tensor:
    """Epsilon-prediction MSE on one batch: obs (B, To, 3, H, W), state (B, To, Ds), action (B, Tp, Da).

    ``cond_dropout``: the share of samples whose conditioning is replaced by zeros, so the same
    network also learns the unconditional noise eps(x_k, k, 0) (for composing views as an exact
    product, ``services.policy.aggregation.compose_with_unconditional``).
    """
    actions = batch["action"]  # (B, Tp, Da)
    B = actions.shape[0]
    cond = policy.encode(batch["obs"], batch.get("state"))  # (B, Dc)
    if cond_dropout > 0:
        keep = torch.rand(B, device=cond.device) >= cond_dropout  # (B,)
        cond = cond * keep[:, None].to(cond.dtype)
    noise = torch.randn(actions.shape, device=actions.device, dtype=actions.dtype)  # (B, Tp, Da)
    k = torch.randint(0, scheduler.config.num_train_timesteps, (B,), device=actions.device).long()  # (B,)
    noisy = scheduler.add_noise(actions, noise, k)  # (B, Tp, Da)
    pred = policy.denoise_step_eps(noisy, k, cond)  # (B, Tp, Da)
    target = noise if scheduler.config.prediction_type == "epsilon" else actions
    return F.mse_loss(pred.float(), target.float())


def denoise_step(
    policy: DiffusionPolicy, scheduler: DDIMScheduler, x_k: torch.Tensor, k: int, cond: torch.Tensor
) -> torch.Tensor:
    """One sampling step from cached features: (B, Tp, Da) a_k -> (B, Tp, Da) a_{k-1}."""
    eps = policy.denoise_step_eps(x_k, k, cond)  # (B, Tp, Da)
    return scheduler.step(eps, k, x_k).prev_sample


@torch.no_grad()
def sample(
    policy: DiffusionPolicy,
    obs: torch.Tensor,
    state: torch.Tensor | None = None,
    scheduler: DDIMScheduler | None = None,
    generator: torch.Generator | None = None,
    on_step: Callable[[int, torch.Tensor, torch.Tensor, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Sample a normalised action chunk (B, Tp, Da) for obs (B, To, 3, H, W) and state (B, To, Ds).

    ``on_step(k, x_k, eps, x_prev)`` is called after every denoising step (for inspection/tests).
    """
    cfg = policy.cfg
    scheduler = scheduler or make_inference_scheduler(cfg.noise)
    cond = policy.encode(obs, state)  # (B, Dc), once for all steps
    B = obs.shape[0]
    x = torch.randn(
        (B, cfg.pred_horizon, cfg.action_dim), generator=generator, device=obs.device, dtype=cond.dtype
    )  # (B, Tp, Da) a_K
    for k in scheduler.timesteps.tolist():
        eps = policy.denoise_step_eps(x, k, cond)  # (B, Tp, Da)
        x_prev = scheduler.step(eps, k, x).prev_sample
        if on_step is not None:
            on_step(k, x, eps, x_prev)
        x = x_prev
    return x


def action_steps(chunk: torch.Tensor, obs_horizon: int, n_action_steps: int) -> torch.Tensor:
    """The actions to execute from a predicted chunk: (B, Tp, Da) -> (B, n_action_steps, Da),
    starting at the current observation step (index To - 1), as in diffusion_policy."""
    start = obs_horizon - 1
    return chunk[:, start : start + n_action_steps]
