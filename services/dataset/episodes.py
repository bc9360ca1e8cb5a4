"""Recorded episodes -> samples aligned at control ticks.

A sample is one control tick k: the RobotState of tick k, the AppliedAction of tick k (what
the robot executed between state k and k + 1: the demonstration action) and, per camera, the
newest frame captured at or before the state's capture time, if it is not stale. All times are
capture times from the MCAP (``publish_time``), never indices.

Stale means older than a tolerance: ``max_frame_age_ns`` if given, otherwise per camera the
camera's usual age at a tick (median) plus half its frame interval (median). In sim frames
share the tick's time, so this is half a period and one lost frame makes its tick stale; a real
camera running on its own clock is normally up to one frame interval old at a tick, and only a
lost frame pushes it past the tolerance.

Nothing is filled in: a tick without an applied action is dropped for every view, a tick
whose frame is missing or too old is dropped for that view, and every drop is counted by
reason. Ticks that remain form contiguous segments; chunks never cross a gap.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.core import topics
from services.core.geometry import quat_wxyz_to_matrix
from services.core.rig import Camera, scale_K
from services.core.validation import Invalid, check
from services.recorder.reader import EpisodeReadError, read_episode


class EpisodeError(ValueError):
    """An episode cannot be used; the message names the file and what is wrong."""


@dataclass
class CameraCalib:
    """One camera as recorded in an episode: its pose (R_ext, position) and intrinsics."""

    camera: Camera
    K: np.ndarray  # (3, 3) at the recorded image size
    width: int
    height: int

    @property
    def name(self) -> str:
        return self.camera.name

    def K_at(self, width: int, height: int) -> np.ndarray:
        """K for the image resized to (width, height), in OpenCV's pixel-centre convention."""
        return scale_K(self.K, (self.width, self.height), (width, height))

    def to_json(self, width: int | None = None, height: int | None = None) -> dict[str, Any]:
        w, h = width or self.width, height or self.height
        return {
            "K": self.K_at(w, h).tolist(),
            "width": w,
            "height": h,
            "R_ext": self.camera.R_ext.tolist(),
            "position": self.camera.position.tolist(),
            "source_K": self.K.tolist(),
            "source_width": self.width,
            "source_height": self.height,
        }

    @classmethod
    def from_json(cls, name: str, d: dict[str, Any]) -> CameraCalib:
        K = np.asarray(d["source_K"], dtype=np.float64)
        fovy = float(np.degrees(2.0 * np.arctan((d["source_height"] / 2.0) / K[1, 1])))
        cam = Camera(name, np.asarray(d["position"]), np.asarray(d["R_ext"]).T, fovy)
        return cls(cam, K, int(d["source_width"]), int(d["source_height"]))


@dataclass
class RawEpisode:
    """What a dataset build needs from one recorded episode, in tick and capture-time order."""

    path: Path
    episode_id: str
    meta: dict[str, Any]  # the recorder's EpisodeMeta fields (task, seed, rig, success, flags, ...)
    state_tick: np.ndarray  # (N,) int64
    state_ns: np.ndarray  # (N,) int64 capture time
    eef_pos: np.ndarray  # (N, 3) base frame
    eef_quat_wxyz: np.ndarray  # (N, 4) base frame
    gripper: np.ndarray  # (N,) closure in [0, 1]
    action_tick: np.ndarray  # (M,) int64
    action: np.ndarray  # (M, 7) dp, drot (axis-angle), gripper; base frame
    action_stale: np.ndarray  # (M,) bool: the driver held still for want of a command
    frame_ns: dict[str, np.ndarray] = field(default_factory=dict)  # camera -> (K,) capture times
    frame_data: dict[str, list[bytes]] = field(default_factory=dict)  # camera -> K JPEG payloads
    calib: dict[str, CameraCalib] = field(default_factory=dict)  # cameras with calibration + pose
    control_hz: float | None = None

    @property
    def cameras(self) -> list[str]:
        return sorted(self.frame_ns)


@dataclass
class Aligned:
    """Samples of one episode at its control ticks (base frame), with per-view frame choice."""

    episode_id: str
    tick: np.ndarray  # (T,) int64, increasing
    stamp_ns: np.ndarray  # (T,) capture time of the state
    eef_pos: np.ndarray  # (T, 3)
    eef_rot: np.ndarray  # (T, 3, 3) EEF rotation at the tick, i.e. when the tick's action executes
    gripper: np.ndarray  # (T,)
    action: np.ndarray  # (T, 7) base frame
    frame_index: dict[str, np.ndarray]  # view -> (T,) index into that camera's frames, -1 = dropped
    drops: dict[str, Any]  # reason -> count; "views": view -> reason -> count
    frame_tolerance_ns: dict[str, int] = field(default_factory=dict)  # view -> max frame age used

    def valid(self, view: str) -> np.ndarray:
        return self.frame_index[view] >= 0


