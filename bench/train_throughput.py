"""Training throughput: samples/s of the real training loop on a real dataset, per preset and batch.

    python bench/train_throughput.py --preset tiny --batch 32
    python bench/train_throughput.py --preset paper --batch 64 --steps 4 --device cuda

Without --data it records two scripted lift episodes in sim (`viewscale collect`, three15 rig,
--size px) and builds a camera-space dataset from them, so the data loader is the real one
(JPEG-decoded frames in memory-mapped arrays). Runs ``services.trainer.train.train`` for
--warmup + --steps steps and reports the steady-state it/s and samples/s (after warm-up), the
share of wall time the loop waited for the data loader (near 0: the loader keeps up), and on a
GPU its mean utilisation (nvidia-smi's, sampled while training) and peak memory.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report  # noqa: E402


def make_dataset(root: Path, size: int) -> Path:
    from services.cli import main as viewscale

    raw, ds = root / "raw", root / "ds"
    if (
        viewscale(
            [
                "collect",
                "--task",
                "lift",
                "--episodes",
                "2",
                "--rig",
                "three15",
                "--out",
                str(raw),
                "--size",
                str(size),
                "--fast",
            ]
        )
        != 0
    ):
        raise SystemExit("collect failed")
    if (
        viewscale(
            [
                "dataset",
                "build",
                "--raw",
                str(raw),
                "--views",
                "F,FL,FR",
                "--space",
                "camera",
                "--out",
                str(ds),
                "--image-size",
                f"{size}x{size}",
                "--contact-episodes",
                "0",
            ]
        )
        != 0
    ):
        raise SystemExit("dataset build failed")
    return ds


class GpuSampler:
    """Mean GPU utilisation (%) while training, from torch.cuda.utilization (NVML)."""

    def __init__(self):
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        import torch

        while not self._stop.wait(0.2):
            try:
                self.samples.append(float(torch.cuda.utilization()))
            except Exception:
                return

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    @property
    def mean(self) -> float | None:
        return round(sum(self.samples) / len(self.samples), 1) if self.samples else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=30, help="timed steps (after warm-up)")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--size", type=int, default=84, help="frame size of the generated dataset")
    ap.add_argument("--data", default=None, help="an existing dataset directory instead of a generated one")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = ap.parse_args()

    import torch

    from services.trainer.config import train_config_from_dict
    from services.trainer.train import train

    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="vs-train-bench-") as tmp:
        data = Path(args.data) if args.data else make_dataset(Path(tmp), args.size)
        stamps: list[float] = []
        cfg = train_config_from_dict(
            {
                "preset": args.preset,
                "data": str(data),
                "out": str(Path(tmp) / "run"),
                "steps": args.warmup + args.steps,
                "batch_size": args.batch,
                "device": args.device,
                "num_workers": args.workers,
                "progress": False,
                "log_every": 1,
                "val_every": 0,
                "checkpoint_every": 0,
                "validation": False,
            }
        )
        with GpuSampler() as gpu:
            result = train(cfg, on_progress=lambda ev: stamps.append(time.perf_counter()))
        timed = stamps[args.warmup - 1 :] if args.warmup > 0 else stamps
        it_s = (len(timed) - 1) / (timed[-1] - timed[0])
        device = (
            "cuda" if (args.device == "auto" and torch.cuda.is_available()) or args.device.startswith("cuda") else "cpu"
        )
        import json

        from services.policy.model.policy import DiffusionPolicy, ModelConfig

        params = DiffusionPolicy(
            ModelConfig.model_validate(json.loads((Path(tmp) / "run" / "config.json").read_text())["model"]),
            load_pretrained=False,
        ).num_parameters()
    report(
        "train_throughput",
        {
            "preset": args.preset,
            "batch": args.batch,
            "device": device,
            "gpu": torch.cuda.get_device_name(0) if device == "cuda" else None,
            "threads": torch.get_num_threads(),
            "workers": args.workers,
            "image": args.size,
            "params_M": round(params / 1e6, 2),
            "steps_timed": len(timed) - 1,
            "it_s": round(it_s, 3),
            "samples_s": round(it_s * args.batch, 1),
            "data_wait": round(result.data_wait, 3),
            "loader_keeps_up": result.data_wait < 0.05,
            "gpu_util_pct": gpu.mean if device == "cuda" else None,
            "gpu_peak_mem_GiB": round(torch.cuda.max_memory_allocated() / 2**30, 2) if device == "cuda" else None,
            "bf16": device == "cuda" and torch.cuda.is_bf16_supported(),
            "final_loss": round(result.loss, 4) if result.loss is not None else None,
        },
    )


if __name__ == "__main__":
    main()
