"""Train a single-view diffusion policy on pseudo-demonstrations.

One loop, in the diffusion_policy way: sample a batch of pseudo-demo windows (every view of every
episode is its own demo), take the epsilon-prediction loss, step AdamW under a warm-up + cosine
schedule, update the EMA weights, and every so often validate (EMA weights, held-out episodes),
plot the loss and write a checkpoint.

Runs on the CPU, one GPU (``device``) or several processes under ``torchrun`` (one GPU each,
DistributedDataParallel; rank 0 validates and writes). Everything that decides the next batch
(data order, crops, noise, diffusion steps) comes from seeded generators whose state is in the
checkpoint, so a resumed run takes the same batches and the same noise as one that never stopped.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from safetensors import SafetensorError
from torch.utils.data import DataLoader, Dataset, Sampler

from services.core.config import ConfigError
from services.core.runtime import LOCK_FILE, reading
from services.core.text import first_few
from services.dataset.pseudo_demos import no_chunk_fits
from services.dataset.store import MANIFEST, DatasetError
from services.policy import checkpoint as ckpt
from services.policy.model.diffusion import compute_loss, make_train_scheduler
from services.policy.model.fastpath import ema_update, gemm_conv1d_pays_off, make_optimizer, use_gemm_conv1d
from services.policy.model.policy import DiffusionPolicy, ModelConfig
from services.trainer.config import TrainConfig, explicitly_set
from services.trainer.data import PseudoDemoDataset

log = logging.getLogger("trainer")


class TrainingError(RuntimeError):
    """Training cannot go on (bad data for this config, diverged loss); the message says why."""


@dataclass
class TrainData:
    """What the loop needs from a dataset: windows to train and validate on, and its description."""

    train: Dataset  # items: obs (To, 3, H, W) [-1, 1], state (To, D), action (Tp, 7), view int
    val: Dataset | None  # held-out episodes, or None
    meta: dict[str, Any]  # the dataset's meta.json
    normalizer: dict[str, Any]  # the dataset's normalizer.json (Normalizer.to_dict)
    source: str = ""  # where it came from (dataset directory)


@dataclass
class TrainResult:
    step: int  # steps done in total
    checkpoint: Path | None  # newest checkpoint
    loss: float | None  # mean training loss over the last log interval
    val_loss: float | None  # last validation loss
    steps_per_s: float = 0.0  # this process, this session
    samples_per_s: float = 0.0  # all processes
    data_wait: float = 0.0  # share of wall time spent waiting for the data loader
    stopped: bool = False  # a stop was requested before ``steps``
    compute_dtypes: set[str] = field(default_factory=set)  # dtypes the U-Net computed in (seen in this session)
    channels_last: bool = False  # the encoder's conv weights were NHWC while training
    history: list[dict[str, Any]] = field(default_factory=list)


# -- data -------------------------------------------------------------------------------------


class StepBatchSampler(Sampler[list[int]]):
    """Endless batches from a seeded stream of epoch permutations, addressable by step.

    The stream is perm(epoch 0) ++ perm(epoch 1) ++ ...; step s takes positions
    [s * B * W, (s + 1) * B * W) of it and rank r the r-th B of those. So the batch of a step
    depends only on (seed, step), which is what makes resume exact, and ranks never overlap.
    """

    def __init__(self, n: int, batch_size: int, seed: int, start_step: int = 0, rank: int = 0, world: int = 1):
        if n <= 0:
            raise TrainingError("the training set is empty")
        self.n, self.batch_size, self.seed = n, batch_size, seed
        self.start_step, self.rank, self.world = start_step, rank, world

    def _perm(self, epoch: int) -> list[int]:
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
        return torch.randperm(self.n, generator=g).tolist()

    def batch_at(self, step: int) -> list[int]:
        pos = (step * self.world + self.rank) * self.batch_size
        out: list[int] = []
        epoch, offset = divmod(pos, self.n)
        perm = self._perm(epoch)
        while len(out) < self.batch_size:
            take = perm[offset : offset + self.batch_size - len(out)]
            out += take
            offset += len(take)
            if offset >= self.n:
                epoch, offset = epoch + 1, 0
                perm = self._perm(epoch)
        return out

    def __iter__(self) -> Iterator[list[int]]:
        step = self.start_step
        while True:
            yield self.batch_at(step)
            step += 1


def load_train_data(cfg: TrainConfig) -> TrainData:
    """Open the dataset directory ``cfg.data`` (built by ``viewscale dataset build``): training and
    held-out episodes of the chosen views, with To/Tp/Ta from the model config where the user set
    them (windows are cut when loading) and from the dataset otherwise."""
    horizons = {
        key: getattr(cfg.model, field)
        for key, field in (("To", "obs_horizon"), ("Tp", "pred_horizon"), ("Ta", "n_action_steps"))
        if explicitly_set(cfg, f"model.{field}")
    }
    kwargs = dict(views=cfg.views, **horizons)
    try:
        train_ds = PseudoDemoDataset(cfg.data, split="train", **kwargs)
        val_ds = PseudoDemoDataset(cfg.data, split="val", **kwargs) if cfg.validation else None
    except DatasetError as exc:
        raise TrainingError(str(exc)) from exc
    except ValueError as exc:  # windows that do not fit the episodes (e.g. Tp too long)
        raise TrainingError(f"dataset {cfg.data}: {exc}") from exc
    if len(train_ds) == 0 and train_ds.demos:  # (before: "the training set is empty", not why)
        why = no_chunk_fits(train_ds.To, train_ds.Tp, train_ds.Ta, train_ds.longest_segment)
        raise TrainingError(f"dataset {cfg.data}: no training samples: {why} (set a shorter model.pred_horizon)")
    if val_ds is not None and len(val_ds) == 0:
        val_ds = None
    meta = dict(train_ds.meta)
    meta.update(To=train_ds.To, Tp=train_ds.Tp, Ta=train_ds.Ta)
    meta["val_episodes"] = list(val_ds.episode_ids) if val_ds is not None else []
    meta["train_episodes"] = list(train_ds.episode_ids)
    return TrainData(train_ds, val_ds, meta, train_ds.normalizer.to_dict(), str(Path(cfg.data).resolve()))


def resolve_model_config(cfg: TrainConfig, meta: dict[str, Any]) -> ModelConfig:
    """The model config with what the dataset decides filled in; conflicts are errors."""
    size = meta.get("image_size")
    if isinstance(size, dict):
        size = (int(size["height"]), int(size["width"]))
    fixed = {
        "image_size": tuple(size) if size is not None else None,
        "state_dim": meta.get("state_dim"),
        "obs_horizon": meta.get("To"),
        "pred_horizon": meta.get("Tp"),
        "action_dim": meta.get("action_dim", 7),
    }
    if meta.get("Ta") is not None and not explicitly_set(cfg, "model.n_action_steps"):
        fixed["n_action_steps"] = meta["Ta"]
    data = cfg.model.model_dump()
    for name, value in fixed.items():
        if value is None:
            continue
        if explicitly_set(cfg, f"model.{name}") and tuple(_as_tuple(data[name])) != tuple(_as_tuple(value)):
            raise ConfigError(
                f"model.{name}={data[name]} does not match the dataset ({value}); "
                f"rebuild the dataset or drop the override"
            )
        data[name] = value
    try:
        return ModelConfig.model_validate(data)
    except ValueError as exc:
        raise ConfigError(f"the model config does not fit the dataset {meta.get('image_size')}: {exc}") from exc


def _as_tuple(v: Any) -> tuple:
    return tuple(v) if isinstance(v, (list, tuple)) else (v,)


def check_action_space(cfg: TrainConfig, meta: dict[str, Any]) -> str:
    space = meta.get("action_space")
    if space not in ("base", "eef", "camera"):
        raise TrainingError(f"dataset {cfg.data} has no valid action_space in meta.json (got {space!r})")
    if cfg.action_space is not None and cfg.action_space != space:
        raise TrainingError(
            f"dataset {cfg.data} holds {space!r}-space actions but the config asks for "
            f"{cfg.action_space!r}; rebuild it with `viewscale dataset build --space {cfg.action_space}` "
            f"or set action_space={space}"
        )
    if meta.get("action_dim", 7) != 7:
        raise TrainingError(f"dataset actions have {meta.get('action_dim')} components; the policy expects 7")
    return space


# -- optimisation helpers ---------------------------------------------------------------------


class LossModule(torch.nn.Module):
    """The training loss as a module's forward, so DistributedDataParallel can wrap it."""

    def __init__(self, policy: DiffusionPolicy, scheduler, cond_dropout: float = 0.0):
        super().__init__()
        self.policy = policy
        self.scheduler = scheduler
        self.cond_dropout = cond_dropout

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return compute_loss(self.policy, self.scheduler, batch, self.cond_dropout)


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Linear warm-up to ``optim.lr``, then cosine to 0 at ``steps`` (or flat)."""
    o = cfg.optim
    if step < o.warmup_steps:
        return o.lr * step / max(1, o.warmup_steps)
    if o.schedule == "constant":
        return o.lr
    progress = min(1.0, (step - o.warmup_steps) / max(1, cfg.steps - o.warmup_steps))
    return o.lr * 0.5 * (1.0 + math.cos(math.pi * progress))


class EMA:
    """Exponential moving average of a model's weights, diffusion_policy's schedule:
    decay(step) = clamp(1 - (1 + step / inv_gamma) ** -power, min, max), 0 at step 0.

    ``fast``: one ``_foreach_lerp_`` over all averaged tensors (``fastpath.ema_update``) instead of
    a multiply and an add per tensor."""

    def __init__(self, model: torch.nn.Module, cfg, fast: bool = True):
        import copy

        self.cfg = cfg
        self.fast = fast
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self._pairs: tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]] | None = None

    def decay(self, step: int) -> float:
        if step <= 0:
            return 0.0
        value = 1.0 - (1.0 + step / self.cfg.inv_gamma) ** -self.cfg.power
        return max(self.cfg.min_decay, min(value, self.cfg.max_decay))

    def _tensors(self, model: torch.nn.Module):
        """(averaged, current, copied-into, copied-from): found once; the tensors are updated in place."""
        if self._pairs is None:
            frozen = {name for name, p in model.named_parameters() if not p.requires_grad}  # e.g. the ViT under LoRA
            ema_state = self.model.state_dict()
            avg, cur, dst, src = [], [], [], []
            for name, t in model.state_dict().items():
                ema_t = ema_state[name]
                if ema_t.dtype.is_floating_point and name not in frozen:
                    avg.append(ema_t)
                    cur.append(t)
                else:  # frozen weights and integer buffers are copied, as diffusion_policy does
                    dst.append(ema_t)
                    src.append(t)
            self._pairs = (avg, cur, dst, src)
        return self._pairs

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int) -> None:
        d = self.decay(step)
        avg, cur, dst, src = self._tensors(model)
        if self.fast:
            ema_update(avg, cur, d)
        else:
            for a, c in zip(avg, cur):
                a.mul_(d).add_(c, alpha=1.0 - d)
        for a, c in zip(dst, src):
            a.copy_(c)


def pick_device(spec: str, local_rank: int) -> torch.device:
    """The device ``spec`` names (auto: CUDA if there is one; cuda: this process's local rank),
    checked to exist here: a ConfigError naming what is wrong, not a traceback from torch."""
    if spec == "auto":
        spec = "cuda" if torch.cuda.is_available() else "cpu"
    if spec == "cuda" and torch.cuda.is_available():
        spec = f"cuda:{local_rank}"
    try:
        return ckpt.inference_device(spec)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _loader_leaves_stops_to_training(_worker_id: int) -> None:
    """A data-loader worker leaves the stop signals to the training process: a terminal's Ctrl-C
    reaches the whole process group, and so does SIGTERM from Slurm's scancel, systemd's stop or
    ``kill -- -PGID``. The worker stops when the loader is shut down (or, if the training process
    is killed outright, when torch's watchdog sees its parent gone). A worker ended by the signal
    would make torch's SIGCHLD handler raise in the training process wherever it is, the
    checkpoint save included, and the stop would save nothing."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)


def dist_env() -> tuple[int, int, int]:
    """(rank, local_rank, world) as torchrun sets them; (0, 0, 1) otherwise."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("LOCAL_RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


def _next_batch(it: Iterator[Any], step: int, out: Path) -> Any:
    """The loader's next batch. What fails in the loader (a worker's error, which torch raises again
    here with the worker's traceback as text, or a second Ctrl-C while waiting for a batch) leaves
    without a reference to the loader's iterator: neither the traceback into the loader nor this
    frame's ``it``, nor the error torch raised it from (its words for a worker that died while
    the training waited for a batch, raised from the error of that wait: whose traceback holds the
    iterator). The iterator's workers ignore SIGTERM (``_loader_leaves_stops_to_training``), so an
    exception that kept it alive to the interpreter's exit left the run hung there."""
    try:
        return next(it)
    except BaseException as exc:
        failure = exc.with_traceback(None)
        failure.__context__ = failure.__cause__ = None
    del it  # (this frame is in the traceback of what is raised below)
    if not isinstance(failure, Exception):  # KeyboardInterrupt, SystemExit
        raise failure
    raise _loader_failed(failure, step, out)


def _loader_failed(exc: Exception, step: int, out: Path) -> TrainingError:
    """One line for a loader that failed: a worker that died (killed: out of memory, most often),
    or the error a worker met reading the dataset (a file removed or cut short under the run)."""
    text = str(exc).strip()
    kept = f"the last checkpoint ({ckpt.latest_checkpoint(out) or 'none yet'}) is kept"
    if text.startswith("DataLoader worker (pid"):  # torch's words for a worker gone
        died = text.split(". ")[0].rstrip(".")
        return TrainingError(f"training stopped at step {step}: {died}; {kept}: run the same command to resume")
    said = text.splitlines()[-1] if text else type(exc).__name__
    if "Original Traceback" in text:  # a worker's error, its last line "module.Error: message"
        said = said.split(": ", 1)[-1]
    return TrainingError(f"reading the dataset failed at step {step}: {said}; {kept}")


def _to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items() if torch.is_tensor(v)}


