"""Named starting points for model and training hyper-parameters.

A preset is a nested dict of overrides applied on top of the config defaults and under any
YAML file, environment variable or ``--set`` (``services.trainer.config.load_train_config``).

- ``tiny``: a few-channel ResNet and U-Net that trains a few hundred steps in minutes on a
  laptop CPU; for smoke runs, tests and CI, not for success rates.
- ``paper``: diffusion_policy's image (CNN, hybrid) defaults: ResNet-18 with GroupNorm and
  spatial softmax (the 64-d keypoint projection followed by a ReLU, as robomimic's), U-Net
  down dims 512/1024/2048, batch 64, AdamW lr 1e-4 (betas 0.95/0.999,
  weight decay 1e-6), cosine schedule with 500 warm-up steps, EMA power 0.75, DDPM 100 / DDIM 10.
- ``paper-small``: the same with down dims 256/512/1024 (diffusion_policy's smaller U-Net).
- ``paper-dinov3``: the paper's simulation baseline: a pretrained DINOv3-base ViT fine-tuned with
  LoRA (set ``model.encoder.vit_weights`` to a local safetensors file); the crop is
  0.9 x the image size rounded down to whole 16-pixel patches.
"""

from __future__ import annotations

import copy
from typing import Any

_PAPER: dict[str, Any] = {
    "batch_size": 64,
    "optim": {"lr": 1e-4, "warmup_steps": 500, "weight_decay": 1e-6, "betas": [0.95, 0.999]},
    "ema": {"power": 0.75},
    "model": {
        "encoder": {
            "kind": "resnet18",
            "width": 64,
            "stage_strides": [1, 2, 2, 2],
            "num_keypoints": 32,
            "feature_dim": 64,
            "feature_relu": True,  # robomimic's encoder: ReLU after the keypoint projection
        },
        "down_dims": [512, 1024, 2048],
        "diffusion_step_embed_dim": 128,
    },
}


def _paper(**model: Any) -> dict[str, Any]:
    """The paper preset with some ``model`` entries replaced whole."""
    out = copy.deepcopy(_PAPER)
    out["model"].update(model)
    return out


PRESETS: dict[str, dict[str, Any]] = {
    "tiny": {
        "batch_size": 32,
        "optim": {"lr": 3e-3, "warmup_steps": 20, "weight_decay": 0.0},
        "ema": {"power": 0.75},
        "val_every": 100,
        "checkpoint_every": 200,
        "model": {
            "encoder": {"width": 8, "stage_strides": [1, 2, 1, 1], "num_keypoints": 16, "feature_dim": 32},
            "down_dims": [64, 128],
            "diffusion_step_embed_dim": 64,
        },
    },
    "paper": _PAPER,
    "paper-small": _paper(down_dims=[256, 512, 1024]),
    "paper-dinov3": _paper(
        encoder={"kind": "dinov3", "feature_dim": 256, "lora_rank": 16, "lora_alpha": 32},
        down_dims=[256, 512, 1024],
    ),
}


def preset(name: str) -> dict[str, Any]:
    """A copy of the named preset's overrides."""
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return copy.deepcopy(PRESETS[name])