def default_max_frame_age_ns(control_hz: float | None) -> int:
    """Half a control period: the tolerance of a camera too sparse to measure."""
    hz = control_hz if control_hz and control_hz > 0 else 10.0
    return int(0.5e9 / hz)


def frame_tolerance_ns(frame_ns: np.ndarray, ages: np.ndarray, control_hz: float | None) -> int:
    """Median age of a camera's frame at a tick plus half its median frame interval."""
    if len(frame_ns) < 3 or len(ages) == 0:
        return default_max_frame_age_ns(control_hz)
    interval = float(np.median(np.diff(frame_ns)))
    if interval <= 0:
        return default_max_frame_age_ns(control_hz)
    return int(np.median(ages) + interval / 2)


def align(
    ep: RawEpisode, views: list[str], max_frame_age_ns: int | None = None, drop_stale_actions: bool = False
) -> Aligned:
    """Pair each state tick with its applied action and each view's frame; count what is dropped."""
    name = ep.path.name
    for v in views:
        if v not in ep.frame_ns:
            have = ", ".join(ep.cameras) or "none"
            raise EpisodeError(f"{name}: no camera {v!r} in this episode (cameras: {have})")
    drops: dict[str, Any] = {"duplicate_state": 0, "no_action": 0, "stale_action": 0, "action_without_state": 0}

    # States by tick; a repeated tick keeps its first message.
    order = np.argsort(ep.state_tick, kind="stable")
    s_tick = ep.state_tick[order]
    first = np.ones(len(s_tick), bool)
    first[1:] = s_tick[1:] != s_tick[:-1]
    drops["duplicate_state"] = int((~first).sum())
    keep = order[first]

    a_order = np.argsort(ep.action_tick, kind="stable")
    a_tick = ep.action_tick[a_order]
    a_first = np.ones(len(a_tick), bool)
    a_first[1:] = a_tick[1:] != a_tick[:-1]
    a_order, a_tick = a_order[a_first], a_tick[a_first]

    s_tick = ep.state_tick[keep]
    pos = np.minimum(np.searchsorted(a_tick, s_tick), max(len(a_tick) - 1, 0))
    has_action = a_tick[pos] == s_tick if len(a_tick) else np.zeros(len(s_tick), bool)
    drops["no_action"] = int((~has_action).sum())
    drops["action_without_state"] = int(len(a_tick) - has_action.sum())
    a_idx = a_order[pos[has_action]]
    keep = keep[has_action]
    stale = ep.action_stale[a_idx].astype(bool)
    drops["stale_action"] = int(stale.sum())
    if drop_stale_actions:
        keep, a_idx = keep[~stale], a_idx[~stale]

    stamp = ep.state_ns[keep].astype(np.int64)
    frame_index: dict[str, np.ndarray] = {}
    tolerance: dict[str, int] = {}
    drops["views"] = {}
    for v in views:
        f_ns = ep.frame_ns[v]
        i = np.searchsorted(f_ns, stamp, side="right") - 1  # newest frame at or before the tick
        missing = i < 0
        age = stamp - f_ns[np.maximum(i, 0)] if len(f_ns) else np.zeros_like(stamp)
        tol = (
            max_frame_age_ns if max_frame_age_ns is not None else frame_tolerance_ns(f_ns, age[~missing], ep.control_hz)
        )
        tolerance[v] = int(tol)
        too_old = ~missing & (age > tol)
        i = np.where(missing | too_old, -1, i)
        frame_index[v] = i.astype(np.int64)
        drops["views"][v] = {"missing_frame": int(missing.sum()), "stale_frame": int(too_old.sum())}

    return Aligned(
        episode_id=ep.episode_id,
        tick=ep.state_tick[keep].astype(np.int64),
        stamp_ns=stamp,
        eef_pos=ep.eef_pos[keep].astype(np.float64),
        eef_rot=quat_wxyz_to_matrix(ep.eef_quat_wxyz[keep]) if len(keep) else np.zeros((0, 3, 3)),
        gripper=ep.gripper[keep].astype(np.float64),
        action=ep.action[a_idx].astype(np.float64),
        frame_index=frame_index,
        drops=drops,
        frame_tolerance_ns=tolerance,
    )


def segments(tick: np.ndarray) -> np.ndarray:
    """End indices (exclusive) of the runs of consecutive ticks, like a replay buffer's episode_ends."""
    tick = np.asarray(tick)
    if len(tick) == 0:
        return np.zeros(0, np.int64)
    breaks = np.nonzero(np.diff(tick) != 1)[0] + 1
    return np.append(breaks, len(tick)).astype(np.int64)


