"""Fuzzing a real recording: malformed and well-formed-but-wrong payloads on every recorded topic and
garbage on every control key, from a seeded corpus, while the services record an episode."""

from __future__ import annotations

import math
import queue
import threading

import numpy as np
import pytest

from services.core import topics
from services.core.bus import Bus
from services.core.rig import load_rig
from services.core.tensors import compressed_image
from services.core.validation import Invalid, check, parse
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefAction, EefCommand
from services.pb.episode_pb2 import EpisodeReply, SimCommand, SimControlReply, SimControlRequest
from services.pb.sensors_pb2 import ObjectPose, RobotState, TaskState
from services.recorder.reader import read_episode
from services.session.collect import LocalStack
from services.session.config import SessionConfig
from services.session.session import Session

CAMERAS = ("F", "FL", "FR")
PER_TICK = 8  # payloads per topic per tick: a few hundred per topic over the fuzzed ticks
FUZZ_TICKS = range(2, 40)  # the can expert needs ~68 ticks: the fuzzing ends well before the episode


def corpus(rng: np.random.Generator, topic: topics.Topic, stamp: int) -> list[bytes]:
    """Payloads that must all be refused on ``topic``: garbage, other schemas, wrong values."""
    nan = math.nan
    h = Header(stamp_ns=stamp, seq=10**6)
    state = RobotState(header=h, tick=5, eef_pos=[0.4, 0, 0.2], eef_quat_wxyz=[0, 1, 0, 0], gripper=0.0)
    act = EefAction(dp=[0.01, 0, 0], drot=[0, 0, 0], gripper=0.0)
    img = compressed_image(np.zeros((84, 84, 3), np.uint8), stamp, "F")
    out = [bytes(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8)) for _ in range(3)]
    out.append(img.SerializeToString()[: int(rng.integers(5, 60))])  # truncated
    if topic.msg_type is RobotState:
        out += [
            RobotState(header=h, eef_pos=[nan, 0, 0], eef_quat_wxyz=[0, 1, 0, 0]).SerializeToString(),
            RobotState(header=h, eef_pos=[0.4, 0, 0.2], eef_quat_wxyz=[0, 3, 0, 0]).SerializeToString(),
            RobotState(
                header=h, eef_pos=[0.4, 0, 0.2], eef_quat_wxyz=[0, 1, 0, 0], episode_id="x" * 300
            ).SerializeToString(),
            img.SerializeToString(),
        ]
    elif topic.msg_type is AppliedAction:
        out += [
            AppliedAction(header=h, action=EefAction(dp=[nan, 0, 0], drot=[0, 0, 0])).SerializeToString(),
            AppliedAction(header=h, action=act, limits=["teleport"]).SerializeToString(),
        ]
    elif topic.msg_type is EefCommand:
        out += [
            EefCommand(header=h, tick=5, action=EefAction(dp=[5.0, 0, 0], drot=[0, 0, 0])).SerializeToString(),
            EefCommand(header=h, tick=5, action=EefAction(dp=[0, 0], drot=[0, 0, 0])).SerializeToString(),
            state.SerializeToString(),
        ]
    elif topic.msg_type is TaskState:
        out += [
            TaskState(
                header=h, task="can", objects=[ObjectPose(name="can", pos=[0, nan, 0], quat_wxyz=[1, 0, 0, 0])]
            ).SerializeToString(),
            TaskState(header=h, task="").SerializeToString(),
        ]
    elif topic.key.endswith("/image"):
        small = compressed_image(np.zeros((30, 40, 3), np.uint8), stamp, topic.key.split("/")[1])
        png = compressed_image(np.zeros((84, 84, 3), np.uint8), stamp, "F")
        png.format = "png"
        cut = compressed_image(np.zeros((84, 84, 3), np.uint8), stamp, "F")
        cut.data = cut.data[:100]
        out += [small.SerializeToString(), png.SerializeToString(), cut.SerializeToString(), state.SerializeToString()]
    elif topic.key.endswith("/calibration"):
        cal = load_rig("three15").cameras["F"].calibration_msg(84, 84, stamp)
        cal.K[0] = nan
        zero = load_rig("three15").cameras["F"].calibration_msg(0, 84, stamp)
        out += [cal.SerializeToString(), zero.SerializeToString()]
    elif topic.key.endswith("/pose"):
        pose = load_rig("three15").cameras["F"].pose_msg(stamp)
        pose.rotation.w = 5.0
        out += [pose.SerializeToString()]
    refused = []
    for p in out:
        try:
            parse(topic, p)
        except Invalid:
            refused.append(p)  # every payload is refused here, so the recorder's count must match
    return refused


