"""Episode MCAPs (written by the recorder's writer) -> dataset build -> loaded training batches."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from dataset_fixtures import trajectory, write_episode
from scipy.spatial.transform import Rotation

from services.cli import main as viewscale
from services.core.action_spaces import from_space
from services.core.geometry import rot6d_to_matrix
from services.core.rig import load_rig
from services.dataset.build import BuildParams, build_dataset, split_episodes
from services.dataset.episodes import CameraCalib, EpisodeError
from services.dataset.store import DatasetError, DatasetStore
from services.trainer.data import load_dataset

VIEWS = ("F", "FL", "FR")
N = 40


@pytest.fixture(scope="module")
def raw_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("raw")
    for i in range(3):
        write_episode(d, f"ep{i:03d}", N, seed=i)
    return d


@pytest.fixture(scope="module")
def camera_ds(raw_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "camera"
    build_dataset(raw_dir, out, BuildParams(views=VIEWS, space="camera", image_size=(64, 48)))
    return out


def item_ticks(ds, i):
    """(demo, obs ticks, action ticks) of item i, read from the stored tick arrays."""
    j, cur, s, e = ds.index[i]
    tick = np.load(ds.demos[j].path("tick"))
    obs_rows = np.clip(np.arange(cur - ds.To + 1, cur + 1), s, e - 1)
    act_rows = np.clip(np.arange(cur - ds.To + 1, cur - ds.To + 1 + ds.Tp), s, e - 1)
    return ds.demos[j], tick[obs_rows], tick[act_rows]


def test_build_gives_one_pseudo_demo_per_view_and_batches_of_the_contract_shapes(camera_ds):
    store = DatasetStore(camera_ds)
    s = store.summary
    assert s["episodes"] == 3 and s["views"] == list(VIEWS) and s["pseudo_demos"] == 9
    assert s["ticks"] == 3 * N and s["rows"] == 9 * N
    per_demo = N - 16 + 8 + 2 - 1  # diffusion_policy sample count for one unbroken run
    assert s["samples"] == 9 * per_demo
    ds = load_dataset(camera_ds, split="all")
    assert len(ds) == 9 * per_demo
    loader = torch.utils.data.DataLoader(ds, batch_size=8, shuffle=True, num_workers=2)
    batch = next(iter(loader))
    assert batch["obs"].shape == (8, 2, 3, 48, 64) and batch["obs"].dtype == torch.float32
    assert batch["state"].shape == (8, 2, 10)
    assert batch["action"].shape == (8, 16, 7)
    assert batch["view"].shape == (8,)
    assert batch["obs"].min() >= -1 and batch["obs"].max() <= 1 and batch["obs"].max() > 0.9
    # The normaliser is fitted on the training episodes: there, no component exceeds 1.
    train = load_dataset(camera_ds, split="train")
    batch = torch.utils.data.default_collate([train[i] for i in range(len(train))])
    assert batch["action"].abs().max() <= 1 + 1e-6
    assert batch["state"].abs().max() <= 1 + 1e-6


def test_samples_hold_the_recorded_actions_in_each_cameras_frame(camera_ds):
    """Unnormalise, undo the camera transform with the calibration in meta.json, and compare with
    the base-frame actions the episode was generated from, tick by tick."""
    ds = load_dataset(camera_ds, split="all")
    rig = load_rig("five15")
    acts = {f"ep{i:03d}": trajectory(N, i)[0] for i in range(3)}
    for i in np.random.default_rng(0).choice(len(ds), 40, replace=False):
        item = ds[int(i)]
        demo, _, a_ticks = item_ticks(ds, i)
        cam = ds.camera(demo.view)
        np.testing.assert_allclose(cam["R_ext"], rig.cameras[demo.view].R_ext, atol=1e-6)
        a = ds.normalizer.unnormalize_action(item["action"].numpy().astype(np.float64))
        base = from_space(a, "camera", R_ext=np.asarray(cam["R_ext"]))
        np.testing.assert_allclose(base, acts[demo.episode_id][a_ticks], atol=2e-6)
        assert item["view"] == ds.views.index(demo.view)


def test_camera_space_state_is_the_eef_pose_in_that_camera(camera_ds):
    ds = load_dataset(camera_ds, split="all")
    rig = load_rig("five15")
    for i in (0, len(ds) // 2, len(ds) - 1):
        demo, o_ticks, _ = item_ticks(ds, i)
        _, pos, R, grip = trajectory(N, int(demo.episode_id[2:]))
        cam = rig.cameras[demo.view]
        s = ds.normalizer.unnormalize_state(ds[i]["state"].numpy().astype(np.float64))
        np.testing.assert_allclose(s[:, 0:3], cam.to_camera(pos[o_ticks]), atol=1e-5)
        np.testing.assert_allclose(rot6d_to_matrix(s[:, 3:9]), cam.R_ext @ R[o_ticks], atol=1e-5)
        np.testing.assert_allclose(s[:, 9], grip[o_ticks], atol=1e-6)


def test_cached_frames_are_the_ticks_frames_and_meta_K_projects_into_them(camera_ds):
    """Each recorded frame shows a dot at the EEF; in the cache it must sit where meta.json's K
    (rescaled to the cached size) and R_ext project the EEF of the same tick."""
    ds = load_dataset(camera_ds, split="all")
    for i in range(0, len(ds), 23):
        demo, o_ticks, _ = item_ticks(ds, i)
        _, pos, _, _ = trajectory(N, int(demo.episode_id[2:]))
        cam = ds.camera(demo.view)
        K, R_ext, c = np.asarray(cam["K"]), np.asarray(cam["R_ext"]), np.asarray(cam["position"])
        for k, tick in enumerate(o_ticks):
            img = (ds[i]["obs"][k].numpy().transpose(1, 2, 0) + 1) * 127.5
            bright = np.argwhere(img.min(axis=2) > 200)
            assert len(bright), "the EEF dot is in every frame"
            v, u = bright.mean(axis=0)
            p = K @ (R_ext @ (pos[tick] - c))
            assert abs(u - p[0] / p[2]) < 1.0 and abs(v - p[1] / p[2]) < 1.0


def test_normalizer_is_shared_isotropic_and_bounded(camera_ds):
    ds = load_dataset(camera_ds, split="train")
    n = json.loads((camera_ds / "normalizer.json").read_text())
    assert set(n) >= {"action", "state", "image"}
    # Over every training pseudo-demo of every view no normalised component exceeds 1, and the bound is met.
    a = np.concatenate([np.load(d.path("action")) for d in ds.demos])
    a_n = ds.normalizer.normalize_action(a)
    assert np.abs(a_n).max() <= 1 + 1e-6
    assert np.linalg.norm(a_n[:, 0:3], axis=1).max() == pytest.approx(1.0, abs=1e-5)
    assert np.linalg.norm(a_n[:, 3:6], axis=1).max() == pytest.approx(1.0, abs=1e-5)


def test_meta_and_manifest_describe_the_build(camera_ds, raw_dir):
    meta = json.loads((camera_ds / "meta.json").read_text())
    assert meta["action_space"] == "camera" and meta["state_frame"] == "camera"
    assert (meta["To"], meta["Tp"], meta["views"]) == (2, 16, list(VIEWS))
    assert meta["image_size"] == {"width": 64, "height": 48}
    rig = load_rig("five15")
    for v in VIEWS:
        K = np.asarray(meta["cameras"][v]["K"])
        np.testing.assert_allclose(K, rig.cameras[v].K(64, 48), atol=1e-6)  # same size: K unchanged
        np.testing.assert_allclose(meta["cameras"][v]["position"], rig.cameras[v].position, atol=1e-6)
        calib = CameraCalib.from_json(v, meta["cameras"][v])  # rebuilds the camera at inference
        np.testing.assert_allclose(calib.camera.R_ext, rig.cameras[v].R_ext, atol=1e-9)
        np.testing.assert_allclose(calib.K_at(32, 24), rig.cameras[v].K(32, 24), atol=1e-9)
    manifest = json.loads((camera_ds / "manifest.json").read_text())
    assert manifest["complete"]
    for src in manifest["sources"]:
        assert src["sha256"] == hashlib.sha256(Path(src["path"]).read_bytes()).hexdigest()
    sheet = cv2.imread(str(camera_ds / "contact_sheet.png"))
    # three views tall, three episodes x (first, middle, last) wide, frames doubled or more
    assert sheet.shape[0] > 3 * 2 * 48 and sheet.shape[1] == 9 * 64 * 4


def test_resized_cache_keeps_K_consistent(raw_dir, tmp_path):
    out = tmp_path / "ds"
    build_dataset(raw_dir, out, BuildParams(views=("FR",), space="base", image_size=(32, 24)), contact_episodes=1)
    ds = load_dataset(out, split="all")
    K = np.asarray(ds.camera("FR")["K"])
    np.testing.assert_allclose(K, load_rig("five15").cameras["FR"].K(32, 24), atol=1e-6)
    assert ds[0]["obs"].shape == (2, 3, 24, 32)


def test_eef_space_uses_the_rotation_of_the_actions_own_tick(raw_dir, tmp_path):
    out = tmp_path / "eef"
    build_dataset(raw_dir, out, BuildParams(views=("F",), space="eef", image_size=(32, 24)), contact_episodes=0)
    ds = load_dataset(out, split="all")
    assert ds.meta["state_frame"] == "base"
    for i in (0, 7, len(ds) - 1):
        demo, _, a_ticks = item_ticks(ds, i)
        _, pos, R, _ = trajectory(N, int(demo.episode_id[2:]))
        a = ds.normalizer.unnormalize_action(ds[i]["action"].numpy().astype(np.float64))
        for k, t in enumerate(a_ticks):
            if t + 1 < N:
                # the step from tick t to t+1, seen from the EEF at tick t
                np.testing.assert_allclose(a[k, 0:3], R[t].T @ (pos[t + 1] - pos[t]), atol=1e-6)
                np.testing.assert_allclose(Rotation.from_rotvec(a[k, 3:6]).as_matrix(), R[t].T @ R[t + 1], atol=1e-5)


def test_held_out_views_are_simply_not_included(raw_dir, tmp_path):
    out = tmp_path / "two"
    r = build_dataset(
        raw_dir, out, BuildParams(views=("FU", "F"), space="camera", image_size=(32, 24)), contact_episodes=0
    )
    assert r.summary["pseudo_demos"] == 6 and r.summary["views"] == ["FU", "F"]
    ds = load_dataset(out, split="all")
    assert {d.view for d in ds.demos} == {"FU", "F"}
    assert set(ds.meta["cameras"]) == {"FU", "F"}
    only_f = load_dataset(out, split="all", views=["F"])
    assert {d.view for d in only_f.demos} == {"F"} and all(only_f[i]["view"] == 1 for i in range(3))
    with pytest.raises(DatasetError, match="FL"):
        load_dataset(out, views=["FL"])


def test_drops_are_counted_and_chunks_never_cross_them(tmp_path):
    raw = tmp_path / "raw"
    write_episode(
        raw,
        "gappy",
        N,
        cameras=["F", "FL"],
        drop_frames={"F": [10]},
        missing_actions=[25],
        frame_delay_ns={"FL": {30: 40_000_000}},
        corrupt_frames={"FL": [5]},
        stale_actions=[3],
    )
    r = build_dataset(raw, tmp_path / "ds", BuildParams(views=("F", "FL"), image_size=(32, 24)), contact_episodes=0)
    d = r.summary["drops"]
    assert d["no_action"] == 1 and d["stale_action"] == 1
    assert d["views"]["F"] == {"missing_frame": 0, "stale_frame": 1, "bad_frame": 0}  # tick 10 found only frame 9
    assert d["views"]["FL"] == {"missing_frame": 0, "stale_frame": 1, "bad_frame": 1}
    assert r.summary["rows_per_view"] == {"F": N - 2, "FL": N - 3}
    ds = load_dataset(tmp_path / "ds", split="all")
    for i in range(len(ds)):
        _, o_ticks, a_ticks = item_ticks(ds, i)
        # consecutive ticks inside a chunk, apart from edge repeats
        steps = np.diff(np.r_[o_ticks, a_ticks])
        assert set(np.unique(np.diff(a_ticks))) <= {0, 1}, steps
        for t in a_ticks:
            assert t != 25
    fl = [d for d in ds.demos if d.view == "FL"][0]
    assert list(np.load(fl.path("ends"))) == [5, 24, 28, N - 3]  # runs 0-4, 6-24, 26-29, 31-39


def test_rebuild_is_skipped_when_nothing_changed_and_incremental_otherwise(tmp_path):
    raw = tmp_path / "raw"
    for i in range(2):
        write_episode(raw, f"ep{i}", 24, cameras=["F"], seed=i)
    out = tmp_path / "ds"
    params = BuildParams(views=("F",), image_size=(32, 24))
    first = build_dataset(raw, out, params, contact_episodes=0)
    assert (first.built, first.reused, first.up_to_date) == (2, 0, False)
    stamp = (out / "episodes" / "ep0" / "F.frames.npy").stat().st_mtime_ns
    said: list[str] = []
    again = build_dataset(raw, out, params, contact_episodes=0, progress=said.append)
    assert again.up_to_date and again.built == 0
    assert not any("hashing" in m for m in said)  # unchanged size and mtime: the recorded hash stands
    write_episode(raw, "ep2", 24, cameras=["F"], seed=2)
    third = build_dataset(raw, out, params, contact_episodes=0)
    assert (third.built, third.reused) == (1, 2) and third.summary["episodes"] == 3
    assert (out / "episodes" / "ep0" / "F.frames.npy").stat().st_mtime_ns == stamp
    (raw / "ep1.mcap").unlink()
    write_episode(raw, "ep1", 30, cameras=["F"], seed=5)  # same name, new content
    fourth = build_dataset(raw, out, params, contact_episodes=0)
    assert (fourth.built, fourth.reused) == (1, 2) and fourth.summary["ticks"] == 24 + 30 + 24
    (raw / "ep2.mcap").unlink()
    fifth = build_dataset(raw, out, params, contact_episodes=0)
    assert fifth.summary["episodes"] == 2 and not (out / "episodes" / "ep2").exists()
    changed = build_dataset(raw, out, BuildParams(views=("F",), space="base", image_size=(32, 24)), contact_episodes=0)
    assert changed.built == 2  # another action space reshapes every episode's arrays


def test_a_failed_build_leaves_no_dataset_that_looks_complete(tmp_path):
    raw = tmp_path / "raw"
    write_episode(raw, "ep0", 24, cameras=["F"])
    out = tmp_path / "ds"
    build_dataset(raw, out, BuildParams(views=("F",), image_size=(32, 24)), contact_episodes=0)
    assert len(load_dataset(out, split="all")) > 0
    bad = write_episode(raw, "ep1", 24, cameras=["F"])
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2] + b"\x00" * 64 + data[len(data) // 2 + 64 :])  # damage a chunk
    write_episode(raw, "ep2", 24, cameras=["F"], seed=2)
    with pytest.raises(EpisodeError, match="ep1.mcap"):  # raised in a worker thread, reported here
        build_dataset(raw, out, BuildParams(views=("F",), image_size=(32, 24)), contact_episodes=0, jobs=2)
    with pytest.raises(DatasetError, match="not a complete dataset"):
        load_dataset(out)
    assert not list((out / "episodes").glob(".tmp-*"))
    # --skip-bad builds from what is readable and says what it skipped
    r = build_dataset(raw, out, BuildParams(views=("F",), image_size=(32, 24)), skip_bad=True, contact_episodes=0)
    assert r.summary["episodes"] == 2 and "ep1.mcap" in r.summary["skipped_episodes"][0]["error"]
    assert len(load_dataset(out, split="all")) > 0


def test_bad_input_gets_a_clear_error_naming_the_file_or_view(tmp_path):
    raw = tmp_path / "raw"
    write_episode(raw, "nocal", 24, cameras=["F", "FL"], no_calibration=["FL"])
    out = tmp_path / "ds"
    with pytest.raises(EpisodeError, match=r"nocal\.mcap.*'FL'.*calibration"):
        build_dataset(raw, out, BuildParams(views=("F", "FL"), space="camera", image_size=(32, 24)))
    # base space does not need the calibration
    r = build_dataset(raw, out, BuildParams(views=("F", "FL"), space="base", image_size=(32, 24)))
    assert r.summary["pseudo_demos"] == 2
    with pytest.raises(EpisodeError, match=r"nocal\.mcap.*'FX'.*F, FL"):
        build_dataset(raw, tmp_path / "x", BuildParams(views=("FX",), image_size=(32, 24)))
    with pytest.raises(DatasetError, match="empty view selection"):
        BuildParams(views=())
    with pytest.raises(DatasetError, match="max_frame_age_ms must be positive, got -5"):
        BuildParams(views=("F",), max_frame_age_ms=-5)  # (it was taken, and dropped every frame as stale)
    with pytest.raises(DatasetError, match="does not exist"):
        build_dataset(tmp_path / "nowhere", out, BuildParams(views=("F",)))
    with pytest.raises(DatasetError, match="no episode files"):
        (tmp_path / "empty").mkdir()
        build_dataset(tmp_path / "empty", out, BuildParams(views=("F",)))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap at all")
    with pytest.raises(EpisodeError, match="junk.mcap"):
        build_dataset([tmp_path / "junk.mcap"], tmp_path / "y", BuildParams(views=("F",)))
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "nothing")
    write_episode(tmp_path / "sized", "sized", 24, cameras=["F"], calib_size=(128, 96))
    with pytest.raises(EpisodeError, match=r"sized\.mcap.*'F'.*64x48.*128x96"):
        build_dataset(tmp_path / "sized", tmp_path / "z", BuildParams(views=("F",), image_size=(32, 24)))


def test_the_normaliser_never_sees_the_held_out_episodes(tmp_path):
    ids = ["e0", "e1", "e2", "big"]
    seed = next(s for s in range(100) if split_episodes(ids, 0.25, s)[1] == ["big"])
    for i, name in enumerate(ids):
        write_episode(tmp_path / "raw", name, 30, cameras=["F"], seed=i, scale=3.0 if name == "big" else 1.0)
    out = tmp_path / "ds"
    build_dataset(tmp_path / "raw", out, BuildParams(views=("F",), val_fraction=0.25, split_seed=seed))
    store = DatasetStore(out)
    assert store.split("val") == ["big"] and sorted(store.split("train")) == ["e0", "e1", "e2"]
    norms = {d.episode_id: np.linalg.norm(d.load("action")[:, 0:3], axis=1).max() for d in store.demos}
    assert store.normalizer.pos_scale == pytest.approx(max(norms[i] for i in ("e0", "e1", "e2")), rel=1e-6)
    assert norms["big"] > 2 * store.normalizer.pos_scale  # fitted on all of them it would be this one's
    assert store.summary["split"] == {"train": 3, "val": 1, "val_episodes": ["big"]}


def test_split_is_by_episode_deterministic_and_disjoint(camera_ds):
    train = load_dataset(camera_ds, split="train")
    val = load_dataset(camera_ds, split="val")
    assert set(train.episode_ids) | set(val.episode_ids) == {"ep000", "ep001", "ep002"}
    assert not set(train.episode_ids) & set(val.episode_ids) and len(val.episode_ids) == 1
    assert load_dataset(camera_ds, split="val").episode_ids == val.episode_ids
    split = json.loads((camera_ds / "meta.json").read_text())["split"]  # recorded with the dataset
    assert (split["train"], split["val"]) == (train.episode_ids, val.episode_ids)
    assert {d.episode_id for d in val.demos} == set(val.episode_ids)
    ids = [f"e{i}" for i in range(50)]
    tr, va = split_episodes(ids, 0.2, seed=1)
    assert len(va) == 10 and split_episodes(list(reversed(ids)), 0.2, seed=1)[1] == sorted(va, key=ids.index)[::-1]


def test_cli_build_and_info(raw_dir, tmp_path, capsys):
    out = tmp_path / "cli"
    rc = viewscale(
        [
            "dataset",
            "build",
            "--raw",
            str(raw_dir),
            "--views",
            "F,FR",
            "--space",
            "camera",
            "--out",
            str(out),
            "--image-size",
            "32x24",
            "--contact-episodes",
            "1",
            "--jobs",
            "2",
        ]
    )
    cap = capsys.readouterr()
    assert rc == 0
    assert "[3/3] ep002.mcap" in cap.err  # per-episode progress
    assert "pseudo-demos" in cap.out and (out / "contact_sheet.png").is_file()
    assert viewscale(["dataset", "info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "episodes      3" in info and "F, FR" in info and "pos_scale" in info
    assert viewscale(["dataset", "info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] > 0
    for argv, needle in (
        (["--views", "F,NOPE"], "'NOPE'"),
        (["--views", ","], "empty view selection"),
        (["--views", "F", "--contact-episodes", "-1"], "--contact-episodes must be 0 or more, got -1"),
    ):
        rc = viewscale(
            ["dataset", "build", "--raw", str(raw_dir), "--out", str(tmp_path / "bad"), "--jobs", "1", *argv]
        )
        err = capsys.readouterr().err
        last = err.strip().splitlines()[-1]
        assert rc == 2 and needle in last and last.startswith("error:") and "Traceback" not in err
    assert not (tmp_path / "bad").exists()  # the failed builds took back the --out they made
    (tmp_path / "bad").mkdir()
    assert viewscale(["dataset", "info", str(tmp_path / "bad")]) == 2
    assert "not a complete dataset" in capsys.readouterr().err
    # another command's folder is said as what it is (it was "not a complete dataset: no manifest.json")
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    for path, says in [
        (raw_dir, f"{raw_dir} is a folder of recorded episodes, not a dataset: build one from them with "),
        (tmp_path / "run", f"{tmp_path / 'run'} is a training run, not a dataset"),
    ]:
        assert viewscale(["dataset", "info", str(path)]) == 2
        assert capsys.readouterr().err.strip().startswith(f"error: {says}")
        assert viewscale(["train", "--data", str(path), "--out", str(tmp_path / "new-run")]) == 2
        assert capsys.readouterr().err.strip().startswith(f"error: {says}")


@pytest.mark.parametrize(
    "space,state_frame", [("camera", "auto"), ("base", "auto"), ("eef", "auto"), ("camera", "base"), ("eef", "camera")]
)
def test_contact_sheet_action_path_retraces_the_state_path(raw_dir, tmp_path, space, state_frame):
    """The generated episodes move exactly by their actions, so the path the contact sheet draws from
    a pseudo-demo's actions (in their own frame) must land on the EEF states it draws in white."""
    from services.dataset.contact_sheet import trajectories

    out = tmp_path / "ds"
    build_dataset(
        raw_dir,
        out,
        BuildParams(views=("FL",), space=space, state_frame=state_frame, image_size=(32, 24)),
        contact_episodes=1,
    )
    ds = DatasetStore(out)
    d = ds.demos[0]
    pos_cam, path = trajectories(
        d.load("state"), d.load("action"), d.load("ends"), space, ds.meta["state_frame"], d.calib
    )
    np.testing.assert_allclose(pos_cam, load_rig("five15").cameras["FL"].to_camera(trajectory(N, 0)[1]), atol=1e-5)
    np.testing.assert_allclose(path, pos_cam, atol=1e-4)


