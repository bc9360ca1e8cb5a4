"""A sim episode recorded through the real services -> dataset build -> a loaded training batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.cli import main as viewscale
from services.core import topics
from services.core.action_spaces import from_space, to_space
from services.recorder.reader import read_episode
from services.trainer.data import load_dataset

VIEWS = ["F", "FL", "FR", "FU", "FD"]


@pytest.mark.slow
def test_recorded_sim_episode_to_training_batch(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "ds"
    assert (
        viewscale(
            [
                "collect",
                "--task",
                "lift",
                "--episodes",
                "1",
                "--rig",
                "five15",
                "--out",
                str(raw),
                "--size",
                "64",
                "--fast",
            ]
        )
        == 0
    )
    assert (
        viewscale(
            [
                "dataset",
                "build",
                "--raw",
                str(raw),
                "--views",
                ",".join(VIEWS),
                "--space",
                "camera",
                "--out",
                str(out),
                "--image-size",
                "64",
                "--contact-episodes",
                "1",
            ]
        )
        == 0
    )
    capsys.readouterr()

    ds = load_dataset(out, split="all")
    B = 4
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=B, shuffle=True, num_workers=2)))
    assert batch["obs"].shape == (B, 2, 3, 64, 64)
    assert batch["state"].shape == (B, 2, 10)
    assert batch["action"].shape == (B, 16, 7)
    assert batch["obs"].min() >= -1 and batch["obs"].max() <= 1
    assert batch["action"].abs().max() <= 1 + 1e-6

    # Every pseudo-demo's actions, returned to the base frame with its own calibration, are the
    # applied actions of the recording, tick for tick; and two views differ by their relative rotation.
    (mcap,) = sorted(raw.glob("*.mcap"))
    ep = read_episode(mcap, topics=[topics.APPLIED_ACTION.mcap_topic])
    applied = {
        r.msg.tick: [*r.msg.action.dp, *r.msg.action.drot, r.msg.action.gripper]
        for r in ep.messages(topics.APPLIED_ACTION.mcap_topic)
    }
    per_view = {}
    for d in ds.demos:
        tick = np.load(d.path("tick"))
        a = np.load(d.path("action")).astype(np.float64)
        R_ext = np.asarray(ds.camera(d.view)["R_ext"])
        np.testing.assert_allclose(
            from_space(a, "camera", R_ext=R_ext), np.array([applied[t] for t in tick]), atol=1e-6
        )
        per_view[d.view] = (tick, a, R_ext)
    tF, aF, RF = per_view["F"]
    tL, aL, RL = per_view["FL"]
    common = np.intersect1d(tF, tL)
    aF, aL = aF[np.isin(tF, common)], aL[np.isin(tL, common)]
    np.testing.assert_allclose(aL, to_space(aF, "camera", R_ext=RL @ RF.T), atol=1e-6)

    # The EEF projects inside every cached frame of every view (calibration and frames agree).
    for d in ds.demos:
        cam = ds.camera(d.view)
        K = np.asarray(cam["K"])
        p = np.load(d.path("state"))[:, 0:3] @ K.T  # camera-frame EEF positions
        uv = p[:, :2] / p[:, 2:3]
        assert (p[:, 2] > 0).all() and (uv >= 0).all() and (uv <= 63).all()
    assert (out / "contact_sheet.png").is_file()
