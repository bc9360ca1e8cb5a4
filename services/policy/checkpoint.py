"""Checkpoints: safetensors plus JSON, never a pickle.

A run directory holds ``checkpoints/step_NNNNNNN/`` folders and a ``latest`` file naming the
newest complete one (written last, atomically, so a crash mid-save leaves the previous one
current). Each folder has:

- ``model.safetensors``: the weights to serve (the EMA weights when EMA is on);
- ``policy.json``: everything needed to use them: the model config, the normaliser (as
  ``Normalizer.to_dict`` writes it), the action space, the training views with their rig
  calibration (K, R_ext, position), and where the data came from;
- ``train_state.safetensors`` + ``train_state.json``: what resuming needs besides that: the raw
  (non-averaged) weights, AdamW's moments, the RNG states, and the step.

``load_policy`` reads only the first two; nothing is unpickled anywhere.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.core.runtime import OutputError, exclusive

if TYPE_CHECKING:  # torch, safetensors and the model are imported where they are used: reading a
    import torch  # checkpoint's JSON (`viewscale eval`, the session, the CLI) must not load torch

    from services.policy.model.policy import DiffusionPolicy, ModelConfig

FORMAT = "viewscale-policy"
VERSION = 1
MODEL_FILE = "model.safetensors"
POLICY_FILE = "policy.json"
STATE_FILE = "train_state.safetensors"
STATE_JSON = "train_state.json"
LATEST = "latest"

log = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A checkpoint is missing, incomplete or does not fit the requested model."""


@dataclass
class LoadedPolicy:
    policy: DiffusionPolicy  # in eval mode, on the requested device
    info: dict[str, Any]  # policy.json: model, normalizer, action_space, views, calibration, ...
    path: Path

    @property
    def normalizer(self):
        from services.core.normalizer import Normalizer

        return Normalizer.from_dict(self.info["normalizer"])

    @property
    def action_space(self) -> str:
        return self.info["action_space"]


def _contiguous(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().contiguous().cpu() for k, v in state.items()}


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def checkpoint_dir(run_dir: str | Path, step: int) -> Path:
    return Path(run_dir) / "checkpoints" / f"step_{step:07d}"


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run (None if it has none)."""
    marker = Path(run_dir) / "checkpoints" / LATEST
    if not marker.is_file():
        return None
    path = marker.parent / marker.read_text().strip()
    if not (path / MODEL_FILE).is_file() or not (path / POLICY_FILE).is_file():
        raise CheckpointError(f"{marker} names {path.name}, which is incomplete")
    return path


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint folder, or a run directory (its latest checkpoint), or a run's ``checkpoints``
    folder (the same). Anything else is a CheckpointError saying what the path is instead."""
    path = Path(path)
    if (path / MODEL_FILE).is_file():
        return path
    if (path / LATEST).is_file() and path.name == "checkpoints":  # runs/x/checkpoints: the run's latest
        path = path.parent
    latest = latest_checkpoint(path)
    if latest is not None:
        return latest
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist")
    if not path.is_dir():
        raise CheckpointError(f"{path} is a file: give a checkpoint folder or a run directory")
    if (path / POLICY_FILE).is_file():
        raise CheckpointError(f"{path} is an incomplete checkpoint: it has no {MODEL_FILE}")
    from services.dataset.store import MANIFEST, META  # (only here: a path that is no checkpoint)

    if (path / MANIFEST).is_file() and (path / META).is_file():
        raise CheckpointError(
            f"{path} is a dataset, not a checkpoint: train a policy on it (viewscale train --data {path})"
        )
    if (path / "checkpoints").is_dir() or (path / "config.json").is_file():
        raise CheckpointError(
            f"run directory {path} has no complete checkpoint yet "
            "(a run saves one every checkpoint_every steps and at its end)"
        )
    raise CheckpointError(f"{path} is neither a checkpoint folder nor a run directory with checkpoints")


def optimizer_to_tensors(optim: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    """AdamW state as flat tensors (``optim.<param index>.<name>``) plus JSON-able param groups."""
    import torch

    sd = optim.state_dict()
    tensors = {}
    for idx, state in sd["state"].items():
        for name, value in state.items():
            t = value if torch.is_tensor(value) else torch.tensor(value)
            tensors[f"optim.{idx}.{name}"] = t
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in sd["param_groups"]]
    return tensors, groups


def optimizer_from_tensors(
    optim: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], groups: list[dict[str, Any]]
) -> None:
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        if not key.startswith("optim."):
            continue
        _, idx, name = key.split(".", 2)
        state.setdefault(int(idx), {})[name] = value
    groups = [{k: (tuple(v) if k == "betas" else v) for k, v in g.items()} for g in groups]
    optim.load_state_dict({"state": state, "param_groups": groups})


