"""Faults during a live collection session: garbage on every topic, a sim killed mid-episode."""

from __future__ import annotations

import threading
import time

import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from services.core import topics
from services.core.bus import Bus
from services.core.success import SuccessWatch
from services.pb.episode_pb2 import (
    EpisodeCommand,
    EpisodeReply,
    EpisodeRequest,
    SimCommand,
    SimControlReply,
    SimControlRequest,
)
from services.pb.sensors_pb2 import RobotState, TaskState
from services.recorder.reader import read_episode
from services.session.collect import LocalStack

RIG = ["F", "FL", "FR"]


@pytest.fixture
def stack(tmp_path):
    overrides = {"sim": ["rig=three15", "realtime=false"], "recorder": [f"out_dir={tmp_path}"], "teleop": []}
    with LocalStack(tmp_path, None, overrides) as s:
        yield s


def sim(bus: Bus, command, **kw) -> SimControlReply:
    reply = SimControlReply.FromString(
        bus.query(topics.SIM_CONTROL, SimControlRequest(command=command, **kw).SerializeToString(), 30)
    )
    assert reply.ok, reply.error
    return reply


def recorder(bus: Bus, command, **kw) -> EpisodeReply:
    reply = EpisodeReply.FromString(
        bus.query(topics.EPISODE_CONTROL, EpisodeRequest(command=command, **kw).SerializeToString(), 60)
    )
    assert reply.ok, reply.error
    return reply


def start_episode(bus: Bus, episode_id: str, seed: int, **run) -> None:
    """Reset the sim, open the recording, start ticking: what a session does per episode."""
    sim(bus, SimCommand.SIM_COMMAND_RESET, task="lift", seed=seed, episode_id=episode_id)
    recorder(
        bus,
        EpisodeCommand.EPISODE_COMMAND_START,
        episode_id=episode_id,
        task="lift",
        seed=seed,
        rig="three15",
        control_hz=20,
    )
    sim(bus, SimCommand.SIM_COMMAND_RUN, **run)


def wait_for_tick(bus: Bus, episode_id: str, tick: int, until_success: bool = False) -> None:
    cv = threading.Condition()
    seen = {"tick": -1, "success": False}

    def on_task(msg: TaskState, _rx):
        if msg.episode_id == episode_id:
            with cv:
                seen["tick"], seen["success"] = msg.tick, msg.success
                cv.notify_all()

    bus.subscribe(topics.TASK_STATE, on_task)
    with cv:
        ok = cv.wait_for(lambda: seen["tick"] >= tick and (seen["success"] or not until_success), timeout=120)
    assert ok, f"episode {episode_id} stuck at tick {seen['tick']}"


def test_garbage_on_every_topic_is_counted_and_loses_no_good_data(stack):
    with Bus(stack.bus_config()) as bus:
        bus.wait_alive(["sim", "teleop", "recorder"], timeout=60)
        start_episode(bus, "garbage", seed=3)
        wait_for_tick(bus, "garbage", 3)
        raw = {t.key: bus.session.declare_publisher(bus.key(t.key)) for t in topics.session_topics(RIG)}
        bad_jpeg = CompressedImage(frame_id="F", format="jpeg", data=b"\xff\xd8 not really a jpeg").SerializeToString()
        wrong_schema = RobotState(eef_pos=[1, 2]).SerializeToString()
        for key, pub in raw.items():
            pub.put(b"\x0a\xff\xff\xff\xff")  # truncated length-delimited field
            pub.put(wrong_schema if "image" not in key else bad_jpeg)
        bad_sim = SimControlReply.FromString(bus.query(topics.SIM_CONTROL, b"\xff\xff", 10))
        assert not bad_sim.ok and "malformed" in bad_sim.error
        bad_req = EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, b"\xff\xff", 10))
        assert not bad_req.ok
        wait_for_tick(bus, "garbage", 4, until_success=True)
        ticks = sim(bus, SimCommand.SIM_COMMAND_PAUSE).ticks
        meta = recorder(bus, EpisodeCommand.EPISODE_COMMAND_STOP, episode_id="garbage", success=True, ticks=ticks).meta
    stack.check_alive()  # nothing crashed
    ep = read_episode(meta.path)
    assert meta.malformed.get("/camera/F/image", meta.malformed.get("camera/F/image", 0)) >= 1
    assert sum(meta.malformed.values()) >= len(topics.session_topics(RIG))
    for name in RIG:  # every good frame is there
        assert len(ep.messages(f"/camera/{name}/image")) == ticks
    assert [r.msg.tick for r in ep.messages("/robot/state")] == list(range(ticks))
    assert not any(r.msg.stale for r in ep.messages("/robot/applied")), "a bad command displaced a good one"
    assert "malformed payload on teleop/command" in (stack.log_dir / "sim.log").read_text()
    assert "robot/state" in (stack.log_dir / "teleop.log").read_text()


