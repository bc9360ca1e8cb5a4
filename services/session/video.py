"""An MP4 of one recorded episode from one camera, with the tick and the outcome drawn in.

VP9 in MP4 (``vp09``), which browsers, notebooks and code-review pages play; OpenCV's MPEG-4 Part 2
(``mp4v``), which they do not, only where this OpenCV build has no VP9 encoder (said once, in the log).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from services.core.tensors import decode_jpeg
from services.recorder.reader import read_episode

SCALE = 4  # 84 px frames become 336 px: big enough to see the gripper
CODECS = ("vp09", "mp4v")  # the first this OpenCV can write
log = logging.getLogger("video")
_said_fallback: list[str] = []


def open_writer(out: Path, fps: float, size: tuple[int, int]) -> tuple[cv2.VideoWriter, str]:
    """A writer of ``out`` with the first of ``CODECS`` this OpenCV build encodes, and its code."""
    for code in CODECS:
        writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*code), fps, size)
        if writer.isOpened():
            if code != CODECS[0] and not _said_fallback:
                _said_fallback.append(code)
                log.warning("this OpenCV has no VP9 encoder: videos are %s, which browsers do not play", code)
            return writer, code
        writer.release()
    raise RuntimeError(f"OpenCV cannot write {out} (no VP9 or MPEG-4 encoder in this build)")


def annotate(rgb: np.ndarray, text: str, colour: tuple[int, int, int]) -> np.ndarray:
    """(H, W, 3) RGB scaled up, with ``text`` on a dark band at the bottom."""
    img = cv2.resize(rgb, (rgb.shape[1] * SCALE, rgb.shape[0] * SCALE), interpolation=cv2.INTER_NEAREST)
    band = max(18, img.shape[0] // 12)
    img[-band:] = (img[-band:] * 0.35).astype(np.uint8)
    cv2.putText(img, text, (6, img.shape[0] - band // 3), cv2.FONT_HERSHEY_SIMPLEX, band / 40, colour, 1, cv2.LINE_AA)
    return img


def write_video(episode: Path, camera: str, out: Path, success: bool | None = None, fps: float | None = None) -> Path:
    """``out`` (.mp4) of ``camera``'s frames in ``episode``; the last second repeats the final frame."""
    ep = read_episode(episode, topics=[f"/camera/{camera}/image"])
    frames = ep.messages(f"/camera/{camera}/image")
    if not frames:
        raise ValueError(f"{episode.name} has no frames of camera {camera!r} (cameras: {', '.join(ep.cameras)})")
    if success is None:
        success = bool(ep.metadata.get("success"))
    fps = fps or float(ep.metadata.get("control_hz") or 20.0)
    verdict, colour = ("SUCCESS", (80, 220, 80)) if success else ("FAILURE", (240, 80, 60))
    out.parent.mkdir(parents=True, exist_ok=True)
    first = decode_jpeg(frames[0].msg.data)
    size = (first.shape[1] * SCALE, first.shape[0] * SCALE)
    writer, _ = open_writer(out, fps, size)
    try:
        img = first
        for i, rec in enumerate(frames):
            img = annotate(decode_jpeg(rec.msg.data), f"{camera}  tick {i}", (235, 235, 235))
            writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        last = annotate(decode_jpeg(frames[-1].msg.data), f"{camera}  {verdict} in {len(frames)} ticks", colour)
        for _ in range(int(fps)):
            writer.write(cv2.cvtColor(last, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return out
