"""The diffusion policy model, torch only: encoder, noise U-Net, loss and sampling, presets.

Public API::

    policy = DiffusionPolicy(ModelConfig(...))
    loss = compute_loss(policy, make_train_scheduler(cfg.noise), batch)   # training
    cond = policy.encode(obs, state)                                      # once per observation
    eps = policy.denoise_step_eps(x_k, k, cond)                           # one denoising step
    chunk = sample(policy, obs, state)                                    # the whole DDIM loop

Names are imported lazily, so ``services.policy.model.normalizer`` (numpy only) can be used
without importing torch.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "DiffusionPolicy": "policy",
    "ModelConfig": "policy",
    "NoiseConfig": "policy",
    "EncoderConfig": "encoder",
    "PRESETS": "presets",
    "preset": "presets",
    "action_steps": "diffusion",
    "compute_loss": "diffusion",
    "denoise_step": "diffusion",
    "make_inference_scheduler": "diffusion",
    "make_train_scheduler": "diffusion",
    "sample": "diffusion",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
