"""Image encoders: crops, GroupNorm, spatial softmax, and the DINOv3 + LoRA path on a tiny ViT."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from pydantic import ValidationError
from safetensors.torch import save_file
from tiny_models import TINY_VIT
from torch import nn

from services.policy.model.encoder import (
    EncoderConfig,
    ResNet18Encoder,
    SpatialSoftmax,
    build_encoder,
    crop_images,
)

torch.set_num_threads(1)


def test_centre_crop_is_the_middle_window_and_random_crop_varies():
    x = torch.arange(2 * 3 * 6 * 6, dtype=torch.float32).view(2, 3, 6, 6)
    centre = crop_images(x, (4, 4), random=False)
    assert torch.equal(centre, x[:, :, 1:5, 1:5])
    torch.manual_seed(0)
    windows = {tuple(crop_images(x, (4, 4), random=True)[0, 0, 0, :1].tolist()) for _ in range(20)}
    assert len(windows) > 1  # the top-left pixel moves with the random window
    img = torch.randn(8, 3, 10, 12)
    out = crop_images(img, (7, 9), random=True)
    # every random crop is a true sub-window of its own image
    for i in range(8):
        found = any(torch.equal(out[i], img[i, :, t : t + 7, left : left + 9]) for t in range(4) for left in range(4))
        assert found
    with pytest.raises(ValueError, match="larger"):
        crop_images(img, (11, 11), random=False)


def test_crop_ratio_gives_diffusion_policy_crop():
    assert EncoderConfig().crop_for((84, 84)) == (76, 76)
    assert EncoderConfig(crop=(60, 70)).crop_for((84, 84)) == (60, 70)
    assert EncoderConfig(kind="dinov3", vit_config=TINY_VIT).crop_for((84, 84)) == (72, 72)  # whole 8-px patches


def test_spatial_softmax_finds_a_peaked_keypoint():
    ss = SpatialSoftmax(1, 1)
    with torch.no_grad():
        ss.keypoints.weight.fill_(1.0)
        ss.keypoints.bias.zero_()
    fmap = torch.zeros(1, 1, 5, 5)
    fmap[0, 0, 4, 0] = 100.0  # bottom-left: x = -1, y = +1
    assert torch.allclose(ss(fmap), torch.tensor([[-1.0, 1.0]]), atol=1e-4)


def test_resnet_uses_groupnorm_and_eval_is_deterministic():
    torch.manual_seed(0)
    cfg = EncoderConfig(width=8, stage_strides=(1, 2, 1, 1), num_keypoints=4, feature_dim=12)
    enc = build_encoder(cfg, (32, 32))
    assert isinstance(enc, ResNet18Encoder)
    assert not any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in enc.modules())
    assert sum(isinstance(m, nn.GroupNorm) for m in enc.modules()) >= 17  # stem + 8 blocks x 2
    img = torch.rand(3, 3, 32, 32) * 2 - 1
    enc.eval()
    out = enc(img)
    assert out.shape == (3, 12)
    assert torch.equal(out, enc(img))
    enc.train()
    assert not torch.allclose(enc(img), enc(img))  # random crops differ between calls


def test_groupnorm_groups_divide_any_width():
    """(diffusion_policy's channels // 16 groups: a width it does not divide, 50, failed in GroupNorm)"""
    norms = lambda enc: [m for m in enc.modules() if isinstance(m, nn.GroupNorm)]  # noqa: E731
    stock = build_encoder(EncoderConfig(width=64, num_keypoints=4, feature_dim=8), (32, 32))
    assert {(m.num_channels, m.num_groups) for m in norms(stock)} == {(64, 4), (128, 8), (256, 16), (512, 32)}
    odd = build_encoder(EncoderConfig(width=50, stage_strides=(1, 2, 1, 1), num_keypoints=4, feature_dim=8), (32, 32))
    assert {(m.num_channels, m.num_groups) for m in norms(odd)} == {(50, 2), (100, 5), (200, 10), (400, 25)}
    assert odd.eval()(torch.rand(2, 3, 32, 32) * 2 - 1).shape == (2, 8)


def test_feature_relu_is_robomimics_activation_after_the_projection_and_on_for_the_paper_presets():
    from services.policy.model.presets import preset

    torch.manual_seed(0)
    cfg = EncoderConfig(width=8, stage_strides=(1, 2, 1, 1), num_keypoints=4, feature_dim=32)
    plain = build_encoder(cfg, (32, 32)).eval()
    relu = build_encoder(cfg.model_copy(update={"feature_relu": True}), (32, 32)).eval()
    relu.load_state_dict(plain.state_dict())  # the same weights: the flag adds no parameters
    img = torch.rand(4, 3, 32, 32) * 2 - 1
    raw = plain(img)
    assert (raw < 0).any()  # without it about half the features are negative
    assert torch.equal(relu(img), torch.relu(raw))
    assert preset("paper")["model"]["encoder"]["feature_relu"] is True
    assert preset("paper-small")["model"]["encoder"]["feature_relu"] is True
    assert "feature_relu" not in preset("tiny")["model"]["encoder"]  # tiny keeps what its results were measured with


def _tiny_vit_file(tmp_path: Path) -> tuple[Path, dict[str, torch.Tensor]]:
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(1)
    vit = DINOv3ViTModel(DINOv3ViTConfig(**TINY_VIT))
    state = {k: v.contiguous() for k, v in vit.state_dict().items()}
    path = tmp_path / "vit.safetensors"
    save_file(state, str(path))
    return path, state


def test_dinov3_loads_local_weights_and_trains_only_lora(tmp_path):
    path, state = _tiny_vit_file(tmp_path)
    cfg = EncoderConfig(
        kind="dinov3", vit_config=TINY_VIT, vit_weights=str(path), lora_rank=4, lora_alpha=8, feature_dim=16
    )
    enc = build_encoder(cfg, (36, 36))
    own = enc.vit.state_dict()
    # pretrained weights under LoRA's wrapped names, untouched
    assert torch.equal(
        own["model.layer.1.attention.v_proj.base_layer.weight"], state["model.layer.1.attention.v_proj.weight"]
    )
    assert torch.equal(own["embeddings.cls_token"], state["embeddings.cls_token"])
    trainable = {n for n, p in enc.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n or n.startswith("proj.") for n in trainable)
    assert any("q_proj.lora_A" in n for n in trainable)
    enc.eval()
    out = enc(torch.rand(2, 3, 36, 36) * 2 - 1)
    assert out.shape == (2, 16)
    out.sum().backward()
    assert enc.vit.model.layer[0].attention.q_proj.lora_B.default.weight.grad is not None


@pytest.mark.parametrize(
    ("change", "says"),
    [  # transformers took both: the typo as an attribute nobody reads, the heads as a view error at the first pass
        ({"hiden_size": 64}, "vit_config: 'hiden_size' is not a DINOv3ViTConfig field (its fields include hidden_size"),
        ({"num_attention_heads": 5}, "vit_config: hidden_size 32 must be a positive multiple of num_attention_heads 5"),
    ],
)
def test_a_vit_config_transformers_would_misread_is_refused_naming_the_field(change, says):
    with pytest.raises(ValidationError, match=re.escape(says)):
        EncoderConfig(kind="dinov3", vit_config={**TINY_VIT, **change})
    assert EncoderConfig(kind="resnet18", vit_config={**TINY_VIT, **change}).kind == "resnet18"  # unused there


def test_a_vit_config_field_left_out_is_checked_at_transformers_default():
    """(hidden_size left out is DINOv3ViTConfig's 384 in the model, which 256 heads do not divide)"""
    vit = {k: v for k, v in TINY_VIT.items() if k != "hidden_size"}
    with pytest.raises(
        ValidationError, match=re.escape("hidden_size 384 must be a positive multiple of num_attention_heads 256")
    ):
        EncoderConfig(kind="dinov3", vit_config={**vit, "num_attention_heads": 256})
    assert (
        EncoderConfig(kind="dinov3", vit_config={**vit, "num_attention_heads": 6}).vit_config["num_attention_heads"]
        == 6
    )


def test_dinov3_with_weights_of_another_shape_is_a_clear_error(tmp_path):
    path, _ = _tiny_vit_file(tmp_path)
    other = {**TINY_VIT, "hidden_size": 64, "intermediate_size": 128}
    cfg = EncoderConfig(kind="dinov3", vit_config=other, vit_weights=str(path))
    with pytest.raises(ValueError, match="shape mismatch"):
        build_encoder(cfg, (32, 32))
    with pytest.raises(FileNotFoundError, match="local safetensors"):
        build_encoder(
            EncoderConfig(kind="dinov3", vit_config=TINY_VIT, vit_weights=str(tmp_path / "nope.safetensors")), (32, 32)
        )