@torch.no_grad()
def validation_loss(policy: DiffusionPolicy, data: Dataset, cfg: TrainConfig, device: torch.device, amp: bool) -> float:
    """Mean loss of ``policy`` (eval mode: centre crops) over the first ``val_batches`` batches,
    with fixed noise so successive passes are comparable; the training RNG is left untouched."""
    sched = make_train_scheduler(policy.cfg.noise)
    loader = DataLoader(data, batch_size=cfg.batch_size, shuffle=False, num_workers=0)
    was_training = policy.training
    policy.eval()
    total, count = 0.0, 0
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(cfg.seed + 12345)
        for i, batch in enumerate(loader):
            if i >= cfg.val_batches:
                break
            batch = _to_device(batch, device)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
                loss = compute_loss(policy, sched, batch)
            n = batch["action"].shape[0]
            total += float(loss) * n
            count += n
    policy.train(was_training)
    return total / max(1, count)


def plot_losses(history: list[dict[str, Any]], path: Path) -> None:
    """Training (per log interval) and validation loss against step, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [(h["step"], h["loss"]) for h in history if h.get("loss") is not None]
    val = [(h["step"], h["val_loss"]) for h in history if h.get("val_loss") is not None]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    if train:
        ax.plot(*zip(*train), label="train", lw=1)
    if val:
        ax.plot(*zip(*val), "o-", label="validation (EMA)", ms=3)
    ax.set_xlabel("step")
    ax.set_ylabel("epsilon MSE")
    if train or val:
        ax.set_yscale("log")
        ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)


def _read_history(path: Path, upto: int) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if row.get("step", 0) <= upto:
            rows.append(row)
    return rows


# -- the loop -----------------------------------------------------------------------------------


# What a resumed run must keep: they choose its samples, noise and updates, and the checkpoint
# records them (its views are what the server composes by default).
RESUME_FIXED = ("seed", "batch_size", "cond_dropout", "optim", "ema")


def resume_diff(info: dict[str, Any], cfg: TrainConfig, views: list[str]) -> list[str]:
    """``name saved (now new)`` for each setting of ``RESUME_FIXED`` and the training views that
    differ between a checkpoint's ``info`` and this run; empty for a checkpoint without the record.
    A setting the record lacks (added since it was written) is not compared."""
    saved = info.get("train")
    if not isinstance(saved, dict):
        return []
    now = cfg.model_dump(mode="json")

    def show(v: Any) -> str:
        return ",".join(map(str, v)) if isinstance(v, list) else str(v)

    out = []
    if info.get("views") is not None and list(info["views"]) != views:
        out.append(f"views {show(info['views'])} (now {show(views)})")
    for name in RESUME_FIXED:
        a, b = ckpt.flat_fields(saved.get(name), name), ckpt.flat_fields(now.get(name), name)
        out += [f"{k} {show(a.get(k))} (now {show(b.get(k))})" for k in sorted(a) if a[k] != b.get(k)]
    return out


RUN_FILES = ("config.json", "checkpoints", "log.jsonl")  # what a run folder holds from its first step


def check_run_dir(out: Path) -> None:
    """ConfigError unless ``out`` is missing, empty or a training run: the run's files would go in
    among others' (the dataset trained on, recorded episodes, a checkpoint), and a later training
    in there would take them for a run of its own."""
    held = sorted(p.name for p in out.iterdir() if p.name != LOCK_FILE) if out.is_dir() else []
    if not held or any(name in held for name in RUN_FILES):
        return
    advice = "choose a new or empty folder for the run"
    if MANIFEST in held:
        what = "a dataset"
    elif ckpt.MODEL_FILE in held:
        what = "a checkpoint"
    elif ckpt.LATEST in held and out.name == "checkpoints":
        what, advice = "a run's checkpoints folder", f"give the run's folder, {out.parent}, to resume it"
    else:
        what = f"a folder of other files ({first_few(held)})"
    raise ConfigError(f"out {out} is {what}, not a training run: {advice}")


def train(
    cfg: TrainConfig,
    data: TrainData | None = None,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    stop: threading.Event | None = None,
) -> TrainResult:
    """Train (or resume) the run in ``cfg.out``; returns when ``cfg.steps`` are done or ``stop`` is set.
    The dataset folder is held for reading meanwhile: its frames are read as the training goes, and a
    dataset build over it would otherwise replace them under the run (or remove them: a crash)."""
    check_run_dir(Path(cfg.out))
    data = data or load_train_data(cfg)
    with reading(data.source, "training") if data.source else contextlib.nullcontext():
        return _train(cfg, data, on_progress, stop)


def _train(
    cfg: TrainConfig,
    data: TrainData,
    on_progress: Callable[[dict[str, Any]], None] | None,
    stop: threading.Event | None,
) -> TrainResult:
    rank, local_rank, world = dist_env()
    device = pick_device(cfg.device, local_rank)
    distributed = world > 1
    if distributed and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    main = rank == 0
    out = Path(cfg.out)
    space = check_action_space(cfg, data.meta)
    model_cfg = resolve_model_config(cfg, data.meta)
    views = list(cfg.views or data.meta.get("views", []))
    cameras = data.meta.get("cameras") or {}

    # Resume or start fresh (a run directory is never silently overwritten).
    latest = ckpt.latest_checkpoint(out)
    if latest is not None and not cfg.resume:
        raise ConfigError(f"{out} already has checkpoints ({latest.name}); resume=true continues it, or pick a new out")
    if latest is not None:
        info = ckpt.read_info(latest)
        diff = ckpt.config_diff(ckpt.model_config(info, latest), model_cfg)
        if diff:
            raise ckpt.CheckpointError(
                f"{latest} was trained with a different model config ({', '.join(diff)}); "
                "use the same preset and overrides to resume, or a new out directory"
            )
        if info.get("normalizer") != data.normalizer or info.get("action_space") != space:
            raise ckpt.CheckpointError(
                f"{latest} was trained on a different dataset (normalizer or action space differ); "
                "resume it with the same --data, or use a new out directory"
            )
        changed = resume_diff(info, cfg, views)
        if changed:
            raise ckpt.CheckpointError(
                f"{latest} was trained with other settings: {', '.join(changed)}; resume it with the same "
                "seed, batch size, views, cond_dropout, optim and ema settings (steps, device, workers and "
                "logging may change), or use a new out directory"
            )

    torch.manual_seed(cfg.seed)  # same initial weights on every rank
    try:
        policy = DiffusionPolicy(model_cfg)
    except (OSError, ValueError, SafetensorError) as exc:  # ViT weights missing or unreadable, LoRA targets it lacks
        raise TrainingError(f"the model cannot be built: {exc}") from None
    policy = policy.to(device)
    use_amp = cfg.amp == "bf16" or (cfg.amp == "auto" and device.type == "cuda" and torch.cuda.is_bf16_supported())
    if cfg.amp == "bf16" and device.type != "cuda":
        log.warning("amp=bf16 on %s: autocast on the CPU is slower than float32 here; using it as asked", device)
    if cfg.channels_last == "on" or (cfg.channels_last == "auto" and device.type == "cuda"):
        policy.use_channels_last()
    if cfg.fast_paths and gemm_conv1d_pays_off(device):
        use_gemm_conv1d(policy)  # same maths, faster kernels (services.policy.model.fastpath)
    ema = EMA(policy, cfg.ema, fast=cfg.fast_paths) if cfg.ema.enabled and main else None
    params = [p for p in policy.parameters() if p.requires_grad]
    o = cfg.optim
    optim = make_optimizer(params, o.lr, tuple(o.betas), o.eps, o.weight_decay, fused=cfg.fast_paths)
    torch.manual_seed(cfg.seed + 1 + rank)  # crops, noise and diffusion steps differ between ranks
    start = 0
    history: list[dict[str, Any]] = []
    if latest is not None:
        tensors, state = ckpt.read_train_state(latest)
        raw = {k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")}
        ckpt.load_state_checked(policy, raw, f"{latest} (training weights)")
        if ema is not None:
            ckpt.load_state_checked(ema.model, ckpt.read_weights(latest / ckpt.MODEL_FILE), f"{latest} (EMA weights)")
        ckpt.optimizer_from_tensors(optim, tensors, state["optim_groups"])
        rng_key = f"rng.torch.{rank}"
        if rng_key in tensors:
            torch.set_rng_state(tensors[rng_key])
        if device.type == "cuda" and f"rng.cuda.{rank}" in tensors:
            torch.cuda.set_rng_state(tensors[f"rng.cuda.{rank}"], device)
        start = int(state["step"])
        history = _read_history(out / "log.jsonl", start)
        if main:
            log.info("resuming %s from step %d", out, start)
        saved_world = int(state.get("world", 1))
        if main and saved_world != world:  # allowed (a run moves to the GPUs there are), but not exact
            log.warning(
                "%s was written by %d training processes and is resumed by %d: from step %d on, a step "
                "takes %d samples instead of %d, and the run is no longer the one it would have been",
                latest,
                saved_world,
                world,
                start,
                cfg.batch_size * world,
                cfg.batch_size * saved_world,
            )
    sched = make_train_scheduler(model_cfg.noise)
    net: torch.nn.Module = LossModule(policy, sched, cfg.cond_dropout)
    if distributed:
        net = torch.nn.parallel.DistributedDataParallel(
            net, device_ids=[device.index] if device.type == "cuda" else None
        )

    if main:
        out.mkdir(parents=True, exist_ok=True)
    if main and (latest is None or start < cfg.steps):  # (a run with nothing to train keeps the settings it has)
        run_cfg = cfg.model_dump(mode="json")
        run_cfg["model"] = model_cfg.model_dump(mode="json")
        (out / "config.json").write_text(json.dumps(run_cfg, indent=2) + "\n")

    sampler = StepBatchSampler(len(data.train), cfg.batch_size, cfg.seed, start, rank, world)
    loader = DataLoader(
        data.train,
        batch_sampler=sampler,
        num_workers=cfg.num_workers,
        pin_memory=device.type == "cuda",
        persistent_workers=cfg.num_workers > 0,
        # its own generator: creating the iterator must not draw from the training RNG stream
        generator=torch.Generator().manual_seed(cfg.seed + rank),
        worker_init_fn=_loader_leaves_stops_to_training,
    )

    info_base = {
        "model": model_cfg.model_dump(mode="json"),
        "normalizer": data.normalizer,
        "action_space": space,
        "state_frame": data.meta.get("state_frame"),
        "views": views,
        "calibration": {v: cameras.get(v) for v in views},
        "To": model_cfg.obs_horizon,
        "Tp": model_cfg.pred_horizon,
        "n_action_steps": model_cfg.n_action_steps,
        "control_hz": data.meta.get("control_hz"),
        "tasks": data.meta.get("tasks", []),
        "rigs": data.meta.get("rigs", []),
        "dataset": {
            "path": data.source,
            "episodes": data.meta.get("train_episodes") or [e.get("id") for e in data.meta.get("episodes", [])],
            "val_episodes": data.meta.get("val_episodes", []),
        },
        "train": cfg.model_dump(mode="json"),
    }

    def save(step: int, loss: float | None, val: float | None) -> Path:
        serve = (ema.model if ema is not None else policy).state_dict()
        if not all(torch.isfinite(t).all() for t in serve.values() if t.dtype.is_floating_point):
            raise TrainingError(f"weights are not finite at step {step}; the last good checkpoint is kept")
        optim_t, groups = ckpt.optimizer_to_tensors(optim)
        train_t = {f"model.{k}": v for k, v in policy.state_dict().items()}
        train_t.update(optim_t)
        train_t[f"rng.torch.{rank}"] = torch.get_rng_state()
        if device.type == "cuda":
            train_t[f"rng.cuda.{rank}"] = torch.cuda.get_rng_state(device)
        return ckpt.save_checkpoint(
            out,
            step,
            serve,
            {**info_base, "loss": loss, "val_loss": val},
            train_t,
            {"optim_groups": groups, "world": world},
            keep=cfg.keep_checkpoints,
        )

    if main and latest is not None and start >= cfg.steps:
        log.warning(
            "%s is already at step %d (steps=%d): nothing to train; raise --steps to go on", out, start, cfg.steps
        )
    bar = None
    if main and cfg.progress and start < cfg.steps:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.steps, initial=start, desc="train", unit="step", dynamic_ncols=True, smoothing=0.1)

    # a resumed run's losses are its checkpoint's until this session logs others
    last_loss = next((h["loss"] for h in reversed(history) if h.get("loss") is not None), None)
    last_val = next((h["val_loss"] for h in reversed(history) if h.get("val_loss") is not None), None)
    result = TrainResult(step=start, checkpoint=latest, loss=last_loss, val_loss=last_val, history=history)
    step = start
    t_start = time.perf_counter()
    wait = 0.0
    interval_losses: list[float] = []
    t_interval, n_interval = time.perf_counter(), 0
    log_file = (out / "log.jsonl").open("a") if main else None
    if main and latest is not None:
        # drop log lines past the checkpoint we resumed from (a crash after it logged on)
        (out / "log.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))
    policy.train()
    # What the first step really computed in: the U-Net output under autocast, the conv layout.
    watch = policy.noise_model.final_conv.register_forward_hook(
        lambda _m, _i, out: result.compute_dtypes.add(str(out.dtype).removeprefix("torch."))
    )
    result.channels_last = all(
        p.is_contiguous(memory_format=torch.channels_last) for p in policy.encoder.parameters() if p.dim() == 4
    )
    saved_at = start  # the step of the newest checkpoint
    it = None
    try:
        it = iter(loader)
        while step < cfg.steps:
            if not distributed and stop is not None and stop.is_set():
                result.stopped = True
                break
            t0 = time.perf_counter()
            batch = _to_device(_next_batch(it, step, out), device)
            wait += time.perf_counter() - t0

            lr = lr_at(step, cfg)
            for g in optim.param_groups:
                g["lr"] = lr
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
                loss = net(batch)
            check = loss.detach().clone()
            stopping = False
            if distributed:
                # The loss averaged over the ranks, and whether any rank was asked to stop: all of
                # them stop after the same step (a rank stopping alone would leave the others waiting
                # in the next step's all_reduce).
                asked = float(stop is not None and stop.is_set())
                both = torch.stack([check.float(), torch.tensor(asked, device=check.device)])
                dist.all_reduce(both)
                check, stopping = both[0] / world, bool(both[1] > 0)
            if not torch.isfinite(check):
                raise TrainingError(
                    f"loss is {float(check)} at step {step}: training stopped; the last good checkpoint "
                    f"({ckpt.latest_checkpoint(out) or 'none yet'}) is kept. Lower optim.lr or check the dataset"
                )
            optim.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.optim.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, cfg.optim.grad_clip)
            optim.step()
            step += 1
            watch.remove()
            if ema is not None:
                ema.update(policy, step)
            interval_losses.append(float(check))
            n_interval += 1
            if bar is not None:
                bar.update(1)

            if not distributed:  # (a stop set during this step: logged and saved at this step)
                stopping = stop is not None and stop.is_set()
            last = step == cfg.steps
            # decided alike on every rank, so that all of them meet at the barrier below
            val_due = data.val is not None and bool((cfg.val_every and step % cfg.val_every == 0) or last)
            ckpt_due = bool((cfg.checkpoint_every and step % cfg.checkpoint_every == 0) or last)
            do_val = main and val_due
            do_log = step % cfg.log_every == 0 or last or do_val or stopping
            if do_log and main:
                now = time.perf_counter()
                it_s = n_interval / max(1e-9, now - t_interval)
                row: dict[str, Any] = {
                    "step": step,
                    "loss": sum(interval_losses) / len(interval_losses),
                    "lr": lr,
                    "it_s": round(it_s, 3),
                    "samples_s": round(it_s * cfg.batch_size * world, 2),
                    "data_wait": round(wait / max(1e-9, now - t_start), 3),
                }
                if do_val:
                    row["val_loss"] = validation_loss(
                        ema.model if ema is not None else policy, data.val, cfg, device, use_amp
                    )
                    result.val_loss = row["val_loss"]
                result.loss = row["loss"]
                history.append(row)
                log_file.write(json.dumps(row) + "\n")
                log_file.flush()
                if bar is not None:
                    post = {"loss": f"{row['loss']:.4f}", "lr": f"{lr:.2e}"}
                    if result.val_loss is not None:
                        post["val"] = f"{result.val_loss:.4f}"
                    bar.set_postfix(post, refresh=False)
                if on_progress is not None:
                    eta = (cfg.steps - step) / it_s if it_s > 0 else None
                    on_progress(
                        {**row, "steps": cfg.steps, "eta_s": eta, "val_loss": result.val_loss, "state": "running"}
                    )
                if do_val or last:
                    plot_losses(history, out / "loss.png")
                interval_losses, t_interval, n_interval = [], now, 0
            if main and ckpt_due:
                result.checkpoint = save(step, result.loss, result.val_loss)
                saved_at = step
            if distributed and (val_due or ckpt_due):
                dist.barrier()
            if stopping and not last:
                result.stopped = True
                break
        if result.stopped and main and step > saved_at:
            result.checkpoint = save(step, result.loss, result.val_loss)
            plot_losses(history, out / "loss.png")
    except RuntimeError as exc:
        # torch's SIGCHLD handler raises this wherever the training is when a loader worker dies
        if str(exc).startswith("DataLoader worker (pid"):
            raise _loader_failed(exc, step, out) from None
        raise
    finally:
        if bar is not None:
            bar.close()
        if log_file is not None:
            log_file.close()
        # The loader's workers end here (the iterator's last reference): they ignore SIGTERM, which
        # is all multiprocessing's exit handler would send them, so left to exit the run would hang.
        del loader, it

    elapsed = time.perf_counter() - t_start
    result.step = step
    result.history = history
    if step > start:
        result.steps_per_s = (step - start) / elapsed
        result.samples_per_s = result.steps_per_s * cfg.batch_size * world
        result.data_wait = wait / elapsed
    if distributed:
        dist.barrier()
    return result
