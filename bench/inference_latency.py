"""Single-view inference latency: the encoder once, then the DDIM steps, at batch 1.

    python bench/inference_latency.py --preset tiny
    python bench/inference_latency.py --preset paper --device cuda --steps 10

Times what a per-view worker does per control step: ``policy.encode`` on one observation
(To frames), then ``--steps`` calls of ``denoise_step`` (U-Net + DDIM update) from the cached
features. Randomly initialised weights (latency does not depend on their values); reports the
median and 90th percentile over --reps repetitions after --warmup.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--steps", type=int, default=10, help="DDIM steps")
    ap.add_argument("--size", type=int, default=84, help="frame size")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()

    import torch

    from services.policy.model import DiffusionPolicy, ModelConfig, denoise_step, make_inference_scheduler, preset

    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(
        "cuda"
        if args.device == "auto" and torch.cuda.is_available()
        else ("cpu" if args.device == "auto" else args.device)
    )
    cfg = ModelConfig.model_validate(
        {
            **preset(args.preset)["model"],
            "image_size": (args.size, args.size),
            "state_dim": 10,
            "noise": {"num_inference_steps": args.steps},
        }
    )
    torch.manual_seed(0)
    policy = DiffusionPolicy(cfg, load_pretrained=False).to(device).eval()
    sched = make_inference_scheduler(cfg.noise)
    obs = torch.rand(1, cfg.obs_horizon, 3, args.size, args.size, device=device) * 2 - 1
    state = torch.rand(1, cfg.obs_horizon, 10, device=device) * 2 - 1

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    enc_ms, step_ms, total_ms = [], [], []
    with torch.inference_mode():
        for rep in range(args.warmup + args.reps):
            sync()
            t0 = time.perf_counter()
            cond = policy.encode(obs, state)
            sync()
            t1 = time.perf_counter()
            x = torch.randn(1, cfg.pred_horizon, cfg.action_dim, device=device)
            for k in sched.timesteps.tolist():
                x = denoise_step(policy, sched, x, k, cond)
            sync()
            t2 = time.perf_counter()
            if rep >= args.warmup:
                enc_ms.append(1e3 * (t1 - t0))
                step_ms.append(1e3 * (t2 - t1) / len(sched.timesteps))
                total_ms.append(1e3 * (t2 - t0))

    def p90(v):
        return sorted(v)[int(0.9 * (len(v) - 1))]

    report(
        "inference_latency",
        {
            "preset": args.preset,
            "device": str(device),
            "threads": torch.get_num_threads(),
            "image": args.size,
            "ddim_steps": args.steps,
            "params_M": round(policy.num_parameters() / 1e6, 2),
            "encode_ms_p50": round(statistics.median(enc_ms), 2),
            "step_ms_p50": round(statistics.median(step_ms), 2),
            "total_ms_p50": round(statistics.median(total_ms), 2),
            "total_ms_p90": round(p90(total_ms), 2),
            "reps": args.reps,
        },
    )


if __name__ == "__main__":
    main()
