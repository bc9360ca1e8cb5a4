"""One demonstration -> one pseudo-demonstration per camera view, and the chunks a policy trains on.

A pseudo-demo of view v keeps the ticks where v has a frame, its actions in the chosen action
space (``action_spaces.to_space`` with v's R_ext, or the EEF rotation of each tick), and the
robot state in the chosen state frame. Its rows split into segments of consecutive ticks.

Chunks follow diffusion_policy's ``SequenceSampler``: a sequence of Tp steps starting To - 1
steps before the current one; observations are its first To steps, actions all Tp. Current
steps run from the segment's first tick to the last one that still has Ta real actions ahead
(``pad_before = To - 1``, ``pad_after = Ta - 1``), and indices outside the segment take the
edge row. ``pad_actions="hold"`` instead pads actions past either edge with zero motion and the
edge's gripper, which is what repeating an absolute target means for delta actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.core.action_spaces import state_vector, to_space
from services.dataset.episodes import Aligned, CameraCalib, EpisodeError, segments


@dataclass
class PseudoDemo:
    episode_id: str
    view: str
    tick: np.ndarray  # (n,) int64
    stamp_ns: np.ndarray  # (n,) int64 state capture time
    frame_index: np.ndarray  # (n,) index into the camera's recorded frames
    state: np.ndarray  # (n, D) in the state frame
    action: np.ndarray  # (n, 7) in the action space
    ends: np.ndarray  # (S,) exclusive end row of each segment of consecutive ticks


def make_pseudo_demo(
    al: Aligned, view: str, space: str, state_frame: str, calib: CameraCalib | None, source: str = ""
) -> PseudoDemo:
    needs_calib = space == "camera" or state_frame == "camera"
    if needs_calib and calib is None:
        what = "the camera action space" if space == "camera" else "a camera-frame state"
        raise EpisodeError(
            f"{source or al.episode_id}: camera {view!r} has no calibration/pose recorded; {what} needs it"
        )
    keep = al.valid(view)
    R_ext = calib.camera.R_ext if calib is not None else None
    position = calib.camera.position if calib is not None else None
    action = to_space(al.action[keep], space, eef_rot=al.eef_rot[keep], R_ext=R_ext)
    state = state_vector(
        al.eef_pos[keep], al.eef_rot[keep], al.gripper[keep], state_frame, R_ext=R_ext, cam_position=position
    )
    tick = al.tick[keep]
    return PseudoDemo(
        episode_id=al.episode_id,
        view=view,
        tick=tick,
        stamp_ns=al.stamp_ns[keep],
        frame_index=al.frame_index[view][keep],
        state=state,
        action=action,
        ends=segments(tick),
    )


def shortest_chunked(To: int, Tp: int, Ta: int) -> int:
    """The fewest ticks a segment needs for one chunk of ``chunk_starts`` (To-1 observations padded
    before its start, Ta-1 actions after its end)."""
    return Tp - Ta - To + 2


def longest_segment(ends: np.ndarray) -> int:
    """The most ticks in one segment of a pseudo-demo (``ends``: each segment's end row)."""
    e = np.asarray(ends, dtype=np.int64)
    return int(np.diff(e, prepend=0).max()) if len(e) else 0


def no_chunk_fits(To: int, Tp: int, Ta: int, longest: int) -> str:
    """Why a set of pseudo-demos whose longest segment has ``longest`` ticks gives no sample."""
    return (
        f"no chunk fits: with To={To}, Tp={Tp}, Ta={Ta} a chunk needs a segment of at least "
        f"{shortest_chunked(To, Tp, Ta)} ticks, and the longest here has {longest}"
    )


def chunk_starts(ends: np.ndarray, To: int, Tp: int, Ta: int) -> np.ndarray:
    """(K, 3) rows ``(current, seg_start, seg_end)`` of every chunk of a pseudo-demo's segments."""
    if not 1 <= To <= Tp or not 1 <= Ta <= Tp - To + 1:
        raise ValueError(f"need 1 <= To <= Tp and 1 <= Ta <= Tp - To + 1 (To={To}, Tp={Tp}, Ta={Ta})")
    out = []
    start = 0
    for end in np.asarray(ends, dtype=np.int64):
        L = int(end - start)
        # diffusion_policy: sequence starts idx in [-(To-1), L - Tp + Ta - 1]; current = idx + To - 1
        first, last = 0, L - Tp + Ta - 1 + To - 1
        if last >= first:
            cur = np.arange(first, last + 1, dtype=np.int64) + start
            out.append(np.stack([cur, np.full_like(cur, start), np.full_like(cur, end)], axis=1))
        start = int(end)
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


def chunk_rows(current: int, seg_start: int, seg_end: int, To: int, Tp: int) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (clamped into the segment) of a chunk, and the mask of rows really inside it."""
    idx = np.arange(current - To + 1, current - To + 1 + Tp)
    inside = (idx >= seg_start) & (idx < seg_end)
    return np.clip(idx, seg_start, seg_end - 1), inside


def pad_hold(actions: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Zero the motion of padded action rows (gripper keeps the edge value)."""
    out = np.array(actions, copy=True)
    out[~inside, 0:6] = 0.0
    return out
