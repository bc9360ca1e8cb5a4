"""Small real episode MCAPs in the recorder's layout, written with the recorder's own writer.

A kinematic EEF follows its applied actions exactly (p' = p + dp, R' = Rot(drot) R), and each
camera of the rig renders a white dot at the EEF's projection, so frames and actions agree the
way a sim recording does. Options inject the faults the dataset build must catch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from services.core import topics
from services.core.rig import load_rig
from services.core.tensors import compressed_image
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefAction
from services.pb.episode_pb2 import EpisodeMeta
from services.pb.sensors_pb2 import RobotState
from services.recorder.writer import EPISODE_CHANNEL, EPISODE_RECORD, EpisodeWriter, meta_to_record

T0 = 1_700_000_000_000_000_000


def trajectory(n: int, seed: int = 0, hold: tuple[int, ...] = (), scale: float = 1.0):
    """Base-frame actions (n, 7) and the states they produce: pos (n, 3), R (n, 3, 3), gripper (n,).

    Ticks in ``hold`` are stale: the robot held still with the gripper where it was; ``scale``
    multiplies every motion.
    """
    if n == 0:  # (an episode that recorded no tick)
        return np.zeros((0, 7)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    dp = np.c_[0.006 * np.cos(t / 6 + seed), 0.006 * np.sin(t / 5 + seed), -0.002 * np.cos(t / 9)]
    dr = np.c_[0.02 * np.sin(t / 4), 0.03 * np.cos(t / 7), 0.05 * np.sin(t / 5 + seed)] + rng.normal(0, 0.002, (n, 3))
    dp, dr = scale * dp, scale * dr
    g = (t > n // 2).astype(float)
    for k in hold:
        dp[k], dr[k], g[k] = 0.0, 0.0, g[k - 1] if k > 0 else 0.0
    act = np.c_[dp, dr, g]
    pos = np.zeros((n, 3))
    R = np.zeros((n, 3, 3))
    pos[0] = [0.44 + 0.02 * seed, 0.0, 0.15]  # near the rigs' centre: the EEF stays inside every view
    R[0] = Rotation.from_euler("xyz", [np.pi, 0.1 * seed, 0.0]).as_matrix()
    for k in range(n - 1):
        pos[k + 1] = pos[k] + dp[k]
        R[k + 1] = Rotation.from_rotvec(dr[k]).as_matrix() @ R[k]
    grip = np.r_[0.0, g[:-1]]
    return act, pos, R, grip


def render(cam, p: np.ndarray, width: int, height: int, tick: int) -> np.ndarray:
    img = np.zeros((height, width, 3), np.uint8)
    img[:, :, 2] = np.linspace(40, 90, width, dtype=np.uint8)[None, :]  # something for JPEG to chew on
    img[:, :, 1] = (tick * 3) % 60
    u, v = cam.project(p, width, height)[0]
    ui, vi = int(round(u)), int(round(v))
    y, x = np.ogrid[:height, :width]
    img[(x - ui) ** 2 + (y - vi) ** 2 <= 4] = 255
    return img


def write_episode(
    out_dir: Path,
    episode_id: str,
    n: int = 40,
    *,
    rig: str = "five15",
    cameras: list[str] | None = None,
    width: int = 64,
    height: int = 48,
    control_hz: float = 20.0,
    seed: int = 0,
    drop_frames: dict[str, list[int]] | None = None,
    frame_delay_ns: dict[str, dict[int, int]] | None = None,
    corrupt_frames: dict[str, list[int]] | None = None,
    missing_actions: list[int] = (),
    stale_actions: list[int] = (),
    no_calibration: list[str] = (),
    success: bool = True,
    calib_size: tuple[int, int] | None = None,
    scale: float = 1.0,
    state_fields: dict[int, dict] | None = None,
    command_sources: list[str] = (),
    task: str = "lift",
    rerendered_from: str = "",
) -> Path:
    """Write ``<out_dir>/<episode_id>.mcap``; returns its path."""
    rg = load_rig(rig)
    cams = cameras or rg.names
    period = int(1e9 / control_hz)
    act, pos, R, grip = trajectory(n, seed, tuple(stale_actions), scale)
    drop_frames = drop_frames or {}
    frame_delay_ns = frame_delay_ns or {}
    corrupt_frames = corrupt_frames or {}
    out_dir.mkdir(parents=True, exist_ok=True)
    w = EpisodeWriter(out_dir / f"{episode_id}.mcap")
    frames: dict[str, int] = {c: 0 for c in cams}
    for k in range(n):
        stamp = T0 + k * period
        if k % 20 == 0:
            for c in cams:
                if c in no_calibration:
                    continue
                cam = rg.cameras[c]
                cw, ch = calib_size or (width, height)
                w.write_message(
                    topics.camera_calibration(c).mcap_topic, cam.calibration_msg(cw, ch, stamp), stamp, stamp
                )
                w.write_message(topics.camera_pose(c).mcap_topic, cam.pose_msg(stamp), stamp, stamp)
        for c in cams:
            if k in drop_frames.get(c, []):
                continue
            f_stamp = stamp - frame_delay_ns.get(c, {}).get(k, 0)
            msg = compressed_image(render(rg.cameras[c], pos[k], width, height, k), f_stamp, c)
            if k in corrupt_frames.get(c, []):
                msg.data = b"\xff\xd8" + b"\x00" * 50
            w.write_message(topics.camera_image(c).mcap_topic, msg, stamp + 2_000_000, f_stamp)
            frames[c] += 1
        q = Rotation.from_matrix(R[k]).as_quat()
        state = RobotState(
            header=Header(stamp_ns=stamp, seq=k, frame_id="world"),
            tick=k,
            eef_pos=pos[k].tolist(),
            eef_quat_wxyz=[q[3], q[0], q[1], q[2]],
            joint_pos=[0.0] * 7,
            joint_vel=[0.0] * 7,
            gripper=float(grip[k]),
            episode_id=episode_id,
        )
        for name, value in (state_fields or {}).get(k, {}).items():  # a fault written into tick k
            del getattr(state, name)[:]
            getattr(state, name).extend(value)
        w.write_message(topics.ROBOT_STATE.mcap_topic, state, stamp + 1_000_000, stamp)
        if k not in missing_actions:
            stale = k in stale_actions
            a = EefAction(dp=act[k, 0:3].tolist(), drot=act[k, 3:6].tolist(), gripper=float(act[k, 6]))
            applied = AppliedAction(header=Header(stamp_ns=stamp + period // 2, seq=k), tick=k, action=a, stale=stale)
            w.write_message(topics.APPLIED_ACTION.mcap_topic, applied, stamp + period // 2, stamp + period // 2)
    meta = EpisodeMeta(
        episode_id=episode_id,
        task=task,
        seed=seed,
        rig=rig,
        success=success,
        command_sources=command_sources,
        rerendered_from=rerendered_from,
        control_hz=control_hz,
        achieved_hz=control_hz,
        ticks=n,
        frames=frames,
        start_ns=T0,
        end_ns=T0 + n * period,
    )
    w.write_message(EPISODE_CHANNEL, meta, T0 + n * period, T0 + n * period)
    w.add_metadata(EPISODE_RECORD, meta_to_record(meta))
    return w.close()