def fuzz_topics() -> list[topics.Topic]:
    fixed = [topics.ROBOT_STATE, topics.APPLIED_ACTION, topics.COMMAND, topics.TASK_STATE]
    return fixed + [f(c) for c in CAMERAS for f in (topics.camera_image, topics.camera_calibration, topics.camera_pose)]


@pytest.mark.slow
def test_fuzzing_every_topic_during_a_recording(tmp_path):
    rng = np.random.default_rng(1234)
    sent: dict[str, int] = {}
    control_replies: list[bool] = []
    stack = LocalStack(
        tmp_path,
        None,
        {
            "sim": ["rig=three15", "task=can", "realtime=false"],
            "recorder": [f"out_dir={tmp_path / 'raw'}"],
            "teleop": [],
        },
    )
    cfg = SessionConfig(bus=stack.bus_config(), task="can", rig="three15", episodes=1, warmup_ticks=0)
    with stack, Bus(stack.bus_config()) as bus:
        pubs = {t.key: bus.publisher(t) for t in fuzz_topics()}
        ticks: queue.Queue = queue.Queue()
        done = threading.Event()
        fuzzed: list[int] = []
        errors: list[BaseException] = []

        def sim(command: SimCommand, **fields) -> None:
            reply = SimControlReply.FromString(
                bus.query(topics.SIM_CONTROL, SimControlRequest(command=command, **fields).SerializeToString(), 30)
            )
            assert reply.ok, reply.error

        def fuzz_tick(msg: TaskState) -> None:
            # The sim waits while this tick's payloads go out, so they all land inside the episode
            # however far behind a loaded machine puts this thread (in lockstep it would not wait).
            sim(SimCommand.SIM_COMMAND_PAUSE)
            for t in fuzz_topics():
                for p in corpus(rng, t, msg.header.stamp_ns)[:PER_TICK]:
                    pubs[t.key].put(p)
                    sent[t.key] = sent.get(t.key, 0) + 1
            for key, payload in (
                (topics.EPISODE_CONTROL, bytes(rng.integers(0, 256, 40, dtype=np.uint8))),
                (topics.SIM_CONTROL, SimControlRequest(command=9, task="x").SerializeToString()),
                # A sim RESET's bytes read as an EpisodeRequest with a field of the wrong wire type.
                (topics.EPISODE_CONTROL, SimControlRequest(command=1, task="lift", seed=5).SerializeToString()),
            ):
                raw = bus.query(key, payload, timeout=10)
                reply = (EpisodeReply if key == topics.EPISODE_CONTROL else SimControlReply).FromString(raw)
                control_replies.append(reply.ok)
            sim(SimCommand.SIM_COMMAND_RUN)  # with the limits the session's RUN set
            fuzzed.append(msg.tick)

        def fuzz() -> None:  # its own thread: a zenoh callback must not publish bursts or query
            while not done.is_set():
                try:
                    msg = ticks.get(timeout=0.1)
                except queue.Empty:
                    continue
                try:
                    fuzz_tick(msg)
                except BaseException as exc:  # reported by the test, not lost with the thread
                    errors.append(exc)
                    done.set()
                if msg.tick == FUZZ_TICKS[-1]:
                    done.set()

        def on_task(msg: TaskState, _rx) -> None:
            if msg.episode_id.startswith("can-") and msg.tick in FUZZ_TICKS:
                ticks.put(msg)

        fuzzer = threading.Thread(target=fuzz, daemon=True)
        fuzzer.start()
        bus.subscribe(topics.TASK_STATE, on_task)
        result = Session(cfg, bus, progress=lambda m: None).run()
        done.set()
        fuzzer.join(timeout=30)
        stack.check_alive()  # every service is still running
        assert bus.wait_alive({"sim", "teleop", "recorder"}, timeout=10) is None
    assert not errors, errors
    assert fuzzed == list(FUZZ_TICKS)  # every fuzzed tick inside the episode, before it ended
    assert len(control_replies) == 3 * len(FUZZ_TICKS) and not any(control_replies)  # every bad request refused
    assert result.recorded and result.attempts[0].success  # the expert still did its job
    ep = read_episode(result.recorded[0].meta.path)
    ticks = ep.metadata["ticks"]
    for cam in CAMERAS:
        assert len(ep.messages(f"/camera/{cam}/image")) == ticks == ep.metadata["frames"][cam]
    assert len(ep.messages("/robot/state")) == len(ep.messages("/robot/applied")) == ticks
    for records in ep.topics.values():  # no wrong message in the file
        for r in records:
            check(r.msg)
    assert sum(sent.values()) > 2000 and min(sent.values()) >= len(FUZZ_TICKS)
    assert dict(ep.metadata["malformed"]) == sent
