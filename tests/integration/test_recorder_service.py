"""The recorder in-process on real Zenoh (a loopback router, client sessions) writing real files."""

from __future__ import annotations

import re
import threading
import time
from contextlib import ExitStack

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from polling import wait_for

from services.core import topics
from services.core.bus import Bus, BusConfig, free_tcp_port, router
from services.core.rig import Camera, look_at
from services.core.runtime import LOCK_FILE
from services.core.tensors import compressed_image, encode_jpeg
from services.pb.control_pb2 import AppliedAction
from services.pb.episode_pb2 import (
    EPISODE_COMMAND_DISCARD,
    EPISODE_COMMAND_START,
    EPISODE_COMMAND_STATUS,
    EPISODE_COMMAND_STOP,
    EpisodeMeta,
    EpisodeReply,
    EpisodeRequest,
    SimCommand,
    SimControlRequest,
)
from services.pb.sensors_pb2 import RobotState, TaskState
from services.recorder.config import RecorderConfig
from services.recorder.reader import read_episode
from services.recorder.service import Recorder
from services.recorder.writer import EPISODE_RECORD, record_to_dict

PERIOD_NS = 20_000_000  # 50 Hz capture stamps
RNG = np.random.default_rng(1)


def chunk_log_times(path) -> list[list[int]]:
    """The log times of every chunk's messages, in the order they are stored."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    out = []
    with open(path, "rb") as f:
        for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
            if isinstance(record, Chunk):
                out.append([r.log_time for r in breakup_chunk(record) if isinstance(r, Message)])
    return out


class Net:
    """A loopback router plus helpers to open client sessions on it."""

    def __init__(self, stack: ExitStack):
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.stack = stack
        stack.enter_context(router([self.endpoint]))

    def bus_config(self) -> BusConfig:
        return BusConfig(mode="client", connect=[self.endpoint])

    def client(self) -> Bus:
        return self.stack.enter_context(Bus(self.bus_config()))


@pytest.fixture
def net():
    with ExitStack() as stack:
        yield Net(stack)


@pytest.fixture
def make_recorder(net, tmp_path):
    with ExitStack() as stack:

        def make(**overrides) -> Recorder:
            cfg = RecorderConfig(bus=net.bus_config(), out_dir=tmp_path / "episodes", **overrides)
            bus = stack.enter_context(Bus(cfg.bus))
            return stack.enter_context(Recorder(cfg, bus))

        yield make


def control(bus: Bus, command: int, **fields) -> EpisodeReply:
    req = EpisodeRequest(command=command, **fields)
    return EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=15))


def status(bus: Bus) -> EpisodeReply:
    return control(bus, EPISODE_COMMAND_STATUS)


class Source:
    """A synthetic session: robot state, applied action, task state and a JPEG per camera per tick.
    ``paced``: each tick is sent at its capture stamp, as a real source's is (sent earlier, the
    recorder flags a publisher clock ahead of its own); unpaced, as fast as it goes (a flood)."""

    def __init__(self, bus: Bus, cameras: tuple[str, ...] = ("F", "L"), shape=(24, 32), paced: bool = True):
        self.bus = bus
        self.paced = paced
        self.cameras = cameras
        self.state = bus.publisher(topics.ROBOT_STATE)
        self.applied = bus.publisher(topics.APPLIED_ACTION)
        self.task = bus.publisher(topics.TASK_STATE)
        self.images = {c: bus.publisher(topics.camera_image(c)) for c in cameras}
        self.calib = {c: bus.publisher(topics.camera_calibration(c)) for c in cameras}
        self.pose = {c: bus.publisher(topics.camera_pose(c)) for c in cameras}
        self.frame = RNG.integers(0, 255, (*shape, 3), dtype=np.uint8)
        self.t0 = time.time_ns()
        self.stamps: list[int] = []

    def camera(self, name: str) -> Camera:
        pos = np.array([1.5, 0.3 * len(name), 0.6])
        return Camera(name, pos, look_at(pos, np.array([0.5, 0.0, 0.1])), 50.0)

    def publish_calibration(self) -> None:
        stamp = time.time_ns()
        for c in self.cameras:
            self.calib[c].put(self.camera(c).calibration_msg(32, 24, stamp))
            self.pose[c].put(self.camera(c).pose_msg(stamp))

    def tick(self, i: int, seq: int | None = None, observe: bool = True, act: bool = True) -> int:
        """Tick ``i``: its state and frames (``observe``), then its applied action and task state (``act``)."""
        stamp = self.t0 + i * PERIOD_NS
        seq = i if seq is None else seq
        if self.paced:
            time.sleep(max(0.0, (stamp - time.time_ns()) / 1e9))
        if observe:
            state = RobotState(
                tick=i, eef_pos=[0.4, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0]
            )  # a source that names no episode
            state.header.stamp_ns, state.header.seq = stamp, seq
            self.state.put(state)
            for c in self.cameras:
                self.images[c].put(compressed_image(self.frame, stamp, c))
            self.stamps.append(stamp)
        if act:
            applied = AppliedAction(tick=i)
            applied.header.stamp_ns, applied.header.seq = stamp, seq
            applied.action.dp.extend([0.0, 0.0, 0.01])
            applied.action.drot.extend([0.0, 0.0, 0.0])
            self.applied.put(applied)
            task = TaskState(tick=i, task="lift", seed=3)
            task.header.stamp_ns, task.header.seq = stamp, seq
            self.task.put(task)
        return stamp

    def run(self, ticks: range) -> None:
        for i in ticks:
            self.tick(i)


def start(bus: Bus, episode_id: str, control_hz: float = 50.0) -> EpisodeReply:
    return control(
        bus, EPISODE_COMMAND_START, episode_id=episode_id, task="lift", seed=3, rig="five15", control_hz=control_hz
    )


def test_records_a_session_into_a_self_contained_mcap(net, make_recorder, tmp_path):
    rec = make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub)
    src.publish_calibration()
    wait_for(lambda: len(rec.cached_calibration) == 4, what="calibration cached while idle")
    announced: list[EpisodeMeta] = []
    pub.subscribe(topics.EPISODE, lambda msg, rx: announced.append(msg))
    stray = pub.publisher(topics.Topic("policy/debug", RobotState))  # a key outside the session graph

    reply = start(pub, "ep-0001")
    assert reply.ok and reply.recording, reply.error
    src.run(range(12))
    # Republished mid-episode (1 Hz / sim reset): recorded too. Ahead of later ticks on the same
    # session, so it is in before STOP's tick count is complete (one published after the last tick
    # could arrive after the file closed).
    src.publish_calibration()
    src.run(range(12, 25))
    stray.put(b"not recorded")
    reply = control(pub, EPISODE_COMMAND_STOP, episode_id="ep-0001", success=True, ticks=25)
    assert reply.ok, reply.error
    meta = reply.meta
    assert (meta.ticks, dict(meta.frames), meta.success) == (25, {"F": 25, "L": 25}, True)
    assert meta.achieved_hz == pytest.approx(50.0)
    assert list(meta.flags) == [] and not meta.drops and not meta.malformed and not meta.gaps
    path = tmp_path / "episodes" / "ep-0001.mcap"
    assert meta.path == str(path) and path.is_file()
    assert not list((tmp_path / "episodes").glob("*.part"))
    wait_for(lambda: announced and announced[-1].end_ns, what="the closed episode's EpisodeMeta on recorder/episode")
    assert announced[-1] == meta
    # its start too, once and again each second while it recorded (end_ns 0)
    assert announced[:-1] and all(m.episode_id == "ep-0001" and m.end_ns == 0 for m in announced[:-1])

    # Read back with the mcap library alone, in file order.
    per_channel: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            per_channel.setdefault(channel.topic, []).append((message, decoded))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert schemas == {
        "/robot/state": "viewscale.v1.RobotState",
        "/robot/applied": "viewscale.v1.AppliedAction",
        "/sim/task": "viewscale.v1.TaskState",
        "/recorder/episode": "viewscale.v1.EpisodeMeta",
        **{f"/camera/{c}/image": "foxglove.CompressedImage" for c in "FL"},
        **{f"/camera/{c}/calibration": "foxglove.CameraCalibration" for c in "FL"},
        **{f"/camera/{c}/pose": "foxglove.FrameTransform" for c in "FL"},
    }
    counts = {t: len(v) for t, v in per_channel.items()}
    assert counts == {
        "/robot/state": 25,
        "/robot/applied": 25,
        "/sim/task": 25,
        "/camera/F/image": 25,
        "/camera/L/image": 25,
        "/camera/F/calibration": 2,
        "/camera/L/calibration": 2,
        "/camera/F/pose": 2,
        "/camera/L/pose": 2,
        "/recorder/episode": 1,
    }
    for topic, msgs in per_channel.items():
        assert [m.sequence for m, _ in msgs] == list(range(len(msgs))), topic
        log_times = [m.log_time for m, _ in msgs]
        pub_times = [m.publish_time for m, _ in msgs]
        assert log_times == sorted(log_times) and pub_times == sorted(pub_times), topic
    chunks = chunk_log_times(path)  # what `mcap doctor` checks: every chunk in log-time order
    assert sum(len(c) for c in chunks) == sum(counts.values()) and all(c == sorted(c) for c in chunks)
    for topic in ("/robot/state", "/camera/F/image", "/sim/task"):
        assert [m.publish_time for m, _ in per_channel[topic]] == src.stamps
        # receive time: after capture, inside the episode
        assert all(meta.start_ns <= m.log_time <= meta.end_ns for m, _ in per_channel[topic])
    # The calibration cached before START opens the file, ahead of any frame.
    assert per_channel["/camera/F/calibration"][0][0].log_time < meta.start_ns
    assert per_channel["/camera/F/calibration"][0][1].K == list(src.camera("F").calibration_msg(32, 24, 1).K)
    assert per_channel["/recorder/episode"][0][1].episode_id == "ep-0001"
    record = record_to_dict(metadata[EPISODE_RECORD])
    assert (record["task"], record["seed"], record["rig"], record["frames"], record["flags"]) == (
        "lift",
        3,
        "five15",
        {"F": 25, "L": 25},
        [],
    )

    ep = read_episode(path)
    assert ep.meta == meta and ep.metadata["ticks"] == 25
    assert isinstance(ep.messages("/camera/L/image")[0].msg, CompressedImage)
    assert status(pub).meta == meta  # idle STATUS reports the last episode


def test_control_queryable_answers_every_command_and_error(net, make_recorder, tmp_path):
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    out = tmp_path / "episodes"

    def err(reply: EpisodeReply, text: str) -> None:
        assert not reply.ok and text in reply.error, reply

    err(control(pub, EPISODE_COMMAND_STOP, episode_id="x"), "not recording")
    err(control(pub, EPISODE_COMMAND_DISCARD, episode_id="nope"), "unknown episode id 'nope'")
    err(start(pub, "../escape"), "invalid episode id")
    err(control(pub, 0), "unknown episode command")
    bad = EpisodeReply.FromString(pub.query(topics.EPISODE_CONTROL, b"\xff\xff\xff", timeout=15))
    err(bad, "malformed EpisodeRequest")
    assert not status(pub).recording

    assert start(pub, "a").ok
    err(start(pub, "b"), "already recording episode 'a'")
    err(control(pub, EPISODE_COMMAND_STOP, episode_id="b"), "unknown episode id 'b' (recording 'a')")
    live = status(pub)
    assert live.ok and live.recording and live.meta.episode_id == "a"
    assert (out / "a.mcap.part").is_file()
    discarded = control(pub, EPISODE_COMMAND_DISCARD, episode_id="a")
    assert discarded.ok and not discarded.recording and discarded.meta.episode_id == "a"
    assert [p.name for p in out.iterdir()] == [LOCK_FILE]  # nothing but the recorder's hold on the folder
    assert not status(pub).recording

    assert start(pub, "c").ok
    stopped = control(pub, EPISODE_COMMAND_STOP)  # no id: the current episode
    assert stopped.ok and stopped.meta.episode_id == "c" and (out / "c.mcap").is_file()
    err(start(pub, "c"), "already exists")
    assert control(pub, EPISODE_COMMAND_DISCARD, episode_id="c").ok  # a finished episode's file
    assert not (out / "c.mcap").exists()


def test_control_requests_of_another_type_or_with_absurd_values_are_refused(net, make_recorder, tmp_path):
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    # A sim RESET's bytes: parsed naively they read as an EpisodeRequest START.
    sim = SimControlRequest(command=SimCommand.SIM_COMMAND_RESET, task="lift", seed=5, episode_id="x")
    reply = EpisodeReply.FromString(pub.query(topics.EPISODE_CONTROL, sim.SerializeToString(), timeout=15))
    assert not reply.ok and "wrong schema" in reply.error and not status(pub).recording
    assert [p.name for p in (tmp_path / "episodes").iterdir()] == [LOCK_FILE]
    assert start(pub, "big").ok
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=10**9)
    assert not reply.ok and "ticks = 1000000000" in reply.error and status(pub).recording  # nothing stored
    assert control(pub, EPISODE_COMMAND_STOP, success=True, ticks=0).ok


def test_well_formed_wrong_messages_are_counted_per_reason_and_never_written(net, make_recorder):
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    src.publish_calibration()
    raw_state = pub.publisher(topics.ROBOT_STATE)
    raw_image = pub.publisher(topics.camera_image("F"))
    assert start(pub, "wrong-values").ok
    for i in range(10):
        src.tick(i)
        if i % 2 == 0:
            bad = RobotState(tick=i, eef_pos=[float("nan"), 0, 0.2], eef_quat_wxyz=[1, 0, 0, 0])
            bad.header.stamp_ns, bad.header.seq = src.t0 + i * PERIOD_NS, 1000 + i
            raw_state.put(bad.SerializeToString())
            other = RobotState(tick=i, eef_pos=[0.4, 0, 0.2], eef_quat_wxyz=[1, 0, 0, 0], episode_id="someone-else")
            other.header.stamp_ns = src.t0 + i * PERIOD_NS
            raw_state.put(other.SerializeToString())
            small = compressed_image(np.zeros((12, 16, 3), np.uint8), src.t0 + i * PERIOD_NS, "F")  # 32x24 calibrated
            raw_image.put(small.SerializeToString())
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=10)
    assert reply.ok, reply.error
    m = reply.meta
    assert dict(m.malformed_reasons) == {
        "robot/state: non-finite": 5,
        "robot/state: another episode": 5,
        "camera/F/image: wrong image size": 5,
    }
    assert dict(m.malformed) == {"robot/state": 10, "camera/F/image": 5}
    ep = read_episode(m.path)
    assert ep.metadata["malformed_reasons"] == dict(m.malformed_reasons)
    states = ep.messages("/robot/state")
    assert len(states) == 10 and all(np.isfinite(r.msg.eef_pos).all() and not r.msg.episode_id for r in states)
    assert {(r.msg.format, len(r.msg.data) > 0) for r in ep.messages("/camera/F/image")} == {("jpeg", True)}
    assert len(ep.messages("/camera/F/image")) == 10


def test_malformed_payloads_are_counted_and_no_good_message_is_lost(net, make_recorder):
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    raw_state = pub.publisher(topics.ROBOT_STATE)  # put() takes raw bytes too
    raw_image = pub.publisher(topics.camera_image("F"))
    good_img = compressed_image(src.frame, src.t0, "F")
    undecodable = CompressedImage(format="jpeg", data=b"\xff\xd8" + bytes(300) + b"\xff\xd9")
    undecodable.timestamp.FromNanoseconds(src.t0)
    half = CompressedImage(format="jpeg", data=encode_jpeg(src.frame)[:200])
    half.timestamp.FromNanoseconds(src.t0)

    assert start(pub, "bad-input").ok
    for i in range(12):
        src.tick(i)
        if i % 3 == 0:
            raw_state.put(good_img.SerializeToString())  # wrong schema
            raw_state.put(b"\x0a\x05\x08")  # truncated
            raw_image.put(undecodable.SerializeToString())
            raw_image.put(half.SerializeToString())
            raw_image.put(b"\x12\x04abc")  # truncated
    reply = control(pub, EPISODE_COMMAND_STOP, success=False, ticks=12)
    assert reply.ok, reply.error
    assert dict(reply.meta.malformed) == {"robot/state": 8, "camera/F/image": 12}
    assert (reply.meta.ticks, dict(reply.meta.frames)) == (12, {"F": 12})
    assert any(f.startswith("malformed payloads") for f in reply.meta.flags)
    assert not reply.meta.gaps  # the bad ones never reached the sequence check
    ep = read_episode(reply.meta.path)
    assert [r.msg.tick for r in ep.messages("/robot/state")] == list(range(12))
    assert [r.publish_time for r in ep.messages("/camera/F/image")] == src.stamps
    assert status(pub).ok  # still serving


def test_publisher_restart_flags_the_episode(net, make_recorder):
    make_recorder()
    watcher = net.client()
    watcher.wait_alive(["recorder"], timeout=10)
    assert start(watcher, "restart").ok

    with Bus(net.bus_config()) as first:
        first.announce("sim")
        src = Source(first, cameras=("F",))
        src.run(range(10))
        wait_for(lambda: status(watcher).meta.ticks == 10, what="first run recorded")
    wait_for(lambda: any("sim lost liveliness" in f for f in status(watcher).meta.flags), what="liveliness loss")

    with Bus(net.bus_config()) as second:
        second.announce("sim")
        again = Source(second, cameras=("F",))
        again.t0 = src.t0 + 10 * PERIOD_NS
        again.run(range(10))  # sequences restart at 0
        wait_for(lambda: status(watcher).meta.ticks == 20, what="second run recorded")
        reply = control(watcher, EPISODE_COMMAND_STOP, success=True, ticks=20)
    assert reply.ok, reply.error
    flags = list(reply.meta.flags)
    assert "service sim lost liveliness mid-episode" in flags
    assert "service sim restarted mid-episode" in flags
    assert "publisher restart on robot/state: sequence went back 1x" in flags
    assert reply.meta.gaps["robot/state"] == 1 and reply.meta.gaps["sim/task"] == 1
    assert dict(reply.meta.frames) == {"F": 20}
    assert len(read_episode(reply.meta.path).messages("/robot/state")) == 20
    assert status(watcher).ok


def test_a_slow_writer_with_tiny_queues_drops_and_counts(net, make_recorder):
    make_recorder(queue_size=2)
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    # Noise compresses badly: ~300 kB frames whose full decode keeps the writer far behind.
    src = Source(pub, cameras=("F",), shape=(480, 640), paced=False)
    assert start(pub, "flood").ok
    src.run(range(60))
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=60)
    assert reply.ok, reply.error
    meta = reply.meta
    dropped = meta.drops["camera/F/image"]
    assert dropped > 0 and meta.frames["F"] + dropped == 60
    assert meta.ticks == 60 and meta.drops["robot/state"] + len(read_episode(meta.path).messages("robot/state")) == 60
    assert any(f.startswith("drops: recorder queues overflowed") for f in meta.flags)
    # Drops at all mean the zenoh callback returned instead of waiting for room: with BLOCK
    # publishers, a blocking callback would have pushed back on the source and dropped nothing.
    assert len(read_episode(meta.path).messages("/camera/F/image")) == meta.frames["F"]


def test_an_episode_below_the_rate_floor_is_flagged(net, make_recorder):
    make_recorder(min_rate_fraction=0.9, stop_grace_s=0.2)  # 12 ticks never come: don't wait long
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    assert start(pub, "slow", control_hz=100.0).ok  # stamps are 50 Hz
    src.run(range(10))
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=12)
    assert reply.ok
    flags = list(reply.meta.flags)
    assert "low rate: robot state at 50.00 Hz < 0.9 x 100 Hz" in flags
    assert "robot/state: 10 states for 12 ticks" in flags and "camera F: 10 frames for 12 ticks" in flags


def test_a_publisher_whose_clock_is_off_the_recorders_is_flagged(net, make_recorder):
    """A camera host 300 ms ahead and a robot host 800 ms behind the recorder's clock (before:
    recorded without a word, and the dataset paired each state with a frame six ticks away)."""
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F", "L"))
    assert start(pub, "skewed").ok
    for i in range(10):
        stamp = src.tick(i, observe=False)  # applied actions and task state: on time
        state = RobotState(tick=i, eef_pos=[0.4, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0])
        state.header.stamp_ns, state.header.seq = stamp - 800_000_000, i
        src.state.put(state)
        src.images["F"].put(compressed_image(src.frame, stamp + 300_000_000, "F"))
        src.images["L"].put(compressed_image(src.frame, stamp - 800_000_000, "L"))  # a slow stream: latency
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=10)
    assert reply.ok, reply.error
    clock = [f for f in reply.meta.flags if f.startswith("clock:")]
    assert len(clock) == 2, list(reply.meta.flags)
    ahead = (
        r"clock: camera/F/image stamped up to (2\d\d|300) ms after the recorder received it: its "
        + "publisher's clock is ahead"
    )
    behind = r"clock: robot/state reached the recorder (8\d\d|9\d\d) ms after its capture stamp at the quickest: "
    assert re.match(ahead, clock[0]) and re.match(behind, clock[1]), clock


def test_stop_waits_for_the_last_ticks_applied_action(net, make_recorder):
    make_recorder()
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    assert start(pub, "late").ok
    src.run(range(9))
    src.tick(9, act=False)  # the last tick's state and frame are in; what it applied is not yet
    late = threading.Timer(0.5, lambda: src.tick(9, observe=False))
    late.start()
    t0 = time.monotonic()
    reply = control(pub, EPISODE_COMMAND_STOP, success=True, ticks=10)
    late.join()
    assert reply.ok and time.monotonic() - t0 >= 0.5, reply.error  # STOP waited for it
    assert reply.meta.ticks == 10 and list(reply.meta.flags) == []
    ep = read_episode(reply.meta.path)
    assert len(ep.messages("/robot/applied")) == len(ep.messages("/sim/task")) == len(ep.messages("/robot/state")) == 10


def test_an_episode_short_of_applied_actions_is_flagged(net, make_recorder):
    make_recorder(stop_grace_s=0.2)
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    assert start(pub, "short").ok
    src.run(range(7))
    src.tick(7, act=False)  # the source dies between its last observation and its action
    reply = control(pub, EPISODE_COMMAND_STOP, success=False, ticks=8)
    assert reply.ok and reply.meta.ticks == 8
    assert list(reply.meta.flags) == ["robot/applied: 7 applied actions for 8 ticks"]


def test_a_stop_that_says_interrupted_flags_the_episode(net, make_recorder):
    make_recorder(stop_grace_s=0.2)
    pub = net.client()
    pub.wait_alive(["recorder"], timeout=10)
    src = Source(pub, cameras=("F",))
    assert start(pub, "cut").ok
    src.run(range(5))
    reply = control(pub, EPISODE_COMMAND_STOP, success=False, ticks=5, interrupted="SIGTERM to the session")
    assert reply.ok and not reply.meta.success
    assert list(reply.meta.flags) == ["interrupted: SIGTERM to the session"]


def test_shutdown_closes_the_open_episode_as_interrupted(net, tmp_path):
    cfg = RecorderConfig(bus=net.bus_config(), out_dir=tmp_path / "episodes")
    pub = net.client()
    with Bus(cfg.bus) as bus, Recorder(cfg, bus):
        pub.wait_alive(["recorder"], timeout=10)
        assert start(pub, "cut").ok
        Source(pub, cameras=("F",)).run(range(5))
        wait_for(lambda: status(pub).meta.ticks == 5, what="ticks recorded")
    assert not (tmp_path / "episodes" / "cut.mcap.part").exists()
    ep = read_episode(tmp_path / "episodes" / "cut.mcap")
    assert any(f.startswith("interrupted") for f in ep.flags) and ep.metadata["frames"] == {"F": 5}


def test_a_second_recorder_on_the_same_folder_is_refused(net, make_recorder, tmp_path):
    """(two sessions on one --out: the second one's recorder took the first one's episode ids, and
    warned about its open .part as left over from a crash)"""
    from services.core.runtime import OutputError

    make_recorder()  # holds tmp_path / "episodes"
    # (on a bus of its own: on the same bus, the bus check below refuses it first)
    own_bus = net.bus_config().model_copy(update={"namespace": "second"})
    cfg = RecorderConfig(bus=own_bus, out_dir=tmp_path / "episodes")
    with Bus(cfg.bus) as bus:
        with pytest.raises(OutputError, match=r"episodes is in use by another recorder \(pid \d+"):
            Recorder(cfg, bus).__enter__()
    # another folder is fine, and a folder whose recorder closed is free again, its lock file gone
    other = RecorderConfig(bus=own_bus, out_dir=tmp_path / "other")
    with Bus(other.bus) as bus:
        with Recorder(other, bus):
            assert (tmp_path / "other" / LOCK_FILE).exists()
        assert not (tmp_path / "other" / LOCK_FILE).exists()
        with Recorder(other, bus):
            pass


def test_a_second_recorder_on_the_same_bus_is_refused(net, make_recorder, tmp_path):
    """(both answered every episode request and recorded every episode, each into its own folder:
    `viewscale episode start` showed one's reply, `stop` the other's)"""
    from services.core.config import ConfigError

    make_recorder()
    cfg = RecorderConfig(bus=net.bus_config(), out_dir=tmp_path / "elsewhere")
    with Bus(cfg.bus) as bus:
        with pytest.raises(
            ConfigError, match=r"^another recorder is on this bus \(namespace 'vs'\): both would record every"
        ):
            Recorder(cfg, bus).__enter__()
    assert not (tmp_path / "elsewhere").exists()  # refused before its folder is made
