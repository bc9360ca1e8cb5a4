"""The OpenCV camera driver on real media: generated video files and a real RTSP server on
loopback (gst-rtsp-server, the way an IP camera serves its stream), including a stream that
stops and comes back. Frames carry their number, so order, repeats and gaps are checked."""

from __future__ import annotations

import os
import signal
import time

import pytest
from camera_media import RtspServer, code_of, grab_until, require_rtsp_server, write_video
from pydantic import ValidationError

from services.camera.base import Frame
from services.camera.config import CAMERA_DRIVERS, CameraConfig, OpenCVCameraConfig
from services.camera.opencv import OpenCVCamera, fourcc_text, safe_label, v4l2_stamp
from services.core.bus import free_tcp_port
from services.core.config import ConfigError
from services.core.rig import load_rig

RIG = load_rig("three15")


def build(cameras: dict, width: int = 160, height: int = 120, **settings) -> OpenCVCamera:
    cfg = OpenCVCameraConfig(cameras=cameras, **settings)
    return CAMERA_DRIVERS.build(cfg, rig=RIG, width=width, height=height)


def codes(frames: list[Frame]) -> list[int]:
    return [code_of(f.rgb) for f in frames]


def test_a_video_file_plays_in_order_resized_and_then_ends(tmp_path):
    video = write_video(tmp_path / "f.avi", range(30), fps=40)
    driver = build({"F": {"source": str(video)}, "FL": {"source": str(video), "at_end": "loop"}}, width=80, height=60)
    try:
        got = grab_until(driver, lambda g: not driver.stats()["F"].connected and len(g["FL"]) >= 40)
        f = got["F"]
        assert all(fr.rgb.shape == (60, 80, 3) for fr in f)  # 160x120 resized to the service's size
        seen = codes(f)
        assert seen == sorted(set(seen)) and seen[-1] == 29  # in order, never twice, to the end
        stamps = [fr.stamp_ns for fr in f]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        looped = codes(got["FL"])
        assert 0 in looped[1:] and all(b != a for a, b in zip(looped, looped[1:]))  # played again, no repeats

        # The ended camera is gone: counted as a gap, never handed out again, and grab() does not wait for it.
        st = driver.stats()
        assert (st["F"].connected, st["F"].gaps, st["F"].reconnects, st["F"].frames) == (False, 1, 0, 30)
        assert st["F"].resolution == (160, 120) and st["F"].exposure is None
        assert st["FL"].connected and st["FL"].gaps == 0 and st["FL"].fps > 0
        t = time.monotonic()
        assert "F" not in driver.grab(time.time_ns())
        assert time.monotonic() - t < 1.0
    finally:
        driver.close()


def test_frames_not_grabbed_in_time_are_counted_as_drops(tmp_path):
    video = write_video(tmp_path / "f.avi", range(20), fps=50)
    driver = build({"F": {"source": str(video)}})
    try:
        deadline = time.monotonic() + 10
        while driver.stats()["F"].connected:  # nobody grabs while the file plays
            assert time.monotonic() < deadline
            time.sleep(0.02)
        st = driver.stats()["F"]
        assert st.frames == 20 and st.drops == 19  # only the newest is kept
        assert codes(list(driver.grab(time.time_ns()).values())) == [19]
    finally:
        driver.close()


def test_bad_sources_fail_at_start_naming_each_camera_and_source(tmp_path):
    port = free_tcp_port()  # nothing listens there
    with pytest.raises(ConfigError) as err:
        build(
            {
                "F": {"source": str(tmp_path / "missing.avi")},
                "FL": {"source": "/dev/video99"},
                "FR": {"source": f"rtsp://user:secret@127.0.0.1:{port}/cam"},
            },
            open_timeout_s=2,
        )
    text = str(err.value)
    assert "\n" not in text
    assert f"camera F: cannot open {tmp_path / 'missing.avi'}: no such file" in text
    assert "camera FL: cannot open /dev/video99: no such device /dev/video99" in text
    assert f"camera FR: cannot open rtsp://user:***@127.0.0.1:{port}/cam" in text and "secret" not in text
    (tmp_path / "junk.avi").write_bytes(b"not a video")
    with pytest.raises(ConfigError, match="camera F: cannot open .*junk.avi: not a video"):
        build({"F": {"source": str(tmp_path / "junk.avi")}})
    with pytest.raises(ConfigError, match=r"camera X not in rig three15 \(F, FL, FR\)"):
        build({"X": {"source": str(tmp_path / "junk.avi")}})