def test_an_episode_from_another_camera_placement_keeps_its_own_calibration(tmp_path):
    raw = tmp_path / "raw"
    moved = tmp_path / "moved.yaml"
    moved.write_text("name: moved\ndistance: 1.2\ncameras:\n  F: {yaw_deg: 5}\n")
    write_episode(raw, "a", 24, cameras=["F"])
    write_episode(raw, "b", 24, cameras=["F"], rig=str(moved))
    out = tmp_path / "ds"
    r = build_dataset(raw, out, BuildParams(views=("F",), image_size=(32, 24)), contact_episodes=0)
    store = DatasetStore(out)
    assert store.meta["calibration_varies"] == {"F": True}
    by_ep = {d.episode_id: d for d in store.demos}
    np.testing.assert_allclose(by_ep["a"].calib["position"], load_rig("five15").cameras["F"].position, atol=1e-9)
    np.testing.assert_allclose(by_ep["b"].calib["position"], load_rig(str(moved)).cameras["F"].position, atol=1e-9)
    # each pseudo-demo's actions went through its own camera's R_ext
    for ep_id, rig in (("a", load_rig("five15")), ("b", load_rig(str(moved)))):
        d = by_ep[ep_id]
        base = from_space(np.load(d.path("action")).astype(np.float64), "camera", R_ext=rig.cameras["F"].R_ext)
        np.testing.assert_allclose(base, trajectory(24, 0)[0], atol=2e-6)
    assert r.summary["episodes"] == 2


