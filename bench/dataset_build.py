"""Dataset cache build throughput against JPEG decode alone, and data-loader throughput.

    python bench/dataset_build.py                       # collects 10 lift episodes (84 px) first
    python bench/dataset_build.py --size 224 --image-size 84
    python bench/dataset_build.py --raw data/raw        # use episodes already recorded

Reports, in one run on the same episodes:
- ``decode_fps``: frames/s of ``cv2.imdecode`` alone on every JPEG payload of the chosen views
  (payloads already in memory: the floor any cache build pays);
- ``build_fps``: frames/s of a full ``build_dataset`` (read MCAP, hash, align, decode, resize,
  write arrays, normalizer, summary, contact sheet), forced to rebuild every episode, with
  ``--jobs`` episodes at once; ``episode_stage_fps`` counts only the per-episode work
  (read, align, decode, resize, write), the part that grows with the data;
- ``loader_samples_per_s``: training items/s from a DataLoader at batch 64 with 2 workers,
  shuffled, after the first batch (worker start-up excluded).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.common import report  # noqa: E402
from services.core import topics  # noqa: E402
from services.dataset.build import BuildParams, build_dataset, find_episodes  # noqa: E402
from services.recorder.reader import read_episode  # noqa: E402


def collect_episodes(out: Path, episodes: int, size: int, task: str, rig: str) -> None:
    from services.cli import main as viewscale

    rc = viewscale(
        [
            "collect",
            "--task",
            task,
            "--episodes",
            str(episodes),
            "--rig",
            rig,
            "--out",
            str(out),
            "--size",
            str(size),
            "--fast",
        ]
    )
    if rc != 0:
        raise SystemExit(f"collection failed (exit {rc})")


def decode_only(paths: list[Path], views: list[str], repeats: int) -> tuple[int, float]:
    payloads = []
    for p in paths:
        ep = read_episode(p, topics=[topics.camera_image(v).mcap_topic for v in views])
        for v in views:
            payloads += [r.msg.data for r in ep.messages(topics.camera_image(v).mcap_topic)]
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for data in payloads:
            bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        best = min(best, time.perf_counter() - t)
    return len(payloads), best


def loader_rate(ds_dir: Path, batch: int, workers: int, batches: int) -> tuple[float, int]:
    import torch

    from services.trainer.data import load_dataset

    ds = load_dataset(ds_dir, split="all")
    loader = torch.utils.data.DataLoader(
        ds, batch_size=batch, shuffle=True, num_workers=workers, persistent_workers=workers > 0, drop_last=True
    )
    if len(loader) == 0:
        raise SystemExit(f"dataset has {len(ds)} samples, fewer than one batch of {batch}")
    seen, t0 = 0, None
    while seen < batches:
        for b in loader:
            if t0 is None:  # first batch: workers starting
                t0 = time.perf_counter()
                continue
            assert b["obs"].shape[0] == batch
            seen += 1
            if seen >= batches:
                break
    return seen * batch / (time.perf_counter() - t0), len(ds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--raw", default=None, help="existing episode directory (default: collect into a temp dir)")
    ap.add_argument("--episodes", type=int, default=10, help="episodes to collect (default 10)")
    ap.add_argument("--size", type=int, default=84, help="collected frame size in px (default 84)")
    ap.add_argument("--task", default="lift")
    ap.add_argument("--rig", default="five15")
    ap.add_argument("--views", default="F,FL,FR,FU,FD")
    ap.add_argument("--image-size", type=int, default=84, help="cached frame size (default 84)")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--batches", type=int, default=100, help="batches timed for the loader (default 100)")
    ap.add_argument("--jobs", type=int, default=min(8, os.cpu_count() or 1), help="build processes")
    args = ap.parse_args()
    views = args.views.split(",")

    with tempfile.TemporaryDirectory(prefix="vs-bench-ds-") as tmp:
        tmp = Path(tmp)
        raw = Path(args.raw) if args.raw else tmp / "raw"
        if not args.raw:
            collect_episodes(raw, args.episodes, args.size, args.task, args.rig)
        paths = find_episodes(raw)
        n_dec, t_dec = decode_only(paths, views, repeats=3)

        out = tmp / "ds"
        params = BuildParams(views=tuple(views), space="camera", image_size=(args.image_size, args.image_size))
        res = build_dataset(raw, out, params, force=True, jobs=args.jobs)
        t_build = res.seconds
        loader_sps, n_samples = loader_rate(out, args.batch, args.workers, args.batches)
        report(
            "dataset_build",
            {
                "episodes": len(paths),
                "views": len(views),
                "source_px": args.size if not args.raw else None,
                "cache_px": args.image_size,
                "frames": res.frames,
                "decode_fps": round(n_dec / t_dec, 1),
                "build_fps": round(res.frames / t_build, 1),
                "build_vs_decode": round((res.frames / t_build) / (n_dec / t_dec), 3),
                "build_s": round(t_build, 2),
                "episode_stage_fps": round(res.frames / res.episode_seconds, 1),
                "build_jobs": args.jobs,
                "samples": n_samples,
                "loader_batch": args.batch,
                "loader_workers": args.workers,
                "loader_samples_per_s": round(loader_sps, 1),
                "cpu_cores": os.cpu_count(),
            },
        )


if __name__ == "__main__":
    main()
