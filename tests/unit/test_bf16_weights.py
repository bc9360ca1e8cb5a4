"""Casting the matrix-multiply weights to bfloat16 once gives, under bf16 autocast, the outputs of
autocast over the float32 model to the bit: with the default image encoder, with the DINOv3 ViT
(transformers) and LoRA on it, and with the CPU's GEMM Conv1d."""

from __future__ import annotations

import copy

import pytest
import torch
from tiny_models import TINY_VIT
from torch import nn

from services.policy.model.encoder import EncoderConfig
from services.policy.model.fastpath import KEEP_PACKAGES, MATMUL_LAYERS, cast_matmul_weights, use_gemm_conv1d
from services.policy.model.policy import DiffusionPolicy, ModelConfig

torch.set_num_threads(1)
ENCODERS = {
    "resnet": EncoderConfig(width=8, stage_strides=(1, 2, 1, 1), num_keypoints=4, feature_dim=8),
    "dinov3+lora": EncoderConfig(kind="dinov3", vit_config=TINY_VIT, lora_rank=4, lora_alpha=8, feature_dim=16),
}


@pytest.mark.parametrize("encoder", list(ENCODERS))
@pytest.mark.parametrize("gemm", [False, True])
def test_weights_cast_once_give_the_autocast_outputs_exactly(encoder, gemm):
    torch.manual_seed(0)
    cfg = ModelConfig(
        image_size=(32, 32), state_dim=3, down_dims=(16, 32), diffusion_step_embed_dim=16, encoder=ENCODERS[encoder]
    )
    policy = DiffusionPolicy(cfg, load_pretrained=False).eval()
    if gemm:
        use_gemm_conv1d(policy)
    cast = copy.deepcopy(policy)
    n = cast_matmul_weights(cast, torch.bfloat16)
    library = {id(m) for top in cast.modules() if type(top).__module__.startswith(KEEP_PACKAGES) for m in top.modules()}
    layers = [m for m in cast.modules() if isinstance(m, MATMUL_LAYERS) and id(m) not in library]
    assert n == sum(len(list(m.parameters(recurse=False))) for m in layers) > 0
    assert all(p.dtype == torch.bfloat16 for m in layers for p in m.parameters(recurse=False))
    assert (len(library) > 0) == (encoder == "dinov3+lora")  # the ViT and its adapters: left in float32
    assert all(p.dtype == torch.float32 for m in cast.modules() if id(m) in library for p in m.parameters())
    g = torch.Generator().manual_seed(1)
    To = cfg.obs_horizon
    obs = torch.rand(3, To, 3, 32, 32, generator=g) * 2 - 1
    state = torch.rand(3, To, 3, generator=g) * 2 - 1
    x = torch.randn(3, cfg.pred_horizon, cfg.action_dim, generator=g)
    k = torch.tensor([0, 40, 99])
    outs = []
    for model in (policy, cast):
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            cond = model.encode(obs, state)
            outs.append((cond.float(), model.denoise_step_eps(x, k, cond).float()))
    (c32, e32), (c16, e16) = outs
    assert torch.equal(c32, c16) and torch.equal(e32, e16)
    with torch.no_grad():  # and the float32 model was not touched: its own numbers differ from bf16's
        assert not torch.equal(policy.encode(obs, state), c32)
    assert all(p.dtype == torch.float32 for p in policy.parameters())


def test_only_matrix_multiply_layers_are_cast():
    model = nn.Sequential(nn.Linear(4, 4), nn.GroupNorm(2, 4), nn.LayerNorm(4))
    assert cast_matmul_weights(model, torch.bfloat16) == 2  # the Linear's weight and bias
    assert [p.dtype for p in model.parameters()] == [torch.bfloat16] * 2 + [torch.float32] * 4