def test_sim_killed_mid_episode_flags_it_and_the_recorder_carries_on(stack):
    with Bus(stack.bus_config()) as bus:
        bus.wait_alive(["sim", "teleop", "recorder"], timeout=60)
        start_episode(bus, "crash", seed=5)
        wait_for_tick(bus, "crash", 5)
        stack.restart("sim")  # SIGKILL, then a fresh sim process
        bus.wait_alive(["sim"], timeout=60)
        sim(bus, SimCommand.SIM_COMMAND_RESET, task="lift", seed=5, episode_id="crash")
        sim(bus, SimCommand.SIM_COMMAND_RUN)
        wait_for_tick(bus, "crash", 3)
        sim(bus, SimCommand.SIM_COMMAND_PAUSE)
        meta = recorder(bus, EpisodeCommand.EPISODE_COMMAND_STOP, episode_id="crash", success=False).meta
        assert meta.flags, "a sim restart mid-episode must flag the episode"
        assert any("sim" in f for f in meta.flags), list(meta.flags)
        # The recorder is still fully usable for the next episode.
        start_episode(bus, "after", seed=6)
        wait_for_tick(bus, "after", 3, until_success=True)
        ticks = sim(bus, SimCommand.SIM_COMMAND_PAUSE).ticks
        after = recorder(bus, EpisodeCommand.EPISODE_COMMAND_STOP, episode_id="after", success=True, ticks=ticks).meta
    stack.check_alive()
    assert read_episode(meta.path).metadata["flags"]
    assert after.frames["F"] == ticks and not after.flags


def test_a_run_with_a_tick_limit_stops_the_sim_exactly_there(stack):
    """A late PAUSE (a busy machine, a slow session) must not stretch an episode past its limit."""
    with Bus(stack.bus_config()) as bus:
        bus.wait_alive(["sim", "teleop", "recorder"], timeout=60)
        seen: list[int] = []
        last = threading.Event()

        def on_task(msg: TaskState, _rx) -> None:
            if msg.episode_id == "limit":
                seen.append(msg.tick)
                if msg.tick == 5:
                    last.set()

        bus.subscribe(topics.TASK_STATE, on_task)
        sim(bus, SimCommand.SIM_COMMAND_RESET, task="lift", seed=7, episode_id="limit")
        recorder(bus, EpisodeCommand.EPISODE_COMMAND_START, episode_id="limit", task="lift", seed=7, rig="three15")
        assert sim(bus, SimCommand.SIM_COMMAND_RUN, max_ticks=6).ticks == 0
        assert last.wait(timeout=120), f"the sim stopped short of its limit: ticks {seen}"
        time.sleep(1.0)  # in lockstep the sim would tick on meanwhile
        assert sim(bus, SimCommand.SIM_COMMAND_RUN, max_ticks=6).ticks == 6  # at its limit: stays paused
        ticks = sim(bus, SimCommand.SIM_COMMAND_PAUSE).ticks
        meta = recorder(bus, EpisodeCommand.EPISODE_COMMAND_STOP, episode_id="limit", success=False, ticks=ticks).meta
    assert ticks == 6 and seen == list(range(6))
    ep = read_episode(meta.path)
    assert len(ep.messages("/robot/state")) == len(ep.messages("/robot/applied")) == len(ep.messages("/sim/task")) == 6
    assert not any(r.msg.stale for r in ep.messages("/robot/applied")) and list(meta.flags) == []


def test_a_run_with_settle_ticks_stops_the_sim_once_success_has_held(stack):
    """The session's success rule applied by the sim itself: a demo ends at the same tick however
    late the session's PAUSE comes, and a RUN with no limits keeps the ones the episode has."""
    with Bus(stack.bus_config()) as bus:
        bus.wait_alive(["sim", "teleop", "recorder"], timeout=60)
        seen: list[tuple[int, bool]] = []

        def on_task(msg: TaskState, _rx) -> None:
            if msg.episode_id == "settle":
                seen.append((msg.tick, msg.success))

        bus.subscribe(topics.TASK_STATE, on_task)
        start_episode(bus, "settle", seed=4, max_ticks=200, settle_ticks=3)
        watch = SuccessWatch(3)
        deadline = time.monotonic() + 120
        while not watch.held and time.monotonic() < deadline:
            for tick, ok in seen[watch.tick + 1 :]:
                watch.update(tick, ok)
            time.sleep(0.01)
        assert watch.held, f"the expert did not succeed: {seen[-5:]}"
        time.sleep(1.0)  # in lockstep the sim would tick on meanwhile
        assert sim(bus, SimCommand.SIM_COMMAND_RUN).ticks == watch.tick + 1  # done: stays paused
        paused = sim(bus, SimCommand.SIM_COMMAND_PAUSE)
        meta = recorder(
            bus, EpisodeCommand.EPISODE_COMMAND_STOP, episode_id="settle", success=True, ticks=paused.ticks
        ).meta
    assert watch.tick == watch.since + 3 and paused.ticks == watch.tick + 1 == len(seen)  # not one tick more
    assert paused.success and meta.ticks == paused.ticks and list(meta.flags) == []
