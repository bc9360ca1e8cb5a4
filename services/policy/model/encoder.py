"""Image encoders: one RGB frame -> one feature vector.

Two kinds, chosen by ``EncoderConfig.kind``:

- ``resnet18``: the Diffusion Policy / robomimic encoder trained from scratch: a ResNet-18
  layout (7x7 stem, four stages of two basic blocks) with GroupNorm instead of BatchNorm
  (BatchNorm's running statistics interact badly with the EMA weights), a spatial softmax that
  turns the last feature map into keypoint coordinates, and a linear projection.
- ``dinov3``: a pretrained DINOv3 ViT (transformers' ``DINOv3ViTModel``) whose attention
  projections are fine-tuned with LoRA (peft), the class token projected linearly. Pretrained
  weights come from a local safetensors file; without one the ViT is randomly initialised.

Both take images in [-1, 1] and crop them first: a random crop per image in training, the centre
crop in eval, so the model at inference sees the same scale it trained on.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from pydantic import Field, PositiveInt, model_validator
from torch import nn

from services.core.config import Frozen

# transformers' DINOv3ViTConfig for dinov3-vitb16 (the paper's DINOv3-base).
DINOV3_BASE: dict[str, Any] = {
    "hidden_size": 768,
    "intermediate_size": 3072,
    "num_attention_heads": 12,
    "num_hidden_layers": 12,
    "num_register_tokens": 4,
    "patch_size": 16,
    "image_size": 224,
    "layerscale_value": 1.0,
    "use_gated_mlp": False,
    "key_bias": False,
    "rope_theta": 100.0,
    "pos_embed_rescale": 2.0,
}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class EncoderConfig(Frozen):
    kind: Literal["resnet18", "dinov3"] = "resnet18"  # image backbone
    # (h, w) fed to the backbone (random crop in training, centre in eval)
    crop: tuple[PositiveInt, PositiveInt] | None = None
    crop_ratio: float = Field(0.9, gt=0, le=1)  # with crop unset: crop = ratio * image size (84 -> 76)
    feature_dim: int = Field(64, ge=1)  # output features per frame (the linear projection's width)
    # resnet18
    width: int = Field(64, ge=1)  # channels of the first stage (64 = ResNet-18; 2x per stage after it)
    stage_strides: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (1, 2, 2, 2)  # each stage's first stride
    stem_pool: bool = True  # 3x3/2 max-pool after the 7x7/2 stem conv
    num_keypoints: int = Field(32, ge=1)  # spatial-softmax keypoints (each gives x, y)
    feature_relu: bool = False  # ReLU on the projected features, as robomimic's encoder (diffusion_policy's)
    # dinov3
    vit_config: dict[str, Any] = Field(default_factory=lambda: dict(DINOV3_BASE))  # DINOv3ViTConfig fields
    vit_weights: str | None = None  # local safetensors file (or a dir holding model.safetensors); None = random init
    lora_rank: int = Field(16, ge=0)  # LoRA rank on the attention projections; 0 = fine-tune the whole ViT
    lora_alpha: int = Field(32, ge=1)  # LoRA scaling numerator
    lora_targets: tuple[str, ...] = ("q_proj", "k_proj", "v_proj", "o_proj")  # module names LoRA wraps

    @model_validator(mode="after")
    def _check(self) -> EncoderConfig:
        if self.kind != "dinov3":
            return self
        defaults = vit_config_defaults()
        unknown = sorted(set(self.vit_config) - set(defaults))
        if unknown:  # (transformers keeps any keyword as an attribute: a typo was a silent default)
            raise ValueError(
                f"vit_config: {', '.join(map(repr, unknown))} is not a DINOv3ViTConfig field "
                f"(its fields include {', '.join(sorted(DINOV3_BASE))})"
            )
        # a key left out takes DINOv3ViTConfig's default, as the model built from it does
        width, heads = ({**defaults, **self.vit_config}[k] for k in ("hidden_size", "num_attention_heads"))
        ints = isinstance(width, int) and isinstance(heads, int)
        if not (ints and width > 0 and heads > 0 and width % heads == 0):
            raise ValueError(
                f"vit_config: hidden_size {width} must be a positive multiple of num_attention_heads {heads}"
            )
        if self.crop is not None:
            patch = self.patch_size
            if self.crop[0] % patch or self.crop[1] % patch:
                raise ValueError(f"crop {self.crop} must be a multiple of the ViT patch size {patch}")
        return self

    @property
    def patch_size(self) -> int:
        return int(self.vit_config.get("patch_size", 16))

    def crop_for(self, image_size: tuple[int, int]) -> tuple[int, int]:
        """The crop actually used for frames of ``image_size`` (H, W)."""
        if self.crop is not None:
            return (int(self.crop[0]), int(self.crop[1]))
        h, w = (max(1, round(self.crop_ratio * s)) for s in image_size)
        if self.kind == "dinov3":  # whole patches only
            h, w = (max(self.patch_size, v // self.patch_size * self.patch_size) for v in (h, w))
        return (h, w)


def crop_images(x: torch.Tensor, crop: tuple[int, int], random: bool) -> torch.Tensor:
    """(N, C, H, W) -> (N, C, h, w): one random window per image, or the centre window."""
    n, _, H, W = x.shape
    h, w = crop
    if (h, w) == (H, W):
        return x
    if h > H or w > W:
        raise ValueError(f"crop {crop} is larger than the images {(H, W)}")
    if not random:
        top, left = (H - h) // 2, (W - w) // 2
        return x[:, :, top : top + h, left : left + w]
    tops = torch.randint(0, H - h + 1, (n,), device=x.device)
    lefts = torch.randint(0, W - w + 1, (n,), device=x.device)
    rows = tops[:, None] + torch.arange(h, device=x.device)[None, :]  # (N, h)
    cols = lefts[:, None] + torch.arange(w, device=x.device)[None, :]  # (N, w)
    idx = torch.arange(n, device=x.device)[:, None, None]
    # advanced indexing: (N, h, w, C) -> (N, C, h, w)
    return x.permute(0, 2, 3, 1)[idx, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)


def _gn(channels: int) -> nn.GroupNorm:
    # diffusion_policy's replace_bn_with_gn uses channels // 16 groups; for a width it does not
    # divide, the largest group count below it that does
    groups = max(1, channels // 16)
    while channels % groups:
        groups -= 1
    return nn.GroupNorm(groups, channels)


class BasicBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)
        self.norm1 = _gn(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.norm2 = _gn(c_out)
        self.down = None
        if stride != 1 or c_in != c_out:
            self.down = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False), _gn(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.norm1(self.conv1(x)))
        out = self.norm2(self.conv2(out))
        return F.relu(out + (x if self.down is None else self.down(x)))


class SpatialSoftmax(nn.Module):
    """Feature map -> expected (x, y) in [-1, 1] of ``num_keypoints`` learned keypoints."""

    def __init__(self, channels: int, num_keypoints: int):
        super().__init__()
        self.keypoints = nn.Conv2d(channels, num_keypoints, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # x: (N, C, h, w) -> (N, K * 2)
        n, _, h, w = x.shape
        logits = self.keypoints(x).flatten(2)  # (N, K, h*w)
        attn = logits.softmax(dim=-1)
        ys = torch.linspace(-1.0, 1.0, h, device=x.device, dtype=attn.dtype)
        xs = torch.linspace(-1.0, 1.0, w, device=x.device, dtype=attn.dtype)
        grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
        grid = torch.stack([grid_x.flatten(), grid_y.flatten()], dim=-1)  # (h*w, 2)
        return (attn @ grid).flatten(1)  # (N, K * 2)


class ResNet18Encoder(nn.Module):
    def __init__(self, cfg: EncoderConfig, crop: tuple[int, int]):
        super().__init__()
        self.crop = crop
        w = cfg.width
        stem = [nn.Conv2d(3, w, 7, stride=2, padding=3, bias=False), _gn(w), nn.ReLU()]
        if cfg.stem_pool:
            stem.append(nn.MaxPool2d(3, stride=2, padding=1))
        self.stem = nn.Sequential(*stem)
        stages, c_in = [], w
        for i, stride in enumerate(cfg.stage_strides):
            c_out = w * 2**i
            stages.append(nn.Sequential(BasicBlock(c_in, c_out, stride), BasicBlock(c_out, c_out, 1)))
            c_in = c_out
        self.stages = nn.Sequential(*stages)
        self.pool = SpatialSoftmax(c_in, cfg.num_keypoints)
        self.proj = nn.Linear(cfg.num_keypoints * 2, cfg.feature_dim)
        self.feature_relu = cfg.feature_relu

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        # img: (N, 3, H, W) in [-1, 1] -> (N, feature_dim)
        x = crop_images(img, self.crop, random=self.training)
        x = self.stages(self.stem(x))  # (N, C, h, w)
        feats = self.proj(self.pool(x))  # (N, feature_dim)
        return F.relu(feats) if self.feature_relu else feats


def _read_safetensors(path: str | Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    path = Path(path)
    if path.is_dir():
        path = path / "model.safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"ViT weights {path} do not exist (give a local safetensors file)")
    return load_file(str(path))


class DinoV3Encoder(nn.Module):
    """DINOv3 ViT with LoRA on the attention projections; the class token, projected."""

    def __init__(self, cfg: EncoderConfig, crop: tuple[int, int], load_pretrained: bool = True):
        super().__init__()
        from transformers import DINOv3ViTConfig, DINOv3ViTModel

        self.crop = crop
        vit_cfg = DINOv3ViTConfig(**{**cfg.vit_config, "image_size": crop[0]})
        self.vit = DINOv3ViTModel(vit_cfg)
        if load_pretrained and cfg.vit_weights:
            self._load_pretrained(cfg.vit_weights)
        if cfg.lora_rank > 0:
            from peft import LoraConfig, inject_adapter_in_model

            lora = LoraConfig(r=cfg.lora_rank, lora_alpha=cfg.lora_alpha, target_modules=list(cfg.lora_targets))
            self.vit = inject_adapter_in_model(lora, self.vit)
            for name, p in self.vit.named_parameters():
                p.requires_grad = "lora_" in name
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.proj = nn.Linear(vit_cfg.hidden_size, cfg.feature_dim)

    def _load_pretrained(self, path: str) -> None:
        state = _read_safetensors(path)
        own = self.vit.state_dict()
        fixed = {}
        for key, value in state.items():
            # Accept the bare model's keys, a wrapper's ``dinov3.`` prefix, and checkpoints written
            # before transformers nested the blocks under ``model.``.
            for cand in (key, key.removeprefix("dinov3."), "model." + key, "model." + key.removeprefix("dinov3.")):
                if cand in own:
                    fixed[cand] = value
                    break
        missing = sorted(set(own) - set(fixed) - {"embeddings.mask_token"})  # mask_token: pretraining only
        if missing:
            raise ValueError(
                f"ViT weights {path} do not fit the configured ViT: {len(missing)} tensors missing "
                f"(first: {missing[:3]}); check model.encoder.vit_config"
            )
        bad = [k for k in fixed if fixed[k].shape != own[k].shape]
        if bad:
            raise ValueError(f"ViT weights {path}: shape mismatch for {bad[:3]}; check model.encoder.vit_config")
        self.vit.load_state_dict(fixed, strict=False)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        # img: (N, 3, H, W) in [-1, 1] -> (N, feature_dim)
        x = crop_images(img, self.crop, random=self.training)
        x = ((x + 1.0) / 2.0 - self.mean) / self.std  # ImageNet statistics, as DINOv3 was trained
        cls = self.vit(pixel_values=x).pooler_output  # (N, hidden)
        return self.proj(cls)


def build_encoder(cfg: EncoderConfig, image_size: tuple[int, int], load_pretrained: bool = True) -> nn.Module:
    crop = cfg.crop_for(image_size)
    if crop[0] > image_size[0] or crop[1] > image_size[1]:
        raise ValueError(f"encoder crop {crop} is larger than the images {tuple(image_size)}")
    if cfg.kind == "resnet18":
        return ResNet18Encoder(cfg, crop)
    return DinoV3Encoder(cfg, crop, load_pretrained=load_pretrained)


@functools.cache
def vit_config_defaults() -> dict[str, Any]:
    """transformers' DINOv3ViTConfig as it fills every field it knows (its own and every model
    config's) when given none: the names ``vit_config`` may use, and what a name left out becomes."""
    from transformers import DINOv3ViTConfig

    return DINOv3ViTConfig().to_dict()


def vit_config_from_dir(path: str | Path) -> dict[str, Any]:
    """The DINOv3ViTConfig fields of a local model directory's ``config.json``."""
    data = json.loads((Path(path) / "config.json").read_text())
    keys = set(DINOV3_BASE) | {"layer_norm_eps", "hidden_act", "mlp_bias", "query_bias", "value_bias", "proj_bias"}
    return {k: v for k, v in data.items() if k in keys}