def test_episodes_with_wrong_values_are_one_clear_error_or_skipped_with_their_reason(tmp_path, capsys):
    raw = tmp_path / "raw"
    write_episode(raw, "good", 30, cameras=["F"])
    write_episode(raw, "nan-pose", 30, cameras=["F"], state_fields={7: {"eef_pos": [0.4, float("nan"), 0.2]}})
    write_episode(raw, "zero-quat", 30, cameras=["F"], state_fields={3: {"eef_quat_wxyz": [0.0, 0.0, 0.0, 0.0]}})
    args = [
        "dataset",
        "build",
        "--raw",
        str(raw),
        "--views",
        "F",
        "--out",
        str(tmp_path / "ds"),
        "--image-size",
        "32x24",
    ]
    assert viewscale(args) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        "error: nan-pose.mcap: robot state of tick 7: non-finite: eef_pos = [0.4, nan, 0.2]; "
        "--skip-bad builds the other episodes and lists this one"  # (before: no word of how to go on)
    )
    assert viewscale([*args, "--skip-bad"]) == 0
    out = capsys.readouterr()
    assert "nan-pose.mcap: SKIPPED: nan-pose.mcap: robot state of tick 7: non-finite" in out.err
    assert "zero-quat.mcap: SKIPPED: zero-quat.mcap: robot state of tick 3: not a unit quaternion" in out.err
    assert DatasetStore(tmp_path / "ds").episode_ids == ["good"]


