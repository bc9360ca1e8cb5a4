"""Faster ways to compute the same training step on a CPU: same maths, other kernels.

Measured on the 2-core development machine (``bench/train_step.py``, rows in bench/RESULTS.md):

- ``GemmConv1d``: the U-Net's Conv1d layers as one matrix multiply each (im2col + GEMM, and two
  GEMMs plus a col2im in backward). PyTorch's CPU convolution (oneDNN) is slow on these short,
  wide sequences -- its weight gradient above all -- and a GEMM is what such a layer is.
- ``make_optimizer(fused=True)``: AdamW's fused kernel, one pass over every parameter instead of
  a dozen elementwise ops per tensor.
- ``ema_update``: the weight average as one ``torch._foreach_lerp_`` over all tensors.

And for serving in bfloat16 (any device): ``cast_matmul_weights`` stores the linear and
convolution weights in bfloat16 once, where autocast would round them again at every pass
(``bench/serving.py --precision``): the same outputs under autocast, to the bit.

Each one computes what the plain module computes, up to float32 rounding (the tests compare
outputs and gradients on random inputs). State dict keys and shapes are unchanged, so a checkpoint
trained with or without them loads either way.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
import torch.nn.functional as F
from torch import nn


class _GemmConv1dFunction(torch.autograd.Function):
    """conv1d (zero padding, dilation 1, one group) as GEMMs, forward and backward."""

    @staticmethod
    def forward(ctx, x, weight, bias, stride: int, pad: int):
        B, c_in, L = x.shape  # (B, C_in, L)
        c_out, _, k = weight.shape  # (C_out, C_in, k)
        xp = F.pad(x, (pad, pad)) if pad else x
        windows = xp.unfold(2, k, stride)  # (B, C_in, L_out, k), a view
        l_out = windows.shape[2]
        cols = windows.permute(0, 2, 1, 3).reshape(B * l_out, c_in * k)  # (B*L_out, C_in*k)
        w = weight.reshape(c_out, c_in * k)
        out = torch.addmm(bias, cols, w.t()) if bias is not None else cols @ w.t()  # (B*L_out, C_out)
        ctx.save_for_backward(cols, weight)
        ctx.shape = (B, c_in, L, l_out, k, stride, pad, bias is not None)
        return out.view(B, l_out, c_out).transpose(1, 2).contiguous()  # (B, C_out, L_out)

    @staticmethod
    def backward(ctx, grad_out):
        cols, weight = ctx.saved_tensors
        B, c_in, L, l_out, k, stride, pad, has_bias = ctx.shape
        c_out = weight.shape[0]
        g = grad_out.transpose(1, 2).reshape(B * l_out, c_out)  # (B*L_out, C_out)
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[1]:
            grad_w = (g.t() @ cols).view_as(weight)
        if has_bias and ctx.needs_input_grad[2]:
            grad_b = g.sum(0)
        if ctx.needs_input_grad[0]:
            # col2im: each kernel tap j adds its column back at the positions it read
            gcols = (
                (g @ weight.reshape(c_out, c_in * k)).view(B, l_out, c_in, k).permute(0, 2, 3, 1)
            )  # (B, C_in, k, L_out)
            gxp = grad_out.new_zeros(B, c_in, L + 2 * pad)
            for j in range(k):
                gxp[:, :, j : j + stride * (l_out - 1) + 1 : stride] += gcols[:, :, j]
            grad_x = gxp[:, :, pad : pad + L] if pad else gxp
        return grad_x, grad_w, grad_b, None, None


class GemmConv1d(nn.Conv1d):
    """An ``nn.Conv1d`` computed by ``_GemmConv1dFunction``; same parameters, same state dict.

    A float32 batch of one without gradients (one view's denoising step) goes to PyTorch's own
    convolution, measured faster there and slower from two up; in bfloat16 (weights cast, under
    autocast) the GEMM was faster at every batch size (``bench/denoise_step.py``)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (
            x.shape[0] == 1
            and not torch.is_grad_enabled()
            and self.weight.dtype == torch.float32
            and not torch.is_autocast_enabled(x.device.type)
        ):
            return super().forward(x)
        return _GemmConv1dFunction.apply(x, self.weight, self.bias, self.stride[0], self.padding[0])


def _gemm_compatible(m: nn.Module) -> bool:
    return (
        type(m) is nn.Conv1d
        and m.groups == 1
        and m.dilation == (1,)
        and m.padding_mode == "zeros"
        and isinstance(m.padding, tuple)
    )


def use_gemm_conv1d(model: nn.Module) -> int:
    """Compute every plain Conv1d of ``model`` as GEMMs (in place); returns how many."""
    n = 0
    for m in model.modules():
        if _gemm_compatible(m):
            m.__class__ = GemmConv1d
            n += 1
    return n


def use_native_conv1d(model: nn.Module) -> int:
    """Undo ``use_gemm_conv1d``: PyTorch's own convolution again; returns how many."""
    n = 0
    for m in model.modules():
        if type(m) is GemmConv1d:
            m.__class__ = nn.Conv1d
            n += 1
    return n


def gemm_conv1d_pays_off(device: torch.device) -> bool:
    """Where GemmConv1d was measured faster: the CPU (cuDNN's convolutions were not measured against it)."""
    return device.type == "cpu"


def make_optimizer(
    params: Iterable[torch.nn.Parameter],
    lr: float,
    betas: tuple[float, float],
    eps: float,
    weight_decay: float,
    fused: bool,
) -> torch.optim.AdamW:
    """AdamW, fused (one kernel over all parameters) or PyTorch's default (a per-tensor loop on the CPU)."""
    kw = {"fused": True} if fused else {}
    return torch.optim.AdamW(list(params), lr=lr, betas=betas, eps=eps, weight_decay=weight_decay, **kw)


@torch.no_grad()
def ema_update(averaged: list[torch.Tensor], current: list[torch.Tensor], decay: float) -> None:
    """averaged <- decay * averaged + (1 - decay) * current, for every pair at once."""
    if averaged:
        torch._foreach_lerp_(averaged, current, 1.0 - decay)


# The layers whose weights autocast hands to a bfloat16 matrix multiply or convolution: nothing
# else reads them. (GemmConv1d, the CPU's Conv1d, is an nn.Conv1d.)
MATMUL_LAYERS = (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.ConvTranspose1d, nn.ConvTranspose2d)
# Library models whose code reads their weights' dtype (to cast inputs, LoRA's adapters): left as
# they are, autocast casts their weights at each pass as before. Measured: casting inside the
# DINOv3 ViT with LoRA changed the encoder's bf16 output.
KEEP_PACKAGES = ("transformers", "peft")


def cast_matmul_weights(model: nn.Module, dtype: torch.dtype) -> int:
    """Store the weights and biases of ``model``'s MATMUL_LAYERS in ``dtype``, in place (not inside
    KEEP_PACKAGES' modules); returns how many tensors.

    Under autocast to ``dtype`` the outputs are unchanged to the bit (tests/unit/test_bf16_weights.py):
    autocast rounds these same tensors to ``dtype`` before each such op. It does so again at every
    pass, which on a CPU was most of a bf16 request (paper preset, one view: 2902 ms per request,
    and 467 ms with the weights cast once; bench/serving.py rows of 2026-12-04 00:15 and 00:24)."""
    if type(model).__module__.split(".")[0] in KEEP_PACKAGES:
        return 0
    n = 0
    if isinstance(model, MATMUL_LAYERS):
        for p in model.parameters(recurse=False):
            p.data = p.data.to(dtype)
            n += 1
    return n + sum(cast_matmul_weights(child, dtype) for child in model.children())
