"""How close the image encoder's convolutions run to this CPU's matrix-multiply peak.

    python bench/encoder_convs.py                         # tiny, one thread, B = 32 (64 frames)
    python bench/encoder_convs.py --preset paper-small --reps 3

A training step of the ``tiny`` preset is two thirds encoder, and the encoder is mostly
Conv2d. This times every Conv2d of the preset's encoder alone, forward and backward (weight and
input gradients; the stem's input needs none), on the shapes a training batch gives it, and
divides their floating-point work by the time. It also times a plain float32 matrix multiply
(``torch.mm``, 1024 x 1024 x 1024, and the im2col GEMM of the widest layer) on the same thread
count, alternating with the layers, so the ratio says how much faster any kernel for the same
maths could be: near 1, only less arithmetic would help. The whole encoder's forward + backward
is timed too, and profiled for the share of its time the convolution kernels take.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402

CONV_OPS = {"aten::mkldnn_convolution", "aten::convolution_backward", "aten::thnn_conv2d", "aten::_slow_conv2d_forward"}


def median_s(fn, reps: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--batch", type=int, default=32, help="samples; each has To = 2 frames")
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=8)
    args = ap.parse_args()

    import torch
    from torch import nn

    from services.policy.model.encoder import EncoderConfig, build_encoder
    from services.policy.model.presets import preset

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = EncoderConfig.model_validate(preset(args.preset)["model"]["encoder"])
    enc = build_encoder(cfg, (args.size, args.size)).train()
    images = torch.rand(args.batch * 2, 3, args.size, args.size) * 2 - 1  # (B * To, 3, H, W)

    shapes: dict[str, tuple] = {}
    convs = [(n, m) for n, m in enc.named_modules() if type(m) is nn.Conv2d]
    hooks = [
        m.register_forward_hook(lambda m, i, o, n=n: shapes.__setitem__(n, (i[0].shape, o.shape))) for n, m in convs
    ]
    enc(images)
    for h in hooks:
        h.remove()

    def sgemm_gflops(m: int, k: int, n: int) -> float:
        a, b = torch.randn(m, k), torch.randn(k, n)
        return 2 * m * k * n / median_s(lambda: a @ b, args.reps) / 1e9

    peaks = [sgemm_gflops(1024, 1024, 1024)]
    layers, flop_total, time_total = [], 0.0, 0.0
    widest = max(convs, key=lambda nm: nm[1].weight.numel())[0]
    for name, conv in convs:
        in_shape, out_shape = shapes[name]
        first = name == convs[0][0]  # the stem: its input (the image) needs no gradient
        x = torch.randn(in_shape, requires_grad=not first)
        fwd_flop = 2.0 * out_shape.numel() * conv.weight[0].numel()
        bwd_flop = fwd_flop * (1 if first else 2)
        y = conv(x)
        grad = torch.ones_like(y)
        t_f = median_s(lambda conv=conv, x=x: conv(x), args.reps)
        t_b = median_s(lambda conv=conv, x=x, grad=grad: conv(x).backward(grad), args.reps) - t_f
        flop_total += fwd_flop + bwd_flop
        time_total += t_f + t_b
        layers.append(
            {
                "layer": name,
                "in": list(in_shape),
                "out": list(out_shape),
                "fwd_ms": round(t_f * 1e3, 3),
                "bwd_ms": round(t_b * 1e3, 3),
                "gflops_s": round((fwd_flop + bwd_flop) / (t_f + t_b) / 1e9, 1),
            }
        )
        if name == widest:  # the GEMM this layer is, as im2col would run it
            n_out = out_shape[0] * out_shape[2] * out_shape[3]
            peaks.append(sgemm_gflops(n_out, conv.weight[0].numel(), out_shape[1]))
    peaks.append(sgemm_gflops(1024, 1024, 1024))
    encoder_s = median_s(lambda: enc(images).sum().backward(), args.reps)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:  # the convolutions' share, in place
        for _ in range(3):
            enc(images).sum().backward()
    ops = prof.key_averages()
    conv_self = sum(e.self_cpu_time_total for e in ops if e.key in CONV_OPS)
    all_self = sum(e.self_cpu_time_total for e in ops)
    conv_rate = flop_total / time_total / 1e9
    peak = max(peaks)
    report(
        "encoder_convs",
        {
            "preset": args.preset,
            "threads": args.threads,
            "frames": images.shape[0],
            "size": args.size,
            "conv_gflop": round(flop_total / 1e9, 3),
            "conv_ms": round(time_total * 1e3, 1),
            "conv_gflops_s": round(conv_rate, 1),
            "sgemm_gflops_s": [round(p, 1) for p in peaks],
            "conv_over_sgemm_peak": round(conv_rate / peak, 3),
            "encoder_fwd_bwd_ms": round(encoder_s * 1e3, 1),
            "conv_share_of_encoder": round(conv_self / all_self, 3),
            "layers": layers,
        },
    )


if __name__ == "__main__":
    main()