def _mode_by_umask(path: Path) -> None:
    """safetensors creates its files 0600 whatever the umask; give them the mode any file of the
    user gets (0644 under umask 022), or a server or worker running as another user (a container's)
    cannot read the weights next to a readable policy.json."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(path, 0o666 & ~mask)


def save_checkpoint(
    run_dir: str | Path,
    step: int,
    serve_state: dict[str, torch.Tensor],
    info: dict[str, Any],
    train_tensors: dict[str, torch.Tensor],
    train_json: dict[str, Any],
    keep: int = 2,
) -> Path:
    """Write one checkpoint folder, then point ``latest`` at it, then drop the oldest beyond ``keep``
    and the ``.partial`` folders of saves that were cut short (a run stopped at once mid-save)."""
    from safetensors import SafetensorError
    from safetensors.torch import save_file

    path = checkpoint_dir(run_dir, step)
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        save_file(_contiguous(serve_state), str(tmp / MODEL_FILE), metadata={"format": FORMAT})
        _write_json(tmp / POLICY_FILE, {"format": FORMAT, "version": VERSION, "step": step, **info})
        save_file(_contiguous(train_tensors), str(tmp / STATE_FILE))
        for name in (MODEL_FILE, STATE_FILE):
            _mode_by_umask(tmp / name)
        _write_json(tmp / STATE_JSON, {"step": step, **train_json})
        shutil.rmtree(path, ignore_errors=True)
        os.replace(tmp, path)
        marker = path.parent / LATEST
        marker_tmp = marker.with_name(LATEST + ".tmp")
        marker_tmp.write_text(path.name + "\n")
        os.replace(marker_tmp, marker)
    except (OSError, SafetensorError) as exc:  # a full disk, a folder gone or read-only (before: a traceback)
        shutil.rmtree(tmp, ignore_errors=True)  # (what it wrote of this one: room again)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        kept = latest_checkpoint(run_dir)
        raise CheckpointError(
            f"cannot save checkpoint {path.name} in {run_dir}: {reason}; "
            + (f"the newest saved is {kept}: the same command resumes from it" if kept else "none is saved yet")
        ) from exc
    done = sorted(p for p in path.parent.glob("step_*") if p.is_dir() and not p.name.endswith(".partial"))
    for old in done[:-keep]:
        if old != path:
            _remove_unless_served(old)
    for cut in path.parent.glob("step_*.partial"):
        shutil.rmtree(cut, ignore_errors=True)
    return path


def _remove_unless_served(old: Path) -> None:
    """Remove an old checkpoint folder, unless a policy server or worker serves it (they hold it
    for reading: a worker restarted later loads it again). A later save removes it once none does."""
    try:
        with exclusive(old, "checkpoint removal"):
            shutil.rmtree(old, ignore_errors=True)
    except OutputError as exc:
        log.info("checkpoint %s kept: %s", old, exc)


def checkpoint_sha256(path: str | Path) -> str:
    """sha256 over what serving loads (the weights, then policy.json): equal on server and workers."""
    path = resolve_checkpoint(path)
    h = hashlib.sha256()
    for name in (MODEL_FILE, POLICY_FILE):
        with open(path / name, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def model_id(path: str | Path) -> str:
    """``<run directory>@<checkpoint>``, e.g. ``lift-five15-camera@step_0002000``."""
    path = resolve_checkpoint(path)
    return f"{path.parent.parent.name}@{path.name}"


def read_info(path: str | Path) -> dict[str, Any]:
    """The checkpoint's ``policy.json``; a CheckpointError naming the file when it cannot be read.
    (No torch here: the evaluation process reads it too.)"""
    path = resolve_checkpoint(path)
    file = path / POLICY_FILE
    try:
        info = json.loads(file.read_text())
    except (OSError, ValueError) as exc:
        raise _unreadable(file, exc) from None
    if not isinstance(info, dict) or info.get("format") != FORMAT or info.get("version") != VERSION:
        raise CheckpointError(f"{path} is not a {FORMAT} v{VERSION} checkpoint")
    return info


def model_config(info: dict[str, Any], path: str | Path) -> ModelConfig:
    """The model config of the ``info`` read from checkpoint or run ``path`` (``read_info``); a
    CheckpointError naming its policy.json when this version cannot build it (before: pydantic's
    traceback)."""
    from pydantic import ValidationError

    from services.core.config import describe_errors
    from services.policy.model.policy import ModelConfig

    try:
        return ModelConfig.model_validate(info.get("model"))
    except ValidationError as exc:
        raise CheckpointError(
            f"{resolve_checkpoint(path) / POLICY_FILE} holds a model config this version cannot build "
            f"({describe_errors(exc, ModelConfig)}): was it edited, or written by another version?"
        ) from None


def read_weights(file: str | Path) -> dict[str, torch.Tensor]:
    """The tensors of a checkpoint's safetensors file; CheckpointError naming it when it cannot be
    read (truncated by a copy, overwritten, missing)."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        return load_file(str(file))
    except (SafetensorError, OSError) as exc:
        raise _unreadable(file, exc) from None


