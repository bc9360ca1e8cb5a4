"""Trainer parts that need no dataset: config precedence, the step-addressed batch sampler, the
EMA and LR schedules, and the optimiser state's round trip through safetensors + JSON."""

from __future__ import annotations

import math
import re

import pytest
import torch
from safetensors.torch import load_file, save_file

from services.core.config import ConfigError
from services.policy.checkpoint import config_diff, optimizer_from_tensors, optimizer_to_tensors
from services.policy.model.policy import ModelConfig
from services.trainer.config import EmaConfig, explicitly_set, load_train_config, train_config_from_dict
from services.trainer.train import EMA, StepBatchSampler, lr_at, pick_device, resolve_model_config

torch.set_num_threads(1)


def test_preset_yaml_env_cli_precedence(tmp_path):
    yaml = tmp_path / "train.yaml"
    yaml.write_text("preset: paper\nsteps: 100\nbatch_size: 8\noptim: {lr: 0.002}\n")
    cfg = load_train_config(
        yaml,
        ["steps=300", "model.down_dims=[64,128,256]"],
        environ={"VIEWSCALE_BATCH_SIZE": "16", "VIEWSCALE_STEPS": "200"},
    )
    assert cfg.preset == "paper"
    assert cfg.steps == 300  # CLI over env over YAML
    assert cfg.batch_size == 16  # env over YAML over preset (64)
    assert cfg.optim.lr == 0.002  # YAML over preset
    assert cfg.optim.warmup_steps == 500 and cfg.ema.power == 0.75  # from the paper preset
    assert cfg.model.down_dims == (64, 128, 256)
    assert cfg.model.encoder.width == 64  # the preset's nested value survives a sibling override
    tiny = load_train_config(None, [], environ={})
    assert tiny.preset == "tiny" and tiny.model.down_dims == (64, 128)


def test_bad_config_is_a_clear_error():
    with pytest.raises(ConfigError, match="unknown preset"):
        load_train_config(None, ["preset=huge"], environ={})
    with pytest.raises(ConfigError, match="lr"):
        load_train_config(None, ["optim.lr=fast"], environ={})
    with pytest.raises(ConfigError, match="nonsense"):
        load_train_config(None, ["nonsense=1"], environ={})


@pytest.mark.parametrize(
    ("override", "says"),
    [  # each was taken, and failed at the optimiser's construction as a traceback or trained on
        ("optim.lr=-1", "optim.lr: Input should be greater than 0"),
        ("optim.betas=[0.9,1.5]", "optim.betas: each must be in [0, 1)"),
        ("optim.weight_decay=-0.1", "optim.weight_decay: Input should be greater than or equal to 0"),
        ("ema.max_decay=1.5", "ema.max_decay: Input should be less than or equal to 1"),
        ("ema.min_decay=0.99", "ema: min_decay 0.99 is above max_decay 0.5"),
        ("views=[F,F]", "views: names F more than once"),
        ("views=[]", "views: names no view"),
        # the model's and its schedulers' settings: each was an IndexError, a ZeroDivisionError, a
        # torch or diffusers error at the model's first pass, or a policy that acts on nothing
        ("model.down_dims=[]", "model.down_dims: Tuple should have at least 1 item"),
        ("model.down_dims=[-8,16]", "model.down_dims.0: Input should be greater than 0"),
        ("model.n_groups=0", "model.n_groups: Input should be greater than or equal to 1"),
        ("model.kernel_size=4", "model: kernel_size 4 must be odd"),
        ("model.obs_horizon=0", "model.obs_horizon: Input should be greater than or equal to 1"),
        ("model.n_action_steps=0", "model.n_action_steps: Input should be greater than or equal to 1"),
        (
            "model.diffusion_step_embed_dim=2",
            "model.diffusion_step_embed_dim: Input should be greater than or equal to 4",
        ),
        ("model.diffusion_step_embed_dim=7", "model.diffusion_step_embed_dim: Input should be a multiple of 2"),
        ("model.action_dim=0", "model.action_dim: Input should be greater than or equal to 1"),
        ("model.image_size=[0,84]", "model.image_size.0: Input should be greater than 0"),
        (
            "model.noise.num_train_timesteps=0",
            "model.noise.num_train_timesteps: Input should be greater than or equal to 1",
        ),
        (
            "model.noise.num_inference_steps=0",
            "model.noise.num_inference_steps: Input should be greater than or equal to 1",
        ),
        (
            "model.noise.num_inference_steps=200",
            "model.noise: num_inference_steps 200 is more than num_train_timesteps 100",
        ),
        ("model.noise.beta_schedule=cosine", "model.noise.beta_schedule: Input should be 'linear', 'scaled_linear' or"),
        (
            "model.noise.prediction_type=v_prediction",
            "model.noise.prediction_type: Input should be 'epsilon' or 'sample'",
        ),
        ("model.encoder.width=0", "model.encoder.width: Input should be greater than or equal to 1"),
        ("model.encoder.num_keypoints=0", "model.encoder.num_keypoints: Input should be greater than or equal to 1"),
        ("model.encoder.feature_dim=0", "model.encoder.feature_dim: Input should be greater than or equal to 1"),
        ("model.encoder.crop_ratio=0", "model.encoder.crop_ratio: Input should be greater than 0"),
        ("model.encoder.crop=[0,0]", "model.encoder.crop.0: Input should be greater than 0"),
        ("model.encoder.stage_strides=[0,1,1,1]", "model.encoder.stage_strides.0: Input should be greater than 0"),
        ("model.encoder.lora_rank=-1", "model.encoder.lora_rank: Input should be greater than or equal to 0"),
    ],
)
def test_settings_out_of_range_are_refused_naming_the_field(override, says):
    extra = ["ema.max_decay=0.5"] if override.startswith("ema.min_decay") else []  # (the pair disagrees)
    with pytest.raises(ConfigError, match=re.escape(says)):
        load_train_config(None, [override, *extra], environ={})


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("tpu", "'tpu': not a device name"),
        ("cuda:x", "'cuda:x': not a device name"),
        ("meta", "a policy runs on cpu, cuda or mps"),
    ],
)
def test_a_device_torch_cannot_train_on_is_a_config_error(spec, says):
    # before, `viewscale train --device tpu` was torch's RuntimeError traceback
    with pytest.raises(ConfigError, match=re.escape(says)):
        pick_device(spec, local_rank=0)
    assert pick_device("auto", 0).type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device is visible"):
            pick_device("cuda", 0)


