"""The fast paths compute what the plain PyTorch modules compute (services.policy.model.fastpath)."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from services.policy.model.fastpath import (
    GemmConv1d,
    cast_matmul_weights,
    ema_update,
    make_optimizer,
    use_gemm_conv1d,
    use_native_conv1d,
)
from services.policy.model.unet1d import ConditionalUnet1D
from services.trainer.config import EmaConfig
from services.trainer.train import EMA

torch.set_num_threads(1)


def close(a: torch.Tensor, b: torch.Tensor, rel: float = 1e-5) -> None:
    """Equal up to float32 rounding of sums of many products: relative to the tensor's scale."""
    scale = max(a.abs().max().item(), 1e-12)
    assert (a - b).abs().max().item() <= rel * scale, ((a - b).abs().max().item(), scale)


@pytest.mark.parametrize(
    "c_in, c_out, k, stride, pad, bias, length",
    [
        (64, 128, 5, 1, 2, True, 16),  # a U-Net block conv
        (128, 128, 3, 2, 1, True, 8),  # the stride-2 down conv
        (32, 7, 1, 1, 0, True, 16),  # the final 1x1 conv
        (16, 16, 5, 1, 2, False, 3),  # shorter than the kernel, no bias
        (8, 24, 4, 3, 0, True, 13),  # stride and kernel that do not tile the input
    ],
)
def test_gemm_conv1d_matches_conv1d_outputs_and_gradients(c_in, c_out, k, stride, pad, bias, length):
    torch.manual_seed(0)
    plain = nn.Conv1d(c_in, c_out, k, stride=stride, padding=pad, bias=bias)
    fast = copy.deepcopy(plain)
    assert use_gemm_conv1d(fast) == 1 and type(fast) is GemmConv1d
    x = torch.randn(6, c_in, length)
    xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ya, yb = plain(xa), fast(xb)
    assert ya.shape == yb.shape and yb.is_contiguous()
    close(ya, yb)
    g = torch.randn_like(ya)
    ya.backward(g)
    yb.backward(g)
    close(xa.grad, xb.grad)
    close(plain.weight.grad, fast.weight.grad)
    if bias:
        close(plain.bias.grad, fast.bias.grad)
    assert fast.state_dict().keys() == plain.state_dict().keys()


GEMM = "_GemmConv1dFunction"  # the profiler's name for the autograd function


