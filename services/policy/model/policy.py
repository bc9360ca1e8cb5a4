"""The single-view diffusion policy: an image encoder plus a 1D conditional U-Net noise model.

Split for serving: ``encode`` runs once per observation and gives the conditioning vector;
``denoise_step_eps`` predicts the noise of one denoising step from that cached vector. A worker
serving one view calls ``encode`` once and then ``denoise_step_eps`` once per step, so the
steps of several views can be combined before the scheduler update (see ``diffusion.sample``).

Every tensor here is in normalised units (images in [-1, 1], state and actions as the dataset's
normaliser writes them); the normaliser travels with the checkpoint.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field, PositiveInt, model_validator
from torch import nn

from services.core.config import Frozen
from services.policy.model.encoder import EncoderConfig, build_encoder
from services.policy.model.unet1d import ConditionalUnet1D


class NoiseConfig(Frozen):
    num_train_timesteps: int = Field(100, ge=1)  # DDPM steps in training
    beta_schedule: Literal["linear", "scaled_linear", "squaredcos_cap_v2"] = "squaredcos_cap_v2"  # diffusers'
    clip_sample: bool = True  # clip the predicted x_0 to [-1, 1] while sampling
    prediction_type: Literal["epsilon", "sample"] = "epsilon"  # what the U-Net predicts: the noise or x_0
    num_inference_steps: int = Field(10, ge=1)  # DDIM steps at inference (at most num_train_timesteps)

    @model_validator(mode="after")
    def _check(self) -> NoiseConfig:
        if self.num_inference_steps > self.num_train_timesteps:
            raise ValueError(
                f"num_inference_steps {self.num_inference_steps} is more than num_train_timesteps "
                f"{self.num_train_timesteps}: DDIM steps are a subset of the training steps"
            )
        return self


class ModelConfig(Frozen):
    obs_horizon: int = Field(2, ge=1)  # To: observation frames the policy conditions on
    pred_horizon: int = Field(16, ge=1)  # Tp: actions predicted per chunk
    n_action_steps: int = Field(8, ge=1)  # actions executed per chunk, starting at the current obs step (To - 1)
    action_dim: int = Field(7, ge=1)  # dp (3), drot (3), gripper (1)
    state_dim: int = Field(0, ge=0)  # proprioceptive state per frame (0 = images only)
    image_size: tuple[PositiveInt, PositiveInt] = (84, 84)  # (H, W) of the frames the dataset provides
    encoder: EncoderConfig = Field(default_factory=EncoderConfig)  # image backbone
    # U-Net channels per level (diffusion_policy image default)
    down_dims: tuple[PositiveInt, ...] = Field((512, 1024, 2048), min_length=1)
    diffusion_step_embed_dim: int = Field(128, ge=4, multiple_of=2)  # sinusoidal step embedding width (even)
    kernel_size: int = Field(5, ge=1)  # U-Net conv kernel (odd: the convolutions keep the chunk's length)
    n_groups: int = Field(8, ge=1)  # U-Net GroupNorm groups
    noise: NoiseConfig = Field(default_factory=NoiseConfig)  # schedulers

    @model_validator(mode="after")
    def _check(self) -> ModelConfig:
        if self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size {self.kernel_size} must be odd, so the U-Net keeps the chunk's length")
        factor = 2 ** (len(self.down_dims) - 1)
        if self.pred_horizon % factor:
            raise ValueError(
                f"pred_horizon {self.pred_horizon} must be a multiple of {factor} "
                f"for {len(self.down_dims)} U-Net levels"
            )
        if self.obs_horizon - 1 + self.n_action_steps > self.pred_horizon:
            raise ValueError("obs_horizon - 1 + n_action_steps must not exceed pred_horizon")
        if any(d % self.n_groups for d in self.down_dims):
            raise ValueError(f"down_dims {self.down_dims} must be multiples of n_groups {self.n_groups}")
        h, w = self.encoder.crop_for(self.image_size)
        if h > self.image_size[0] or w > self.image_size[1]:
            raise ValueError(f"encoder crop {(h, w)} is larger than image_size {self.image_size}")
        return self

    @property
    def cond_dim(self) -> int:
        return self.obs_horizon * (self.encoder.feature_dim + self.state_dim)


class DiffusionPolicy(nn.Module):
    def __init__(self, cfg: ModelConfig, load_pretrained: bool = True):
        super().__init__()
        self.cfg = cfg
        self.channels_last = False  # NHWC images into the encoder (faster convs on GPU); see use_channels_last
        self.encoder = build_encoder(cfg.encoder, tuple(cfg.image_size), load_pretrained=load_pretrained)
        self.noise_model = ConditionalUnet1D(
            input_dim=cfg.action_dim,
            global_cond_dim=cfg.cond_dim,
            down_dims=tuple(cfg.down_dims),
            diffusion_step_embed_dim=cfg.diffusion_step_embed_dim,
            kernel_size=cfg.kernel_size,
            n_groups=cfg.n_groups,
        )

    def encode(self, obs: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """Observation features for conditioning, computed once per observation.

        obs: (B, To, 3, H, W) in [-1, 1]; state: (B, To, Ds) normalised -> cond: (B, To * (F + Ds)).
        """
        B, To = obs.shape[:2]
        img = obs.flatten(0, 1)  # (B*To, 3, H, W)
        if self.channels_last:
            img = img.contiguous(memory_format=torch.channels_last)
        feats = self.encoder(img)  # (B*To, F)
        feats = feats.view(B, To, -1)  # (B, To, F)
        if self.cfg.state_dim:
            if state is None:
                raise ValueError(f"this policy needs state (B, To, {self.cfg.state_dim})")
            feats = torch.cat([feats, state.to(feats.dtype)], dim=-1)  # (B, To, F + Ds)
        return feats.flatten(1)  # (B, To * (F + Ds))

    def denoise_step_eps(self, x_k: torch.Tensor, k: torch.Tensor | int, cond: torch.Tensor) -> torch.Tensor:
        """Predicted noise of one denoising step.

        x_k: (B, Tp, Da) noisy actions at step k; k: int or (B,) step; cond: (B, Dc) from ``encode``.
        """
        if not torch.is_tensor(k) or k.dim() == 0:
            k = torch.full((x_k.shape[0],), int(k), device=x_k.device, dtype=torch.long)
        return self.noise_model(x_k, k.to(x_k.device), cond)  # (B, Tp, Da)

    def use_channels_last(self) -> DiffusionPolicy:
        """Store the encoder's conv weights and feed its images as NHWC (the layout cuDNN prefers)."""
        self.encoder.to(memory_format=torch.channels_last)
        self.channels_last = True
        return self

    def num_parameters(self, trainable_only: bool = False) -> int:
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable_only)
