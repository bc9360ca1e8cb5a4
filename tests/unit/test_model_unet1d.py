"""The 1D conditional U-Net: shapes through its levels and that both conditioning paths act."""

from __future__ import annotations

import pytest
import torch

from services.policy.model.unet1d import ConditionalUnet1D, SinusoidalPosEmb

torch.set_num_threads(1)


@pytest.mark.parametrize("down_dims", [(16,), (16, 32), (16, 32, 64)])
def test_output_matches_input_shape(down_dims):
    torch.manual_seed(0)
    net = ConditionalUnet1D(input_dim=7, global_cond_dim=10, down_dims=down_dims, diffusion_step_embed_dim=16)
    x = torch.randn(3, 16, 7)  # (B, Tp, Da)
    out = net(x, torch.tensor([0, 5, 99]), torch.randn(3, 10))
    assert out.shape == (3, 16, 7)
    assert torch.isfinite(out).all()


def test_film_conditioning_and_step_embedding_change_the_output():
    torch.manual_seed(0)
    net = ConditionalUnet1D(input_dim=7, global_cond_dim=10, down_dims=(16, 32), diffusion_step_embed_dim=16)
    x = torch.randn(2, 16, 7)
    cond = torch.randn(2, 10)
    k = torch.tensor([3, 3])
    base = net(x, k, cond)
    assert not torch.allclose(base, net(x, k, cond + 1.0), atol=1e-5)  # observation features act (FiLM)
    assert not torch.allclose(base, net(x, torch.tensor([60, 60]), cond), atol=1e-5)  # the step acts
    # Samples in a batch do not leak into each other: row 0 alone gives the same result.
    assert torch.allclose(net(x[:1], k[:1], cond[:1]), base[:1], atol=1e-5)


def test_sinusoidal_embedding_is_sin_then_cos_of_geometric_frequencies():
    emb = SinusoidalPosEmb(8)(torch.tensor([0, 1]))
    assert emb.shape == (2, 8)
    assert torch.allclose(emb[0], torch.tensor([0.0] * 4 + [1.0] * 4))
    # first frequency is 1: sin(1), cos(1)
    assert emb[1, 0].item() == pytest.approx(torch.sin(torch.tensor(1.0)).item(), abs=1e-6)
    assert emb[1, 4].item() == pytest.approx(torch.cos(torch.tensor(1.0)).item(), abs=1e-6)