def _moved(a: CameraCalib, b: CameraCalib) -> bool:
    return bool(
        np.abs(a.camera.position - b.camera.position).max() > 1e-4
        or np.abs(a.camera.R_wc - b.camera.R_wc).max() > 1e-4
        or np.abs(a.K - b.K).max() > 1e-3
        or (a.width, a.height) != (b.width, b.height)
    )


def episode_id(path: str | Path, metadata: dict[str, Any]) -> str:
    """An episode's id: its metadata's, or for a file that names none, the file's stem."""
    return str(metadata.get("episode_id") or Path(path).stem)


def load_raw_episode(path: str | Path, views: list[str]) -> RawEpisode:
    """Read the topics a dataset build needs for ``views`` from one recorded episode."""
    path = Path(path)
    wanted = [topics.ROBOT_STATE.mcap_topic, topics.APPLIED_ACTION.mcap_topic]
    for v in views:
        wanted += [
            topics.camera_image(v).mcap_topic,
            topics.camera_calibration(v).mcap_topic,
            topics.camera_pose(v).mcap_topic,
        ]
    try:
        ep = read_episode(path, topics=wanted)
    except EpisodeReadError as exc:
        raise EpisodeError(str(exc)) from exc
    md = dict(ep.metadata)
    name = path.name
    missing = [v for v in views if v not in ep.cameras]
    if missing:
        have = sorted(md.get("frames", {})) or "unknown"
        raise EpisodeError(
            f"{name}: no frames of camera {', '.join(repr(m) for m in missing)} "
            f"(this episode's cameras: {', '.join(have) if isinstance(have, list) else have})"
        )

    states = ep.messages(topics.ROBOT_STATE.mcap_topic)
    applied = ep.messages(topics.APPLIED_ACTION.mcap_topic)
    if not states:
        raise EpisodeError(f"{name}: no robot states recorded")
    # Files written by other tools or older recorders may hold what today's recorder refuses.
    for what, records in (("robot state", states), ("applied action", applied)):
        for r in records:
            try:
                check(r.msg)
            except Invalid as exc:
                raise EpisodeError(f"{name}: {what} of tick {r.msg.tick}: {exc}") from None
    try:
        eef_pos = np.array([list(r.msg.eef_pos) for r in states], dtype=np.float64).reshape(len(states), 3)
        eef_quat = np.array([list(r.msg.eef_quat_wxyz) for r in states], dtype=np.float64).reshape(len(states), 4)
        act = np.array(
            [[*r.msg.action.dp, *r.msg.action.drot, r.msg.action.gripper] for r in applied], dtype=np.float64
        ).reshape(len(applied), 7)
    except ValueError as exc:
        raise EpisodeError(f"{name}: malformed robot state or applied action ({exc})") from exc

    frame_ns: dict[str, np.ndarray] = {}
    frame_data: dict[str, list[bytes]] = {}
    calib: dict[str, CameraCalib] = {}
    for v in views:
        recs = sorted(ep.messages(topics.camera_image(v).mcap_topic), key=lambda r: r.publish_time)
        frame_ns[v] = np.array([r.publish_time for r in recs], dtype=np.int64)
        frame_data[v] = [r.msg.data for r in recs]
        cals = ep.messages(topics.camera_calibration(v).mcap_topic)
        poses = ep.messages(topics.camera_pose(v).mcap_topic)
        if cals and poses:
            found = []
            for c, p in zip(cals, poses):
                cam, K = Camera.from_msgs(c.msg, p.msg)
                found.append(CameraCalib(cam, K, int(c.msg.width), int(c.msg.height)))
            if any(_moved(found[0], f) for f in found[1:]):
                raise EpisodeError(
                    f"{name}: camera {v!r} calibration or pose changed during the episode; "
                    f"a pseudo-demo needs one fixed camera"
                )
            calib[v] = found[0]

    hz = md.get("control_hz")
    return RawEpisode(
        path=path,
        episode_id=episode_id(path, md),
        meta=md,
        state_tick=np.array([r.msg.tick for r in states], dtype=np.int64),
        state_ns=np.array([r.publish_time for r in states], dtype=np.int64),
        eef_pos=eef_pos,
        eef_quat_wxyz=eef_quat,
        gripper=np.array([r.msg.gripper for r in states], dtype=np.float64),
        action_tick=np.array([r.msg.tick for r in applied], dtype=np.int64),
        action=act,
        action_stale=np.array([r.msg.stale for r in applied], dtype=bool),
        frame_ns=frame_ns,
        frame_data=frame_data,
        calib=calib,
        control_hz=float(hz) if hz else None,
    )