def test_settings_a_source_cannot_take_are_refused_in_the_config():
    with pytest.raises(ValidationError, match="only a V4L2 device can be asked"):
        OpenCVCameraConfig(cameras={"F": {"source": "a.mp4", "fourcc": "MJPG"}})
    with pytest.raises(ValidationError, match="sends at its own rate"):
        OpenCVCameraConfig(cameras={"F": {"source": "rtsp://cam/1", "fps": 30}})
    cfg = CameraConfig.model_validate(
        {"world": "real", "driver": {"type": "opencv", "cameras": {"F": {"source": 0, "fourcc": "MJPG", "fps": 30}}}}
    )
    assert isinstance(cfg.driver, OpenCVCameraConfig) and cfg.driver.cameras["F"].fourcc == "MJPG"


def test_v4l2_frames_are_stamped_by_the_kernel_buffer_time():
    # Arrived at Unix 1000.000 s / monotonic 50.000 s; the kernel stamped the buffer at
    # monotonic 49.970 s: captured 30 ms before arrival, plus 5 ms configured before the kernel.
    assert v4l2_stamp(1_000_000_000_000, 50.0, 49_970.0, 0.005) == 1_000_000_000_000 - 35_000_000
    # A stamp from another clock (or none: 0) is not believed: only the configured latency counts.
    assert v4l2_stamp(1_000_000_000_000, 50.0, 1.7e12, 0.005) == 1_000_000_000_000 - 5_000_000
    assert v4l2_stamp(1_000_000_000_000, 50.0, 0.0, 0.0) == 1_000_000_000_000
    assert fourcc_text(float(0x47504A4D)) == "MJPG" and fourcc_text(0.0) == ""
    assert safe_label(2) == "/dev/video2" and safe_label("rtsp://u:p@h:554/s") == "rtsp://u:***@h:554/s"


def test_an_rtsp_stream_that_stops_and_comes_back(tmp_path):
    require_rtsp_server()
    with RtspServer(fps=20) as server:
        url = server.start(first=0)
        driver = build({"F": {"source": url}}, read_timeout_s=1, open_timeout_s=2, reconnect_min_s=0.1)
        try:
            before = codes(grab_until(driver, lambda g: len(g["F"]) >= 10)["F"])
            assert before == sorted(set(before))
            server.kill()  # the camera loses power
            deadline = time.monotonic() + 5
            while driver.stats()["F"].connected:
                assert time.monotonic() < deadline, "the dropped stream was not noticed"
                t = time.monotonic()
                driver.grab(time.time_ns())
                assert time.monotonic() - t < 1.0  # grab() never hangs on a dead camera
            assert driver.stats()["F"].gaps == 1
            server.start(first=500)  # back, at the same URL, further along
            back = codes(grab_until(driver, lambda g: sum(code_of(f.rgb) >= 500 for f in g["F"]) >= 5)["F"])
            seen = before + back  # a frame captured before the drop may still be handed out, but once
            assert seen == sorted(set(seen))  # never twice, and in order: nothing stale passed off as new
            st = driver.stats()["F"]
            assert (st.connected, st.gaps, st.reconnects) == (True, 1, 1)
            assert st.last_gap_s > 0 and st.resolution == (160, 120)
        finally:
            driver.close()


@pytest.mark.slow
def test_a_silent_rtsp_stream_is_dropped_after_the_read_timeout(tmp_path):
    # A frozen camera (or a pulled network cable) keeps its TCP connection open and says nothing:
    # only the read timeout can tell. SIGSTOP freezes the server exactly like that.
    require_rtsp_server()
    with RtspServer(fps=20) as server:
        driver = build({"F": {"source": server.start()}}, read_timeout_s=0.5, open_timeout_s=1, reconnect_min_s=0.1)
        try:
            grab_until(driver, lambda g: len(g["F"]) >= 5)
            os.kill(server.proc.pid, signal.SIGSTOP)
            t = time.monotonic()
            grab_until(driver, lambda g: not driver.stats()["F"].connected, timeout=5)
            assert time.monotonic() - t < 3
            os.kill(server.proc.pid, signal.SIGCONT)
            grab_until(driver, lambda g: len(g["F"]) >= 5, timeout=15)
            st = driver.stats()["F"]
            assert (st.connected, st.gaps, st.reconnects) == (True, 1, 1)
        finally:
            driver.close()
