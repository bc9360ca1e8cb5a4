"""One denoising step of the U-Net on the CPU, by batch size, with each way of computing its Conv1d layers.

    python bench/denoise_step.py                                  # tiny and paper-small, B = 1, 2, 3, 5, 8
    python bench/denoise_step.py --presets paper --batches 1,3 --reps 10
    python bench/denoise_step.py --precision fp32,bf16           # also under bfloat16, as a bf16 server

A policy server computes one ``denoise_step_eps`` per denoising step: batch 1 for one view, batch V
when V views share a pass (the in-process backend, or a worker grouping a request's views). Three
ways of computing the U-Net's Conv1d layers are timed on the same weights and inputs, in
interleaved repetitions (the machine's load hits each alike):

- ``native``: PyTorch's own ``nn.Conv1d`` (oneDNN on the CPU);
- ``gemm``: every Conv1d as im2col + one matrix multiply (``fastpath._GemmConv1dFunction``);
- ``shipped``: ``fastpath.GemmConv1d`` as ``load_policy`` installs it on the CPU (the GEMM, but a
  batch of one without gradients goes to PyTorch's convolution).

Randomly initialised weights (the time does not depend on their values), one intra-op thread (the
workers' and the in-process engine's default), ``torch.no_grad``; with ``bf16``, the weights cast
once and the pass under bfloat16 autocast, as a server with ``precision: bf16`` computes. Reports
the median ms per step.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="tiny,paper-small", help="comma-separated training presets")
    ap.add_argument("--batches", default="1,2,3,5,8", help="comma-separated batch sizes (views in one pass)")
    ap.add_argument("--reps", type=int, default=0, help="timed repetitions per path (default: 200 tiny, 20 others)")
    ap.add_argument("--threads", type=int, default=1, help="intra-op threads")
    ap.add_argument("--precision", default="fp32", help="fp32, bf16, or both: fp32,bf16")
    args = ap.parse_args()

    import torch

    from services.policy.model import DiffusionPolicy, ModelConfig, preset
    from services.policy.model.fastpath import GemmConv1d, _GemmConv1dFunction, cast_matmul_weights, use_gemm_conv1d

    class AlwaysGemm(GemmConv1d):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return _GemmConv1dFunction.apply(x, self.weight, self.bias, self.stride[0], self.padding[0])

    torch.set_num_threads(args.threads)
    batches = [int(b) for b in args.batches.split(",")]
    rows = []
    for name, precision in [(n, p) for n in args.presets.split(",") for p in args.precision.split(",")]:
        if precision not in ("fp32", "bf16"):
            raise SystemExit(f"error: precision {precision!r}: fp32 or bf16")
        cfg = ModelConfig.model_validate(preset(name)["model"])
        native = DiffusionPolicy(cfg, load_pretrained=False).eval()
        if precision == "bf16":
            cast_matmul_weights(native, torch.bfloat16)
        shipped = copy.deepcopy(native)
        use_gemm_conv1d(shipped)
        gemm = copy.deepcopy(shipped)
        for m in gemm.modules():
            if type(m) is GemmConv1d:
                m.__class__ = AlwaysGemm
        paths = {"native": native, "gemm": gemm, "shipped": shipped}
        reps = args.reps or (200 if name == "tiny" else 20)
        for B in batches:
            x = torch.randn(B, cfg.pred_horizon, cfg.action_dim)
            k = torch.full((B,), 5)
            cond = torch.randn(B, cfg.cond_dim)
            times: dict[str, list[float]] = {p: [] for p in paths}
            autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16")
            with torch.no_grad(), autocast:
                for _ in range(max(3, reps // 10)):  # warm-up
                    for policy in paths.values():
                        policy.denoise_step_eps(x, k, cond)
                for _ in range(reps):
                    for p, policy in paths.items():
                        t0 = time.perf_counter()
                        policy.denoise_step_eps(x, k, cond)
                        times[p].append(time.perf_counter() - t0)
            row = {"preset": name, "precision": precision, "batch": B}
            row.update({f"{p}_ms": round(statistics.median(t) * 1e3, 3) for p, t in times.items()})
            print(row, file=sys.stderr, flush=True)
            rows.append(row)
    report("denoise_step", {"threads": args.threads, "rows": rows})


if __name__ == "__main__":
    main()
