"""``python -m services.camera`` with the OpenCV driver, as a lab runs it: a video file and an
RTSP camera published over a real Zenoh router on loopback, a camera that drops out and comes
back mid-episode flagging the recorder's episode, and a bad source refused at start-up."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml
from camera_media import RtspServer, code_of, require_rtsp_server, write_video

from services.core import topics
from services.core.bus import Bus
from services.core.tensors import decode_jpeg
from services.pb.episode_pb2 import EPISODE_COMMAND_START, EPISODE_COMMAND_STOP, EpisodeReply, EpisodeRequest
from services.recorder.config import RecorderConfig
from services.recorder.service import Recorder

ROOT = Path(__file__).resolve().parents[2]


def control(bus: Bus, command: int, **fields) -> EpisodeReply:
    req = EpisodeRequest(command=command, **fields)
    return EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=15))


@pytest.mark.slow
def test_frames_over_zenoh_and_a_camera_gap_flags_the_episode(zenoh_endpoint, bus_config, make_bus, tmp_path):
    require_rtsp_server()
    video = write_video(tmp_path / "F.avi", range(600), fps=20)  # 30 s: longer than the test
    bus = make_bus()
    got: dict[str, list] = {"F": [], "FL": []}
    presence: list[tuple[str, bool]] = []
    cv = threading.Condition()

    def keep(name):
        def on_image(msg, _rx):
            with cv:
                got[name].append((msg.timestamp.ToNanoseconds(), decode_jpeg(msg.data)))
                cv.notify_all()

        return on_image

    def on_alive(service, alive):
        with cv:
            presence.append((service, alive))
            cv.notify_all()

    def wait(what: str, done, timeout: float = 20.0) -> None:
        with cv:
            assert cv.wait_for(done, timeout=timeout), f"timed out waiting for {what}: {presence}"

    for name in got:
        bus.subscribe(topics.camera_image(name), keep(name))
    bus.watch_alive(on_alive)
    recorder_cfg = RecorderConfig(bus=bus_config, out_dir=tmp_path / "episodes")
    with RtspServer(fps=20) as server, Bus(bus_config) as recorder_bus, Recorder(recorder_cfg, recorder_bus):
        config = tmp_path / "real.yaml"
        driver = {
            "type": "opencv",
            "read_timeout_s": 1,
            "open_timeout_s": 2,
            "reconnect_min_s": 0.1,
            "cameras": {"F": {"source": str(video)}, "FL": {"source": server.start(first=0)}},
        }
        section = {"rig": "three15", "width": 80, "height": 60, "fps": 20, "stats_period_s": 0.5, "driver": driver}
        config.write_text(yaml.safe_dump({"world": "real", "camera": section}))
        log = tmp_path / "camera.log"
        cmd = [sys.executable, "-m", "services.camera", "--config", str(config), "--set", "bus.mode=client"]
        cmd += ["--set", f"bus.connect=[{zenoh_endpoint}]"]
        with open(log, "w") as err:
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
        try:
            line = proc.stdout.readline()
            assert line == "ready camera opencv/three15\n", f"{line!r} {log.read_text()}"
            wait("frames of both cameras", lambda: len(got["F"]) >= 3 and len(got["FL"]) >= 3)
            assert control(bus, EPISODE_COMMAND_START, episode_id="gap", task="lift", rig="three15").ok

            server.kill()  # FL loses power mid-episode
            wait("FL withdrawn", lambda: ("camera/FL", False) in presence)
            with cv:
                f_at_loss, fl_at_loss = len(got["F"]), len(got["FL"])
            server.start(first=500)
            wait("FL back", lambda: ("camera/FL", True) in presence[presence.index(("camera/FL", False)) :])
            wait("new FL frames", lambda: sum(code_of(rgb) >= 500 for _, rgb in got["FL"]) >= 3)
            reply = control(bus, EPISODE_COMMAND_STOP, episode_id="gap")
            assert reply.ok, reply.error
        finally:
            proc.terminate()
            assert proc.wait(timeout=20) == 0, log.read_text()

    flags = list(reply.meta.flags)
    assert "service camera/FL lost liveliness mid-episode" in flags, flags
    assert "service camera/FL restarted mid-episode" in flags, flags
    assert not any("camera/F " in f or f.startswith("service camera/F lost") for f in flags), flags
    assert reply.meta.frames["F"] > 0 and reply.meta.frames["FL"] > 0
    with cv:
        for name, frames in got.items():
            stamps = [s for s, _ in frames]
            assert stamps == sorted(set(stamps)), name  # capture times, in order, each frame once
            seen = [code_of(rgb) for _, rgb in frames]
            assert seen == sorted(set(seen)), (name, seen)  # nothing repeated or stale passed off as new
            assert all(rgb.shape == (60, 80, 3) for _, rgb in frames)
        assert len(got["F"]) > f_at_loss + 5  # F went on publishing while FL was gone
        assert all(code_of(rgb) >= 500 for _, rgb in got["FL"][fl_at_loss + 1 :])  # no FL frame made up for the gap
    text = log.read_text()
    assert "camera FL: rtsp://127.0.0.1" in text and "stopped delivering; reconnecting" in text
    assert "camera FL is not delivering: withdrawn from the bus" in text
    assert "camera FL: connected, " in text and "1 reconnects, 1 gaps (last " in text  # the periodic stats line


def test_a_source_that_cannot_open_is_one_clear_line_at_start_up(tmp_path):
    missing = tmp_path / "missing.avi"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.camera",
            "--set",
            "world=real",
            "--set",
            "rig=three15",
            "--set",
            f"driver={{type: opencv, cameras: {{F: {{source: {missing}}}}}}}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"error: camera F: cannot open {missing}: no such file"
