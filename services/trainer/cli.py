"""``viewscale train``: train a policy on a dataset from ``viewscale dataset build``.

    viewscale train --data data/ds --preset tiny --steps 2000 --out runs/lift-five15-camera
    viewscale train --config train.yaml --set model.down_dims=[256,512,1024] --set optim.lr=3e-4
    torchrun --nproc_per_node=4 -m services.cli train --data data/ds --preset paper --out runs/paper

Settings: preset < --config YAML < VIEWSCALE_<FIELD> env < the flags below < --set key=value.
Running it again with the same --out resumes from the run's latest checkpoint, with the same seed,
batch size, views, cond_dropout, optim and ema settings (a change of these is refused, naming it;
steps, device, workers, logging, validation and checkpointing may change; another number of
torchrun processes is allowed, with a warning: each step then takes another number of samples).
Ctrl-C (SIGINT, SIGTERM, SIGHUP; under torchrun, to any rank) stops every rank after the same step
and saves it; a second one stops at once, back to the latest checkpoint.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
from pathlib import Path


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event, announce: bool):
    """The first SIGINT, SIGTERM or SIGHUP sets ``stop``: training ends after the step in progress and
    saves a checkpoint there. A second one interrupts at once (back to the latest checkpoint). Only
    in the main thread, where Python handles signals; the previous handlers come back after."""
    from services.core.runtime import set_from_signal_handler, signalled_while_starting

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    seen: list[str] = []  # (the event is set a moment later, on another thread: a second signal at once is second)

    def on_signal(signum, _frame):
        name = signal.Signals(signum).name
        if seen or stop.is_set():
            raise KeyboardInterrupt(name)
        seen.append(name)
        if announce:  # os.write: the progress bar may be writing to stderr at this moment
            os.write(2, f"\n{name}: stopping after this step, saving a checkpoint (again to stop at once)\n".encode())
        set_from_signal_handler(stop)  # (never stop.set() here: see there)

    signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    before = {sig: signal.signal(sig, on_signal) for sig in signals}
    if signalled_while_starting():  # (a Ctrl-C that torch's imports swallowed: see remember_interrupts)
        stop.set()
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _train(args: argparse.Namespace) -> int:
    from services.core.config import ConfigError
    from services.core.runtime import OutputError, exclusive, output_dir
    from services.dataset.store import DatasetError, DatasetStore
    from services.policy.checkpoint import CheckpointError, latest_checkpoint
    from services.trainer.config import load_train_config
    from services.trainer.train import TrainingError, dist_env, train

    flags = {
        "data": args.data,
        "out": args.out,
        "preset": args.preset,
        "steps": args.steps,
        "batch_size": args.batch_size,
        "device": args.device,
        "seed": args.seed,
        "num_workers": args.workers,
        "views": json.dumps([v.strip() for v in args.views.strip("[]").split(",") if v.strip()])
        if args.views is not None
        else None,
    }
    overrides = [f"{k}={v}" for k, v in flags.items() if v is not None]
    if args.no_resume:
        overrides.append("resume=false")
    if args.no_progress:
        overrides.append("progress=false")
    stop = threading.Event()
    cfg = None
    try:
        cfg = load_train_config(args.config, [*overrides, *args.set])
        DatasetStore(cfg.data)  # a wrong --data: one line, and no empty run folder left behind
        # made before the dataset is loaded and the model built; taken back if nothing was written
        # one training per run folder: a second one (another terminal) would write in the same run
        held = exclusive(cfg.out, "training") if dist_env()[0] == 0 else contextlib.nullcontext()
        with output_dir(cfg.out, "--out"), held, _stop_on_signals(stop, announce=dist_env()[0] == 0):
            result = train(cfg, stop=stop)
    except (ConfigError, DatasetError, TrainingError, CheckpointError, OutputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # (a second signal: stopped at once, the step in progress and a save under way lost)
        if cfg is None:
            print("interrupted", file=sys.stderr)
            return 130
        try:
            saved = latest_checkpoint(cfg.out)
        except CheckpointError as exc:
            print(f"interrupted: {exc}", file=sys.stderr)
            return 130
        if saved is None:
            print(f"interrupted: {cfg.out} has no checkpoint yet; the same command starts over", file=sys.stderr)
        else:
            print(f"interrupted: the same command resumes from {saved}", file=sys.stderr)
        return 130
    if result.stopped:
        if dist_env()[0] == 0 and result.checkpoint is None:
            print("stopped before the first step: nothing to save", file=sys.stderr)
        elif dist_env()[0] == 0:
            print(
                f"stopped at step {result.step} of {cfg.steps}: checkpoint {result.checkpoint}; "
                "run the same command to resume",
                file=sys.stderr,
            )
        return 130
    if dist_env()[0] != 0:
        return 0
    summary = {
        "step": result.step,
        "loss": result.loss,
        "val_loss": result.val_loss,
        "checkpoint": str(result.checkpoint) if result.checkpoint else None,
        "loss_png": str(Path(cfg.out) / "loss.png"),
        "samples_per_s": round(result.samples_per_s, 2),
        "data_wait": round(result.data_wait, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        val = f"{result.val_loss:.4f}" if result.val_loss is not None else "-"
        loss = f"{result.loss:.4f}" if result.loss is not None else "-"
        print(f"trained {cfg.out} to step {result.step}: loss {loss}, validation {val}")
        print(f"checkpoint {summary['checkpoint']}\nloss curve {summary['loss_png']}")
    return 0


def add_train_command(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train a single-view diffusion policy on a pseudo-demo dataset",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--data", help="dataset directory (default data/ds)")
    p.add_argument(
        "--out",
        help="run directory: new, empty, or an existing run (resumed); a folder of other files is refused "
        "(default runs/default)",
    )
    p.add_argument("--preset", help="hyper-parameter preset: tiny (default), paper, ...; an unknown name lists them")
    p.add_argument("--steps", type=int, help="total optimisation steps")
    p.add_argument("--batch-size", type=int, help="samples per step (per process)")
    p.add_argument("--device", help="auto, cpu, cuda or cuda:N (default auto)")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--workers", type=int, help="data loader worker processes (default 2)")
    p.add_argument("--views", help="train on these views only, e.g. F,FL,FR (default all of the dataset's)")
    p.add_argument("--config", help="YAML file with training settings (any TrainConfig field)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any setting, dotted for nested ones: model.down_dims=[64,128] (repeatable)",
    )
    p.add_argument("--no-resume", action="store_true", help="refuse to continue an existing run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the result as one JSON line")
    p.set_defaults(func=_train)
