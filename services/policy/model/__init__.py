"""The diffusion policy model, torch only: encoder, noise U-Net, loss and sampling, presets.

Public API::

    policy = DiffusionPolicy(ModelConfig(...))
    loss = compute_loss(policy, make_train_scheduler(cfg.noise), batch)   # training
    cond = policy.encode(obs, state)                                      # once per observation
    eps = policy.denoise_step_eps(x_k, k, cond)                           # one denoising step
    chunk = sample(policy, obs, state)                                    # the whole DDIM loop

The normaliser that maps data into the model's units is numpy only and lives in
``services.core.normalizer``.
"""

from services.policy.model.diffusion import (
    action_steps,
    compute_loss,
    denoise_step,
    make_inference_scheduler,
    make_train_scheduler,
    sample,
)
from services.policy.model.encoder import EncoderConfig
from services.policy.model.policy import DiffusionPolicy, ModelConfig, NoiseConfig
from services.policy.model.presets import PRESETS, preset

__all__ = [
    "PRESETS",
    "DiffusionPolicy",
    "EncoderConfig",
    "ModelConfig",
    "NoiseConfig",
    "action_steps",
    "compute_loss",
    "denoise_step",
    "make_inference_scheduler",
    "make_train_scheduler",
    "preset",
    "sample",
]
