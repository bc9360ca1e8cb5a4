"""Rollout videos: VP9 in MP4, which browsers play; MPEG-4 Part 2 only where OpenCV has no VP9."""

from __future__ import annotations

import logging

import cv2

from services.camera.opencv import fourcc_text
from services.session import video


def frames_and_codec(path):
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    return n, fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))


def test_a_rollout_video_is_vp9_and_falls_back_to_mpeg4_saying_so_once(sim_dataset, tmp_path, monkeypatch, caplog):
    episode = sorted((sim_dataset.parent / "raw").glob("*.mcap"))[0]
    out = video.write_video(episode, "F", tmp_path / "a.mp4", success=True, fps=20)
    n, codec = frames_and_codec(out)
    ticks = len(video.read_episode(episode, topics=["/camera/F/image"]).messages("/camera/F/image"))
    assert codec == "VP90" and n == ticks + 20  # every tick, then a second of the verdict
    assert not caplog.records

    monkeypatch.setattr(video, "CODECS", ("zzzz", "mp4v"))  # (an OpenCV build with no encoder of the first)
    monkeypatch.setattr(video, "_said_fallback", [])
    with caplog.at_level(logging.WARNING, logger="video"):
        for name in ("b.mp4", "c.mp4"):
            assert frames_and_codec(video.write_video(episode, "F", tmp_path / name, fps=20)) == (n, "FMP4")
    assert [r.getMessage() for r in caplog.records] == [
        "this OpenCV has no VP9 encoder: videos are mp4v, which browsers do not play"
    ]
