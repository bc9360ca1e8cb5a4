"""``viewscale rerender``: recorded sim episodes replayed through another rig (sim only).

    viewscale rerender --raw data/raw --rig three30 --out data/raw-three30

Every episode is replayed from its seed with its applied actions (deterministic: the replay
holds to 1e-6 m) and rendered through the new rig's cameras, then written as a collected episode
would be: the same channels and schemas (frames, calibration and pose per camera, robot state,
applied action, task state, the final EpisodeMeta and metadata records), stamped with the
recording's own capture times. It differs from a collected one only by ``rerendered_from`` (the
source file) and, of course, the cameras. So every row of a table can use the same expert
demonstrations, and a new camera layout can be tried without collecting again.

An episode whose replay leaves the recorded trajectory (more than ``tolerance_m``), or that has no
seed or task, is refused with its reason; the others go on. One that an earlier run re-rendered
into ``out`` from the same file at the same size is kept, so that a run over a folder that gained
episodes renders only the new ones. A run holds ``out`` while it writes there (a second is refused):
the ``.part`` of an episode it finds there was left by a run that was stopped, and is rendered again.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.core import topics
from services.core.rig import load_rig
from services.core.robot_types import action_from_msg, state_msg
from services.core.runtime import exclusive
from services.core.tensors import compressed_image
from services.dataset.build import find_episodes
from services.pb.control_pb2 import AppliedAction
from services.pb.episode_pb2 import EpisodeMeta
from services.recorder.reader import EpisodeReadError, read_episode
from services.recorder.writer import (
    EPISODE_CHANNEL,
    EPISODE_RECORD,
    PART_SUFFIX,
    START_RECORD,
    EpisodeWriter,
    meta_to_record,
)
from services.recorder.writer import start_record as start_record_of
from sim.service import task_state_msg
from sim.world import SimWorld

CALIBRATION_EVERY_S = 1.0  # as the sim republishes it


class RerenderError(ValueError):
    """An episode that cannot be re-rendered; the message names the file."""


@dataclass
class Rerendered:
    source: Path
    path: Path | None = None
    ticks: int = 0
    max_deviation_m: float = 0.0
    error: str = ""
    kept: bool = False  # re-rendered by an earlier run, from the same file at the same size
    stale_part: bool = False  # a .part of it, left by a run that was stopped, was removed first


def _done_before(path: Path, src: Path, size: int, cameras: list[str]) -> Rerendered | None:
    """The episode at ``path`` when an earlier run re-rendered it from ``src`` at ``size`` (a run
    over a folder that gained episodes renders only the new ones), else None."""
    calibration = [topics.camera_calibration(c).mcap_topic for c in cameras]
    try:
        ep = read_episode(path, topics=calibration)  # (not its frames)
    except EpisodeReadError:
        return None
    cals = [r.msg for t in calibration for r in ep.messages(t)]
    if ep.metadata.get("rerendered_from") != str(src.resolve()) or not cals or int(cals[0].width) != size:
        return None
    return Rerendered(src, path=path, ticks=int(ep.metadata.get("ticks") or 0), kept=True)


@dataclass
class RerenderResult:
    episodes: list[Rerendered] = field(default_factory=list)

    @property
    def written(self) -> list[Rerendered]:
        return [e for e in self.episodes if e.path is not None]


def rerender_episode(
    src: Path,
    rig_name: str,
    out_dir: Path,
    size: int | None = None,
    tolerance_m: float = 1e-5,
    own_folder: bool = False,
) -> Rerendered:
    """Replay ``src`` through ``rig_name`` into ``out_dir``. ``own_folder``: the caller holds the
    folder's lock (``rerender``), so a ``.part`` of this episode there is what a run that was
    stopped left (killed: nothing cleaned up after it), and is rendered again."""
    try:
        ep = read_episode(src)
    except EpisodeReadError as exc:
        raise RerenderError(str(exc)) from None
    md = ep.metadata
    task, seed = md.get("task"), md.get("seed")
    if not task or seed is None:
        raise RerenderError(f"{src.name}: no task or seed recorded (only sim episodes can be re-rendered)")
    states = [r.msg for r in ep.messages(topics.ROBOT_STATE.mcap_topic)]
    applied = {r.msg.tick: r.msg for r in ep.messages(topics.APPLIED_ACTION.mcap_topic)}
    if not states:
        raise RerenderError(f"{src.name}: no robot states")
    if size is None:
        cals = [r.msg for c in ep.cameras for r in ep.messages(f"/camera/{c}/calibration")]
        size = int(cals[0].width) if cals else 84
    rig = load_rig(rig_name)
    hz = float(md.get("control_hz") or 20.0)
    episode_id = f"{md.get('episode_id') or src.stem}-{rig.name}"
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{episode_id}.mcap"
    if path.exists():
        done = _done_before(path, src, size, list(rig.cameras))
        if done is not None:
            return done
        raise RerenderError(
            f"{path} already exists, re-rendered from another file or at another size: move it away to render it again"
        )
    meta = EpisodeMeta(
        episode_id=episode_id,
        task=task,
        seed=int(seed),
        rig=rig.name,
        control_hz=hz,
        lockstep=bool(md.get("lockstep")),
        start_ns=int(md.get("start_ns") or states[0].header.stamp_ns),
        path=str(path),
        rerendered_from=str(src.resolve()),
    )
    out = Rerendered(src)
    part = path.with_name(path.name + PART_SUFFIX)
    if part.exists():
        if not own_folder:
            raise RerenderError(f"{part} exists: another run is rendering it, or one that was stopped left it")
        part.unlink()
        out.stale_part = True
    writer = EpisodeWriter(path)
    try:
        writer.add_metadata(START_RECORD, start_record_of(meta))
        with SimWorld(task, rig, size, size, hz) as world:
            world.reset(int(seed))
            cams = world.rig.cameras
            last_calib = None
            frames: dict[str, int] = {c: 0 for c in cams}
            for k, rec in enumerate(states):
                stamp = int(rec.header.stamp_ns)
                if last_calib is None or stamp - last_calib >= CALIBRATION_EVERY_S * 1e9:
                    for name, cam in cams.items():
                        writer.write_message(
                            topics.camera_calibration(name).mcap_topic,
                            cam.calibration_msg(size, size, stamp),
                            stamp,
                            stamp,
                        )
                        writer.write_message(topics.camera_pose(name).mcap_topic, cam.pose_msg(stamp), stamp, stamp)
                    last_calib = stamp
                robot = world.robot()
                out.max_deviation_m = max(
                    out.max_deviation_m, float(np.abs(robot.eef_pos - np.asarray(rec.eef_pos)).max())
                )
                for name, rgb in world.render().items():
                    writer.write_message(
                        topics.camera_image(name).mcap_topic, compressed_image(rgb, stamp, name), stamp, stamp
                    )
                    frames[name] += 1
                task_msg = task_state_msg(world, rec.tick, stamp, k + 1, int(seed), episode_id)
                replayed_success = task_msg.success  # success at the last observation, as the session decides it
                writer.write_message(topics.TASK_STATE.mcap_topic, task_msg, stamp, stamp)
                writer.write_message(
                    topics.ROBOT_STATE.mcap_topic, state_msg(robot, rec.tick, stamp, k + 1, episode_id), stamp, stamp
                )
                act = applied.get(rec.tick)
                if act is None:
                    break  # the recording stopped here: so does the replay
                a = action_from_msg(act.action)
                world.step(a.dp, a.drot, a.gripper)
                a_stamp = int(act.header.stamp_ns) or stamp
                copy = AppliedAction()
                copy.CopyFrom(act)
                writer.write_message(topics.APPLIED_ACTION.mcap_topic, copy, max(a_stamp, stamp), a_stamp)
                out.ticks += 1
        if out.max_deviation_m > tolerance_m:
            raise RerenderError(
                f"{src.name}: the replay left the recorded trajectory by {out.max_deviation_m:.2e} m "
                f"(more than {tolerance_m:g}); was it recorded with another sim build?"
            )
        meta.success = bool(md.get("success"))
        if replayed_success != meta.success:
            raise RerenderError(f"{src.name}: recorded {'success' if meta.success else 'failure'}, replayed the other")
        meta.ticks = out.ticks
        meta.achieved_hz = float(md.get("achieved_hz") or 0.0)
        meta.frames.update(frames)
        meta.stale_ticks = int(md.get("stale_ticks") or 0)
        meta.clipped_ticks = int(md.get("clipped_ticks") or 0)
        meta.flags.extend(md.get("flags") or [])
        meta.command_sources.extend(md.get("command_sources") or [])
        meta.end_ns = int(md.get("end_ns") or time.time_ns())
        writer.write_message(EPISODE_CHANNEL, meta, meta.end_ns, meta.end_ns)
        writer.flush()
        writer.add_metadata(EPISODE_RECORD, meta_to_record(meta))
        writer.close()
    except BaseException:
        writer.abort()
        raise
    out.path = path
    return out


def rerender(
    raw: Path | list[Path], rig: str, out: Path, size: int | None = None, progress: Callable[[str], None] = print
) -> RerenderResult:
    load_rig(rig)  # an unknown rig fails before anything is read
    sources = find_episodes(raw)
    result = RerenderResult()
    Path(out).mkdir(parents=True, exist_ok=True)
    # one rerender per folder: a second would render the same episodes beside the first
    with exclusive(out, "rerender"):
        for i, src in enumerate(sources, 1):
            t0 = time.perf_counter()
            try:
                done = rerender_episode(src, rig, Path(out), size, own_folder=True)
            except RerenderError as exc:
                result.episodes.append(Rerendered(src, error=str(exc)))
                progress(f"[{i}/{len(sources)}] {src.name}: SKIPPED: {exc}")
                continue
            result.episodes.append(done)
            if done.kept:
                progress(f"[{i}/{len(sources)}] {src.name}: re-rendered before, kept -> {done.path}")
                continue
            progress(
                f"[{i}/{len(sources)}] {src.name}: {done.ticks} ticks through {rig} in "
                f"{time.perf_counter() - t0:.1f} s (replay within {done.max_deviation_m:.1e} m) -> {done.path}"
                + (" (rendered again: a .part of it was left by a run that was stopped)" if done.stale_part else "")
            )
    return result
