"""Training configuration: one frozen model, loaded as preset < YAML < env < ``--set``.

The preset (``tiny``, ``paper``, ...; see ``services.policy.model.presets``) stands in for the
defaults, so a YAML file or a command-line override always wins over it. The dataset fills in
what it decides (frame size, state size, To, Tp) when training starts; a value the user set that
disagrees with the dataset is an error rather than a silent change.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from services.core.bus import BusConfig
from services.core.config import ConfigError, Frozen, LogLevel, checked_names, load_config, validate_config
from services.policy.model.policy import ModelConfig
from services.policy.model.presets import PRESETS, preset


class OptimConfig(Frozen):
    lr: float = Field(1e-4, gt=0)  # AdamW peak learning rate
    betas: tuple[float, float] = (0.95, 0.999)  # AdamW betas (diffusion_policy's), each in [0, 1)
    eps: float = Field(1e-8, gt=0)  # AdamW epsilon
    weight_decay: float = Field(1e-6, ge=0)  # AdamW weight decay
    warmup_steps: int = Field(500, ge=0)  # linear warm-up from 0 to lr
    schedule: Literal["cosine", "constant"] = "cosine"  # after warm-up: cosine decay to 0 at `steps`, or flat
    grad_clip: float = Field(0.0, ge=0)  # max global gradient norm; 0 = no clipping

    @field_validator("betas")
    @classmethod
    def _betas(cls, betas: tuple[float, float]) -> tuple[float, float]:
        if not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError("each must be in [0, 1)")
        return betas


class EmaConfig(Frozen):
    enabled: bool = True  # keep an exponential moving average of the weights (what checkpoints serve)
    power: float = Field(0.75, gt=0)  # decay = 1 - (1 + step / inv_gamma) ** -power, as diffusion_policy's EMAModel
    inv_gamma: float = Field(1.0, gt=0)  # see power
    min_decay: float = Field(0.0, ge=0, le=1)  # lower clamp of the decay
    max_decay: float = Field(0.9999, ge=0, le=1)  # upper clamp of the decay

    @model_validator(mode="after")
    def _clamps(self) -> EmaConfig:
        if self.min_decay > self.max_decay:
            raise ValueError(f"min_decay {self.min_decay} is above max_decay {self.max_decay}")
        return self


class TrainConfig(Frozen):
    data: str = "data/ds"  # dataset directory written by `viewscale dataset build`
    out: str = "runs/default"  # run directory: checkpoints, log.jsonl, loss.png
    preset: str = "tiny"  # hyper-parameter preset applied under YAML/env/CLI values
    steps: int = Field(2000, ge=1)  # optimisation steps in total (a resumed run continues to this count)
    batch_size: int = Field(32, ge=1)  # samples per step per process
    seed: int = 0  # seeds weights, data order, crops and noise
    device: str = "auto"  # auto (cuda if present, else cpu), cpu, cuda, cuda:N; under torchrun: cuda:LOCAL_RANK
    amp: Literal["auto", "bf16", "off"] = "auto"  # bf16 autocast: auto = on for CUDA devices that support it
    channels_last: Literal["auto", "on", "off"] = "auto"  # NHWC images for the encoder: auto = on for CUDA
    num_workers: int = Field(2, ge=0)  # data loader worker processes
    validation: bool = True  # validate on the dataset's held-out episodes (its build decides which)
    val_every: int = Field(200, ge=0)  # steps between validation passes; 0 = only at the end
    val_batches: int = Field(8, ge=1)  # batches per validation pass
    log_every: int = Field(10, ge=1)  # steps between log.jsonl lines and progress events
    checkpoint_every: int = Field(500, ge=0)  # steps between checkpoints; 0 = only at the end
    keep_checkpoints: int = Field(2, ge=1)  # newest checkpoints kept on disk
    resume: bool = True  # continue from the run directory's latest checkpoint when there is one
    progress: bool = True  # progress bar on stderr
    action_space: Literal["base", "eef", "camera"] | None = None  # expected action space; None = the dataset's
    views: list[str] | None = None  # train on these views of the dataset only; None = all
    fast_paths: bool = True  # the measured faster kernels for the same maths (GEMM Conv1d on the CPU, fused
    # AdamW, one-pass EMA: services.policy.model.fastpath); false = the plain PyTorch modules
    cond_dropout: float = Field(0.0, ge=0.0, lt=1.0)  # share of samples trained unconditioned (zero cond):
    # lets the server compose views as an exact product with the unconditional branch
    model: ModelConfig = Field(default_factory=ModelConfig)  # policy architecture
    optim: OptimConfig = Field(default_factory=OptimConfig)  # optimiser and LR schedule
    ema: EmaConfig = Field(default_factory=EmaConfig)  # weight averaging

    @field_validator("views")
    @classmethod
    def _views(cls, views: list[str] | None) -> list[str] | None:
        return checked_names(views, "names no view (leave it out for all of the dataset's)")

    @model_validator(mode="after")
    def _check(self) -> TrainConfig:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        return self


class TrainerServiceConfig(Frozen):
    bus: BusConfig = Field(default_factory=BusConfig)  # zenoh session
    jobs_dir: str | None = None  # watch this directory for *.yaml / *.json job files; None = queries only
    poll_s: float = Field(1.0, gt=0)  # how often the jobs directory is scanned
    # a job file is taken once it has not changed for this long: one being written (copied, saved by
    # an editor) is not read half-written; moving a finished file in is taken at the next scan after
    settle_s: float = Field(1.0, ge=0)
    progress_every_s: float = Field(1.0, ge=0)  # minimum seconds between progress messages
    defaults: list[str] = Field(default_factory=list)  # `key=value` overrides applied under every job's own
    log_level: LogLevel = "INFO"  # logging level of the process


def preset_layer(data: Mapping[str, Any]) -> dict[str, Any]:
    """The base layer of a training config: the preset it names (default ``tiny``)."""
    name = data.get("preset", TrainConfig.model_fields["preset"].default)
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return preset(name)


def train_config_from_dict(data: Mapping[str, Any], source: str = "") -> TrainConfig:
    """Validate ``data`` (YAML/env/CLI values merged) on top of its preset."""
    return validate_config(TrainConfig, data, preset_layer, source)


def load_train_config(
    yaml_path: str | Path | None = None,
    overrides: Iterable[str] = (),
    environ: Mapping[str, str] | None = None,
    section: str | None = None,
) -> TrainConfig:
    """preset < YAML (optionally one ``section`` of it) < ``VIEWSCALE_*`` env < ``key=value`` overrides."""
    return load_config(TrainConfig, yaml_path, overrides, environ, section, base=preset_layer, yaml_from_env=False)


def explicitly_set(cfg: Frozen, path: str) -> bool:
    """Whether the dotted field ``path`` was given (by a preset, YAML, env or CLI) rather than defaulted."""
    node: Any = cfg
    parts = path.split(".")
    for part in parts[:-1]:
        if part not in node.model_fields_set:
            return False
        node = getattr(node, part)
    return parts[-1] in node.model_fields_set