def test_dataset_fills_model_shapes_and_conflicts_are_errors():
    meta = {"image_size": {"width": 40, "height": 32}, "state_dim": 10, "To": 2, "Tp": 16, "Ta": 8, "action_dim": 7}
    cfg = train_config_from_dict({"preset": "tiny"})
    model = resolve_model_config(cfg, meta)
    assert model.image_size == (32, 40) and model.state_dim == 10 and model.n_action_steps == 8
    assert not explicitly_set(cfg, "model.image_size") and explicitly_set(cfg, "model.down_dims")
    clash = train_config_from_dict({"preset": "tiny", "model": {"image_size": [64, 64]}})
    with pytest.raises(ConfigError, match="does not match the dataset"):
        resolve_model_config(clash, meta)


def test_sampler_batches_depend_only_on_seed_and_step():
    s = StepBatchSampler(n=10, batch_size=4, seed=3)
    stream = [b for _, b in zip(range(6), iter(s))]
    # resuming at step 4 yields exactly what the uninterrupted sampler yields from step 4 on
    resumed = [b for _, b in zip(range(2), iter(StepBatchSampler(10, 4, 3, start_step=4)))]
    assert resumed == stream[4:6]
    # every epoch is a permutation: the first 10 positions cover each index once
    flat = sum(stream, [])
    assert sorted(flat[:10]) == list(range(10)) and sorted(flat[10:20]) == list(range(10))
    assert StepBatchSampler(10, 4, seed=4).batch_at(0) != stream[0]
    # two ranks split each global batch without overlap
    r0, r1 = StepBatchSampler(10, 2, 3, rank=0, world=2), StepBatchSampler(10, 2, 3, rank=1, world=2)
    assert r0.batch_at(0) + r1.batch_at(0) == flat[:4]
    # a dataset smaller than a batch wraps into the next epoch
    assert len(StepBatchSampler(3, 8, 0).batch_at(0)) == 8


def test_ema_follows_diffusion_policys_schedule():
    model = torch.nn.Linear(2, 1, bias=False)
    with torch.no_grad():
        model.weight.fill_(1.0)
    ema = EMA(model, EmaConfig(power=0.75))
    assert ema.decay(0) == 0.0
    assert ema.decay(1) == pytest.approx(1 - 2**-0.75)
    assert ema.decay(10**9) == 0.9999  # clamped at max_decay
    with torch.no_grad():
        model.weight.fill_(3.0)
    ema.update(model, 1)
    d = 1 - 2**-0.75
    assert torch.allclose(ema.model.weight, torch.full((1, 2), d * 1.0 + (1 - d) * 3.0))
    assert not ema.model.weight.requires_grad


def test_lr_warms_up_then_follows_a_cosine_to_zero():
    cfg = train_config_from_dict({"preset": "tiny", "steps": 110, "optim": {"lr": 1.0, "warmup_steps": 10}})
    assert lr_at(0, cfg) == 0.0
    assert lr_at(5, cfg) == pytest.approx(0.5)
    assert lr_at(10, cfg) == pytest.approx(1.0)
    assert lr_at(60, cfg) == pytest.approx(0.5)
    assert lr_at(110, cfg) == pytest.approx(0.0, abs=1e-12)
    flat = train_config_from_dict(
        {"preset": "tiny", "steps": 110, "optim": {"lr": 1.0, "warmup_steps": 10, "schedule": "constant"}}
    )
    assert lr_at(100, flat) == 1.0
    assert not math.isnan(lr_at(0, train_config_from_dict({"preset": "tiny", "optim": {"warmup_steps": 0}})))


def test_optimizer_state_round_trips_without_pickle(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 1))
    opt = torch.optim.AdamW(net.parameters(), lr=1e-2, betas=(0.95, 0.999), weight_decay=1e-6)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(5, 3)).pow(2).mean().backward()
        opt.step()
    tensors, groups = optimizer_to_tensors(opt)
    save_file(tensors, str(tmp_path / "o.safetensors"))
    net2 = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 1))
    net2.load_state_dict(net.state_dict())
    opt2 = torch.optim.AdamW(net2.parameters(), lr=1.0)
    optimizer_from_tensors(opt2, load_file(str(tmp_path / "o.safetensors")), groups)
    assert opt2.param_groups[0]["betas"] == (0.95, 0.999) and opt2.param_groups[0]["lr"] == 1e-2
    x = torch.randn(5, 3)
    for o, n in ((opt, net), (opt2, net2)):
        o.zero_grad()
        n(x).pow(2).mean().backward()
        o.step()
    assert all(torch.equal(a, b) for a, b in zip(net.parameters(), net2.parameters()))


def test_config_diff_names_the_fields():
    a = ModelConfig(down_dims=(64, 128), n_groups=8)
    b = ModelConfig(down_dims=(64, 256), n_groups=8, encoder={"width": 32})
    assert config_diff(a, b) == ["down_dims", "encoder.width"]
    assert config_diff(a, a) == []