def _ops(fn) -> set[str]:
    """The operators and autograd functions ``fn`` runs (the profiler's record of them)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return {e.key for e in prof.key_averages()}


def test_a_batch_of_one_without_gradients_takes_pytorchs_convolution_and_the_rest_the_gemm():
    """(one view's float32 denoising step: PyTorch's convolution was measured faster there, and the
    GEMM in bfloat16, bench/denoise_step.py)"""
    torch.manual_seed(2)
    plain = nn.Conv1d(64, 128, 5, padding=2)
    fast = copy.deepcopy(plain)
    use_gemm_conv1d(fast)
    one, six = torch.randn(1, 64, 16), torch.randn(6, 64, 16)
    with torch.no_grad():
        ops = _ops(lambda: fast(one))
        assert "aten::convolution" in ops and GEMM not in ops and torch.equal(fast(one), plain(one))
        ops = _ops(lambda: fast(six))
        assert GEMM in ops and "aten::convolution" not in ops
        close(fast(six), plain(six))
    ops = _ops(lambda: fast(one))  # with gradients (training): the GEMM, and its backward
    assert GEMM in ops and "aten::convolution" not in ops
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):  # a bf16 server's pass
        ops = _ops(lambda: fast(one))
        assert GEMM in ops and "aten::convolution" not in ops
        cast_matmul_weights(fast, torch.bfloat16)
        ops = _ops(lambda: fast(one))
        assert GEMM in ops and "aten::convolution" not in ops


def test_the_unet_with_gemm_convs_is_the_same_function_with_the_same_gradients():
    torch.manual_seed(1)
    plain = ConditionalUnet1D(input_dim=7, global_cond_dim=40, down_dims=(32, 64, 128), diffusion_step_embed_dim=16)
    fast = copy.deepcopy(plain)
    n = use_gemm_conv1d(fast)
    assert n == sum(type(m) is nn.Conv1d for m in plain.modules()) > 10
    assert sum(type(m) is nn.ConvTranspose1d for m in fast.modules()) == 2  # left as they are
    x, k, cond = torch.randn(5, 16, 7), torch.randint(0, 100, (5,)), torch.randn(5, 40)
    ya, yb = plain(x, k, cond), fast(x, k, cond)
    close(ya, yb, 1e-4)
    ya.square().mean().backward()
    yb.square().mean().backward()
    for pa, pb in zip(plain.parameters(), fast.parameters()):
        close(pa.grad, pb.grad, 1e-4)
    # checkpoints load either way: same keys, same shapes
    assert {k: v.shape for k, v in fast.state_dict().items()} == {k: v.shape for k, v in plain.state_dict().items()}
    assert use_native_conv1d(fast) == n and not any(type(m) is GemmConv1d for m in fast.modules())


def _params(seed: int) -> list[torch.nn.Parameter]:
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g)) for s in [(64, 32), (32,), (7, 5, 3), (1,)]]


def test_fused_adamw_takes_the_steps_plain_adamw_takes():
    a, b = _params(0), _params(0)
    opt_a = make_optimizer(a, 1e-3, (0.95, 0.999), 1e-8, 1e-6, fused=False)
    opt_b = make_optimizer(b, 1e-3, (0.95, 0.999), 1e-8, 1e-6, fused=True)
    assert opt_b.param_groups[0]["fused"] and not opt_a.param_groups[0]["fused"]
    g = torch.Generator().manual_seed(1)
    for _ in range(20):
        grads = [torch.randn(p.shape, generator=g) for p in a]
        for pa, pb, gr in zip(a, b, grads):
            pa.grad, pb.grad = gr.clone(), gr.clone()
        opt_a.step()
        opt_b.step()
    moved = sum((pa - q).abs().sum().item() for pa, q in zip(a, _params(0)))
    assert moved > 0.1  # the steps did something
    for pa, pb in zip(a, b):
        torch.testing.assert_close(pa, pb, rtol=1e-5, atol=1e-6)


def test_the_one_pass_ema_averages_as_the_plain_one_and_copies_what_is_not_averaged():
    torch.manual_seed(2)
    model = nn.Sequential(nn.Linear(8, 8), nn.GroupNorm(2, 8), nn.Linear(8, 3))
    model[2].weight.requires_grad_(False)  # frozen: copied, never averaged (as the ViT under LoRA)
    model.register_buffer("count", torch.zeros((), dtype=torch.long))
    plain, fast = EMA(model, EmaConfig(), fast=False), EMA(model, EmaConfig(), fast=True)
    for step in range(1, 30):
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p) * 0.1)
            model.count += 1
        plain.update(model, step)
        fast.update(model, step)
    sa, sb, cur = plain.model.state_dict(), fast.model.state_dict(), model.state_dict()
    for name in sa:
        torch.testing.assert_close(sa[name], sb[name], rtol=1e-5, atol=1e-6)
    assert torch.equal(sb["2.weight"], cur["2.weight"]) and int(sb["count"]) == 29
    assert not torch.allclose(sb["0.weight"], cur["0.weight"])  # averaged, not copied


def test_ema_update_is_a_lerp():
    a, b = [torch.zeros(3), torch.ones(2)], [torch.ones(3), torch.zeros(2)]
    ema_update(a, b, 0.75)
    assert torch.allclose(a[0], torch.full((3,), 0.25)) and torch.allclose(a[1], torch.full((2,), 0.75))