def test_an_unwritable_out_is_one_error_line(raw_dir, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    rc = viewscale(["dataset", "build", "--raw", str(raw_dir), "--views", "F", "--out", str(blocker / "ds")])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip() == f"error: --out {blocker / 'ds'}: not a directory ({blocker} is a file)"


def test_a_build_that_cannot_fit_on_the_disk_is_one_line_before_anything_is_decoded_or_removed(
    raw_dir, tmp_path, capsys
):
    """Frames are stored raw, once per view: at 100000x100000 the three episodes need petabytes.
    Before, the build decoded until an array could not be made or the disk was full."""
    out = tmp_path / "ds"
    build = ["dataset", "build", "--raw", str(raw_dir), "--views", "F,FL,FR", "--out", str(out)]
    assert viewscale([*build, "--image-size", "32x24"]) == 0
    capsys.readouterr()
    manifest = (out / "manifest.json").read_bytes()
    rc = viewscale([*build, "--image-size", "100000"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith("error: the 3 episodes to build need about "), err
    assert f"GiB in {out} ({3 * N} ticks, 3 views of 100000x100000 frames stored raw), and " in err, err
    assert "free some space, write the dataset on another disk (--out)" in err, err
    # the dataset built before is untouched: still complete, still loadable
    assert (out / "manifest.json").read_bytes() == manifest and not list((out / "episodes").glob(".tmp-*"))
    assert len(DatasetStore(out).episode_ids) == 3


def test_a_wrong_raw_or_a_file_for_a_dataset_is_one_line_and_leaves_nothing(tmp_path, capsys):
    """A --raw with no episodes used to leave an empty --out folder behind (made before --raw was
    looked at); `dataset info` on a file said it did not exist."""
    (tmp_path / "empty").mkdir()
    for raw, says in [(tmp_path / "nowhere", "does not exist"), (tmp_path / "empty", "no episode files")]:
        rc = viewscale(["dataset", "build", "--raw", str(raw), "--views", "F", "--out", str(tmp_path / "ds")])
        err = capsys.readouterr().err
        assert rc == 2 and says in err and err.count("\n") == 1, err
        assert not (tmp_path / "ds").exists()
    note = tmp_path / "note.txt"
    note.write_text("keep me\n")
    assert viewscale(["dataset", "info", str(note)]) == 2
    assert capsys.readouterr().err.strip() == f"error: dataset {note} is a file, not a folder"


def test_unfinished_episodes_are_named_with_the_command_that_rescues_them(raw_dir, tmp_path, capsys):
    """An episode a killed recorder left as .mcap.part was not built, without a word."""
    raw = tmp_path / "raw"
    shutil.copytree(raw_dir, raw)
    (raw / "day2").mkdir()
    (raw / "day2" / "ep009.mcap.part").write_bytes((raw / "ep000.mcap").read_bytes()[:5000])
    (raw / "ep000.mcap.part").write_bytes(b"")  # recovered already (ep000.mcap is beside it): not named
    said: list[str] = []
    build_dataset(raw, tmp_path / "ds", BuildParams(views=("F",), image_size=(32, 24)), progress=said.append)
    [warning] = [m for m in said if m.startswith("warning:")]
    assert warning == (
        "warning: 1 episode not finished, being recorded or left by a recorder that stopped (ep009.mcap.part): "
        f"not built; `python -m services.recorder.recover {raw / 'day2'}` rescues what they hold"
    )
    (tmp_path / "only").mkdir()
    (tmp_path / "only" / "ep1.mcap.part").write_bytes(b"")
    rc = viewscale(["dataset", "build", "--raw", str(tmp_path / "only"), "--views", "F", "--out", str(tmp_path / "d2")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert f"error: no episode files (*.mcap) under {tmp_path / 'only'}; 1 episode not finished" in err


def test_an_image_size_above_the_recorded_frames_is_warned_about(raw_dir, tmp_path):
    """(built without a word before: 2000x2000 from 84x84 frames took 1.1 GB for 97 frames)"""
    said: list[str] = []
    build_dataset(raw_dir, tmp_path / "big", BuildParams(views=("F",), image_size=(128, 96)), progress=said.append)
    [warning] = [m for m in said if m.startswith("warning:")]
    assert "image size 128x96 is larger than the recorded frames (F 64x48)" in warning
    said.clear()
    build_dataset(raw_dir, tmp_path / "small", BuildParams(views=("F",), image_size=(32, 24)), progress=said.append)
    assert not [m for m in said if m.startswith("warning:")]


def test_a_horizon_longer_than_every_episode_is_named_at_build_and_at_training(raw_dir, tmp_path):
    """(a build gave "samples 0" without a word, and training then said only "the training set is empty")"""
    from services.trainer.config import train_config_from_dict
    from services.trainer.train import TrainingError, load_train_data

    said: list[str] = []
    out = tmp_path / "long"
    build_dataset(raw_dir, out, BuildParams(views=("F",), image_size=(32, 24), Tp=N + 40), progress=said.append)
    [warning] = [m for m in said if m.startswith("warning:")]
    need = N + 40 - 8 - 2 + 2  # Tp - Ta - To + 2
    assert (
        f"no samples: no chunk fits: with To=2, Tp={N + 40}, Ta=8 a chunk needs a segment of at least {need}" in warning
    )
    assert DatasetStore(out).summary["samples"] == 0
    cfg = {"data": str(out), "out": str(tmp_path / "run"), "preset": "tiny", "progress": False}
    with pytest.raises(TrainingError, match=rf"no training samples: no chunk fits: .*Tp={N + 40}.*set a shorter"):
        load_train_data(train_config_from_dict(cfg))
    # the windows are cut when loading: a shorter horizon for the model finds samples in the same dataset
    assert len(load_train_data(train_config_from_dict({**cfg, "model": {"pred_horizon": 16}})).train) > 0


def test_a_failed_build_leaves_no_output_folder(tmp_path, capsys):
    """(it left --out behind with an empty episodes/ folder in it)"""
    write_episode(tmp_path / "raw", "ep", 24, cameras=["F"])
    out = tmp_path / "new" / "ds"
    rc = viewscale(["dataset", "build", "--raw", str(tmp_path / "raw"), "--out", str(out), "--views", "FX"])
    assert rc == 2 and "'FX'" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    # an --out that was there stays, with what the user had in it
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep\n")
    rc = viewscale(
        ["dataset", "build", "--raw", str(tmp_path / "raw"), "--out", str(tmp_path / "mine"), "--views", "FX"]
    )
    assert rc == 2 and (tmp_path / "mine" / "notes.txt").read_text() == "keep\n"


def test_a_second_build_into_a_folder_being_built_is_refused(tmp_path, capsys):
    """(two builds into one --out, from two terminals, wrote over each other's files)"""
    from services.core.runtime import LOCK_FILE, exclusive

    write_episode(tmp_path / "raw", "ep", 24, cameras=["F"])
    out = tmp_path / "ds"
    out.mkdir()
    with exclusive(out, "dataset build"):  # as the first build holds it
        rc = viewscale(["dataset", "build", "--raw", str(tmp_path / "raw"), "--out", str(out), "--views", "F"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.startswith(f"error: {out} is in use by another dataset build (pid "), err
        assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]  # nothing written
    rc = viewscale(["dataset", "build", "--raw", str(tmp_path / "raw"), "--out", str(out), "--views", "F"])
    assert rc == 0 and not (out / LOCK_FILE).exists() and (out / "manifest.json").is_file()


def test_failed_episodes_and_policy_rollouts_are_left_out_unless_asked_for(tmp_path, capsys):
    """(a demonstration stopped as a failure, and a policy's rollouts in a folder under --raw --
    failed or successful -- were built and trained on as demonstrations, without a word)"""
    raw = tmp_path / "raw"
    write_episode(raw, "good-0", 24, cameras=["F"], seed=0, command_sources=["spacemouse"])
    write_episode(raw, "good-1", 24, cameras=["F"], seed=1)  # (recorded before command_sources)
    write_episode(raw, "stopped-failed", 24, cameras=["F"], seed=2, success=False, command_sources=["spacemouse"])
    rollouts = raw / "eval" / "rollouts"
    write_episode(rollouts, "rollout-ok", 24, cameras=["F"], seed=3, command_sources=["policy"])
    write_episode(rollouts, "rollout-failed", 24, cameras=["F"], seed=4, success=False, command_sources=["policy"])
    # started and stopped with no arm on the bus (before: the whole build failed, 'no frames of camera F')
    write_episode(raw, "no-arm", 0, cameras=["F"], seed=5)
    out = tmp_path / "ds"

    def build(*extra: str) -> tuple[int, str, str]:
        rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F", *extra])
        got = capsys.readouterr()
        return rc, got.out, got.err

    def built() -> list[str]:
        return sorted(e["id"] for e in DatasetStore(out).meta["episodes"])

    rc, text, err = build()
    assert rc == 0, err
    failed = "2 episodes not marked successful (rollout-failed, stopped-failed): --include-failed builds them"
    rollout = "2 episodes driven by a policy (rollout-failed, rollout-ok): --include-rollouts builds them"
    empty = "1 episodes with no robot state recorded (no-arm): nothing to learn from (no robot service or sim ran?)"
    assert f"left out {failed}" in err and f"left out {rollout}" in err and f"left out {empty}" in err
    assert f"  left out      {failed}" in text and f"  left out      {rollout}" in text
    assert built() == ["good-0", "good-1"]
    assert {x["episode"]: x["reason"] for x in DatasetStore(out).summary["left_out_episodes"]} == {
        "stopped-failed": "not marked successful",
        "rollout-ok": "driven by a policy",
        "rollout-failed": "not marked successful, driven by a policy",
        "no-arm": "with no robot state recorded",
    }
    rc, text, err = build()  # nothing changed: up to date, and still says what it leaves out
    assert rc == 0 and "up to date" in text and "rollout-ok" in text
    rc, text, err = build("--include-failed")
    assert rc == 0 and built() == ["good-0", "good-1", "stopped-failed"], err
    rc, text, err = build("--include-rollouts")
    assert rc == 0 and built() == ["good-0", "good-1", "rollout-ok"], err
    rc, text, err = build("--include-failed", "--include-rollouts")
    assert (
        rc == 0
        and [x.split("left out")[1].strip() for x in (text + err).splitlines() if "left out" in x] == [empty] * 2
    )
    assert built() == ["good-0", "good-1", "rollout-failed", "rollout-ok", "stopped-failed"]
    assert DatasetStore(out).summary["successful_episodes"] == 3
    from services.dataset.build import POLICY_SOURCE
    from services.teleop.config import PolicyTeleopConfig

    assert PolicyTeleopConfig.model_fields["type"].default == POLICY_SOURCE  # what a rollout's commands say
    # nothing to learn from at all: one line, and no dataset
    rc = viewscale(["dataset", "build", "--raw", str(rollouts), "--out", str(tmp_path / "none"), "--views", "F"])
    err = capsys.readouterr().err
    assert rc == 2 and "error: none of the 2 episodes is a demonstration to learn from" in err, err
    assert not (tmp_path / "none").exists()


def test_episodes_of_other_control_rates_are_refused_and_other_tasks_warned_about(tmp_path, capsys):
    """(10 Hz and 20 Hz episodes were built into one dataset whose control_hz was then None, and the
    server took 20 Hz; episodes of two tasks, without a word)"""
    raw = tmp_path / "raw"
    for i in range(4):
        write_episode(raw, f"ep-20hz-{i}", 24, cameras=["F"], seed=i)
    write_episode(raw, "ep-10hz", 24, cameras=["F"], seed=9, control_hz=10.0)
    out = tmp_path / "ds"
    rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F"])
    err = capsys.readouterr().err
    assert rc == 2 and "error: episodes recorded at different control rates (10 Hz: ep-10hz; 20 Hz: " in err, err
    assert "ep-20hz-0, ep-20hz-1, ep-20hz-2 and 1 more)" in err and "build each rate's episodes on their own" in err
    assert not out.exists()
    (raw / "ep-10hz.mcap").unlink()
    write_episode(raw, "can-0", 24, cameras=["F"], seed=10, task="can")
    rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F"])
    err = capsys.readouterr().err
    assert rc == 0 and "warning: episodes of 2 tasks (can 1, lift 4): a policy trained on them is not told" in err
    assert DatasetStore(out).meta["tasks"] == ["can", "lift"]


def test_the_same_rollout_ids_in_two_evaluations_are_no_clash_when_left_out(tmp_path, capsys):
    """(`--raw data/demo` stopped at "two episodes named lift-five15-eval-s100000": the two
    evaluations' rollouts share their fixed seeds' ids, and they are not built anyway)"""
    raw = tmp_path / "demo"
    write_episode(raw / "raw", "demo-0", 24, cameras=["F"], seed=0)
    for ev in ("eval-F", "eval-composed"):
        write_episode(raw / ev / "rollouts", "rollout-s100000", 24, cameras=["F"], seed=5, command_sources=["policy"])
    out = tmp_path / "ds"
    rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F"])
    assert rc == 0, capsys.readouterr().err
    assert [e["id"] for e in DatasetStore(out).meta["episodes"]] == ["demo-0"]
    # built, the two would be one episode folder: refused as before
    rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F", "--include-rollouts"])
    assert rc == 2 and "error: two episodes named rollout-s100000: " in capsys.readouterr().err


def test_a_recording_and_its_re_renderings_are_held_out_together(tmp_path, capsys):
    """(a demonstration could be held out while its re-rendering through another rig -- the same
    trajectory -- was trained on: validation on training data)"""
    raw = tmp_path / "raw"
    ids = [f"ep{i}" for i in range(6)]
    for i, ep in enumerate(ids):
        src = write_episode(raw, ep, 24, cameras=["F"], seed=i)
        write_episode(raw / "three30", f"{ep}-three30", 24, cameras=["F"], seed=i, rerendered_from=str(src))
    for split_seed in range(4):
        out = tmp_path / f"ds{split_seed}"
        args = ["--val-fraction", "0.34", "--split-seed", str(split_seed)]
        rc = viewscale(["dataset", "build", "--raw", str(raw), "--out", str(out), "--views", "F", *args])
        assert rc == 0, capsys.readouterr().err
        split = DatasetStore(out).meta["split"]
        val = sorted(split["val"])
        assert len(val) == 4 and {v.removesuffix("-three30") for v in val} == {v for v in val if "-" not in v}, val
        assert not set(val) & set(split["train"])
    # without re-renderings, the split is the one it always was
    assert split_episodes(ids, 0.34, 1) == split_episodes(ids, 0.34, 1, groups={})
    groups = {f"{ep}-three30": ep for ep in ids}
    tr, va = split_episodes([*ids, *groups], 0.34, 1, groups)
    assert {groups.get(v, v) for v in va} == set(split_episodes(ids, 0.34, 1)[1])
    # re-renderings built alone (as the experiments' stages do) split as they always did
    assert split_episodes(list(groups), 0.34, 1, groups) == split_episodes(list(groups), 0.34, 1)


def test_a_build_stopped_by_sigterm_says_so_and_the_same_command_finishes_it(raw_dir, tmp_path):
    """SIGTERM (a scheduler's stop, `kill`) as Ctrl-C: one line, exit 130, and the same command
    builds the rest (before: the process died with no word, exit 143)."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "services.cli", "dataset", "build", "--raw", str(raw_dir), "--views", "F,FL,FR"]
    cmd += ["--out", str(out), "--image-size", "640x480"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if line.startswith("hashing "):  # the build has begun: its first episode comes next
            break
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err, err[-2000:]
    said = f"interrupted (SIGTERM): the episodes built so far are kept in {out}; run the same command to build the rest"
    assert said in err
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr[-2000:]
    assert DatasetStore(out).summary["pseudo_demos"] == 9


def test_an_episode_reached_twice_through_the_raw_paths_is_built_once(raw_dir, tmp_path, capsys):
    """A folder and a file in it, or a folder and a folder inside it: each file once (before:
    `error: two episodes named ep000: .../ep000.mcap and .../ep000.mcap`, the same file)."""
    first = sorted(raw_dir.glob("*.mcap"))[0]
    out = tmp_path / "ds"
    args = ["dataset", "build", "--raw", str(raw_dir), str(first), str(raw_dir) + "/", "--views", "F"]
    assert viewscale([*args, "--out", str(out), "--image-size", "32x24"]) == 0, capsys.readouterr().err
    assert DatasetStore(out).summary["episodes"] == 3


def test_the_seeds_a_collection_continues_after_are_its_own_tasks_collected_ones(tmp_path):
    """`viewscale collect` into a folder continues after its seeds: those of its task, recorded by a
    collection, not an evaluation's rollouts (seeds from 100000 on) nor re-renderings."""
    from services.session.collect import first_seed, recorded_seeds

    write_episode(tmp_path, "lift-a", 5, seed=3)
    write_episode(tmp_path, "lift-eval", 5, seed=100004)
    write_episode(tmp_path, "lift-a-three30", 5, seed=7, rerendered_from=str(tmp_path / "elsewhere.mcap"))
    write_episode(tmp_path, "can-a", 5, seed=9, task="can")
    assert recorded_seeds(tmp_path, "lift") == [3] and recorded_seeds(tmp_path, "can") == [9]
    said: list[str] = []
    assert first_seed(tmp_path, "lift", None, progress=said.append) == 4
    assert said == [f"{tmp_path} holds 1 lift episodes (seeds 3..3): continuing from seed 4"]
    assert first_seed(tmp_path, "square", None, progress=said.append) == 0 and len(said) == 1