def check_weights(path: str | Path) -> None:
    """That a checkpoint's weights file is whole: its header reads and the file holds every tensor
    the header lists (safetensors checks both on open), without reading a tensor. CheckpointError
    as ``read_weights``' otherwise. A server whose workers compute checks it before they start."""
    from safetensors import SafetensorError, safe_open

    file = resolve_checkpoint(path) / MODEL_FILE
    try:
        with safe_open(str(file), framework="pt"):
            pass
    except (SafetensorError, OSError) as exc:
        raise _unreadable(file, exc) from None


def _unreadable(file: str | Path, exc: Exception) -> CheckpointError:
    return CheckpointError(f"{file} cannot be read ({exc}): copy the checkpoint again or use another")


def read_train_state(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    path = Path(path)
    if not (path / STATE_FILE).is_file():
        raise CheckpointError(f"{path} has no training state (was it exported for serving only?)")
    return read_weights(path / STATE_FILE), json.loads((path / STATE_JSON).read_text())


def flat_fields(d: Any, prefix: str = "") -> dict[str, Any]:
    """A dumped config as ``{dotted.field: value}``; ``prefix`` names ``d`` itself (a section)."""
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat_fields(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: d}


def config_diff(a: ModelConfig, b: ModelConfig) -> list[str]:
    """Dotted field names whose values differ between two model configs."""
    fa, fb = flat_fields(a.model_dump(mode="json")), flat_fields(b.model_dump(mode="json"))
    ignore = {"encoder.vit_weights"}  # where pretrained weights came from does not change the model
    return sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k) and k not in ignore)


def load_state_checked(module: torch.nn.Module, state: dict[str, torch.Tensor], what: str) -> None:
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    extra = sorted(set(state) - set(own))
    shapes = sorted(k for k in set(own) & set(state) if own[k].shape != state[k].shape)
    if missing or extra or shapes:
        raise CheckpointError(
            f"{what} does not fit this model: {len(missing)} missing, {len(extra)} unexpected, "
            f"{len(shapes)} of another shape (e.g. {(missing or extra or shapes)[:3]}); "
            "was it trained with a different model config?"
        )
    module.load_state_dict(state, strict=True)


def inference_device(spec: str | torch.device, precision: str = "fp32") -> torch.device:
    """The device ``spec`` names (cpu, cuda, cuda:N, mps), checked to exist on this machine and, for
    ``precision`` bf16 on CUDA, to compute in bfloat16. ValueError naming what is wrong otherwise:
    a server or worker says so in one line before it listens, not in a traceback while loading."""
    import torch

    try:
        device = torch.device(spec)
    except (RuntimeError, TypeError):
        raise ValueError(f"device {str(spec)!r}: not a device name (cpu, cuda or cuda:N)") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {spec}: no CUDA device is visible on this machine (use device cpu)")
        n = torch.cuda.device_count()
        if device.index is not None and device.index >= n:
            have = f"{n} CUDA device{'s' * (n != 1)} (cuda:0 to cuda:{n - 1})"
            raise ValueError(f"device {spec}: this machine has {have}")
        if precision == "bf16":  # (asking creates a CUDA context on that device: only when it matters)
            with torch.cuda.device(device):
                if not torch.cuda.is_bf16_supported():
                    name = torch.cuda.get_device_name(device)
                    raise ValueError(f"precision bf16: {spec} ({name}) does not support bfloat16; use fp32")
    elif device.type == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError(f"device {spec}: MPS is not available on this machine (use device cpu)")
    elif device.type != "cpu":
        raise ValueError(f"device {spec}: a policy runs on cpu, cuda or mps")
    return device


def load_policy(
    path: str | Path, device: str | torch.device = "cpu", expect: ModelConfig | None = None, fast_paths: bool = True
) -> LoadedPolicy:
    """Build the policy from a checkpoint folder (or a run's latest) for inference.

    ``expect``: fail with the differing fields if the checkpoint's model config is not this one.
    ``fast_paths``: compute the U-Net's Conv1d layers as GEMMs where that was measured faster
    (the CPU, for passes of two or more views; one view's pass keeps PyTorch's convolution:
    ``services.policy.model.fastpath``, ``bench/denoise_step.py``); the same maths either way.
    """
    from services.policy.model.fastpath import gemm_conv1d_pays_off, use_gemm_conv1d
    from services.policy.model.policy import DiffusionPolicy

    device = inference_device(device)  # before any weight is read
    path = resolve_checkpoint(path)
    info = read_info(path)
    cfg = model_config(info, path)
    if expect is not None:
        diff = config_diff(expect, cfg)
        if diff:
            raise CheckpointError(f"checkpoint {path} has a different model config: {', '.join(diff)}")
    policy = DiffusionPolicy(cfg, load_pretrained=False)
    load_state_checked(policy, read_weights(path / MODEL_FILE), f"checkpoint {path}")
    policy = policy.to(device).eval()
    if fast_paths and gemm_conv1d_pays_off(device):
        use_gemm_conv1d(policy)
    return LoadedPolicy(policy, info, path)
