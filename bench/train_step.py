"""One training step, phase by phase: the fast paths against the plain PyTorch modules, interleaved.

    python bench/train_step.py                                   # tiny, paper-small, paper; 1 and 2 threads
    python bench/train_step.py --presets tiny --threads 1 --reps 20

For each preset it builds two identical policies (same seed), one with the plain modules (PyTorch's
Conv1d, AdamW's default per-tensor loop, a multiply-add EMA) and one with
``services.policy.model.fastpath`` (GEMM Conv1d, fused AdamW, foreach EMA), and then alternates
one step of each, so the machine's load falls on both alike. Each step is timed by phase:
encoder (forward and backward), U-Net (forward and backward, with the loss), optimizer, EMA.
Inputs are random tensors of the preset's shapes (84x84 frames, To = 2, camera-space state,
Tp = 16): the time of a step does not depend on what the pixels show. Reports the median per
phase and the speed-up of the whole step (plain time / fast time).
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

PHASES = ("encoder", "unet", "optimizer", "ema")


def build(preset_name: str, fast: bool, size: int, state_dim: int):
    import torch

    from services.policy.model.diffusion import make_train_scheduler
    from services.policy.model.fastpath import make_optimizer, use_gemm_conv1d
    from services.policy.model.policy import DiffusionPolicy, ModelConfig
    from services.policy.model.presets import preset
    from services.trainer.config import EmaConfig, OptimConfig
    from services.trainer.train import EMA

    p = preset(preset_name)
    mc = ModelConfig.model_validate({**p["model"], "image_size": (size, size), "state_dim": state_dim})
    torch.manual_seed(0)
    policy = DiffusionPolicy(mc)
    if fast:
        use_gemm_conv1d(policy)
    o = OptimConfig.model_validate(p.get("optim", {}))
    params = [q for q in policy.parameters() if q.requires_grad]
    optim = make_optimizer(params, o.lr, tuple(o.betas), o.eps, o.weight_decay, fused=fast)
    ema = EMA(policy, EmaConfig.model_validate(p.get("ema", {})), fast=fast)
    return policy, make_train_scheduler(mc.noise), optim, ema, mc


def one_step(policy, sched, optim, ema, batch, step: int) -> dict[str, float]:
    import torch
    import torch.nn.functional as F

    t0 = time.perf_counter()
    cond = policy.encode(batch["obs"], batch["state"])  # (B, Dc)
    cond_in = cond.detach().requires_grad_(True)  # split the backward pass at the conditioning
    t1 = time.perf_counter()
    actions = batch["action"]
    noise = torch.randn_like(actions)
    k = torch.randint(0, sched.config.num_train_timesteps, (actions.shape[0],)).long()
    pred = policy.denoise_step_eps(sched.add_noise(actions, noise, k), k, cond_in)
    loss = F.mse_loss(pred, noise)
    optim.zero_grad(set_to_none=True)
    loss.backward()
    t2 = time.perf_counter()
    cond.backward(cond_in.grad)
    t3 = time.perf_counter()
    optim.step()
    t4 = time.perf_counter()
    ema.update(policy, step)
    t5 = time.perf_counter()
    return {"encoder": (t1 - t0) + (t3 - t2), "unet": t2 - t1, "optimizer": t4 - t3, "ema": t5 - t4}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="tiny,paper-small,paper")
    ap.add_argument("--threads", default="1,2", help="intra-op thread counts to run")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--reps", type=int, default=10, help="timed steps per path (tiny); paper presets: --paper-reps")
    ap.add_argument("--paper-reps", type=int, default=3)
    args = ap.parse_args()

    import torch

    rows = []
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        for name in args.presets.split(","):
            reps = args.paper_reps if name.startswith("paper") else args.reps
            paths = {"plain": build(name, False, args.size, 10), "fast": build(name, True, args.size, 10)}
            mc = paths["plain"][4]
            g = torch.Generator().manual_seed(0)
            B, To = args.batch, mc.obs_horizon
            batch = {
                "obs": torch.rand((B, To, 3, args.size, args.size), generator=g) * 2 - 1,
                "state": torch.randn((B, To, 10), generator=g),
                "action": torch.rand((B, mc.pred_horizon, mc.action_dim), generator=g) * 2 - 1,
            }
            times: dict[str, list[dict[str, float]]] = {"plain": [], "fast": []}
            for i in range(reps + 1):  # the first step of each pays for allocations: not counted
                for path, (policy, sched, optim, ema, _) in paths.items():
                    t = one_step(policy, sched, optim, ema, batch, i + 1)
                    if i:
                        times[path].append(t)
            row = {"preset": name, "threads": threads, "batch": B, "size": args.size, "reps": reps}
            for path, ts in times.items():
                row[path] = {ph: round(statistics.median(t[ph] for t in ts) * 1e3, 2) for ph in PHASES}
                row[path]["step_ms"] = round(statistics.median(sum(t.values()) for t in ts) * 1e3, 2)
            row["speedup"] = round(row["plain"]["step_ms"] / row["fast"]["step_ms"], 3)
            print(row, file=sys.stderr, flush=True)
            rows.append(row)
    report("train_step", {"device": "cpu", "rows": rows})


if __name__ == "__main__":
    main()
