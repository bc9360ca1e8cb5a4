"""The recorder's episode rules on their own: counters and flags from hand-made messages."""

from __future__ import annotations

import pytest

from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefCommand
from services.pb.episode_pb2 import EpisodeRequest
from services.pb.sensors_pb2 import RobotState
from services.recorder.episode import EpisodeCounts, episode_meta

T0 = 1_700_000_000_000_000_000
PERIOD = 50_000_000  # 20 Hz


def opened(control_hz: float = 20.0, lockstep: bool = False) -> EpisodeCounts:
    req = EpisodeRequest(episode_id="e1", task="lift", seed=4, rig="five15", control_hz=control_hz, lockstep=lockstep)
    return EpisodeCounts.start(req, "/data/e1.mcap", T0)


def feed(ep: EpisodeCounts, ticks, period=PERIOD, cameras=("F",), stale=(), clipped=(), seq=None):
    for k in ticks:
        s = k if seq is None else seq(k)
        stamp = T0 + k * period
        ep.count("robot/state", RobotState(header=Header(stamp_ns=stamp, seq=s), tick=k), stamp)
        applied = AppliedAction(
            header=Header(stamp_ns=stamp, seq=s), tick=k, stale=k in stale, limits=["speed"] if k in clipped else []
        )
        ep.count("robot/applied", applied, stamp)
        for c in cameras:
            ep.count(f"camera/{c}/image", object(), stamp)


def meta(ep, ticks=0, drops=None, fraction=0.9):
    return episode_meta(
        ep, drops=drops or {}, ticks=ticks, success=True, end_ns=T0 + 10**10, min_rate_fraction=fraction
    )


def test_a_clean_episode_has_no_flags_and_its_counts():
    ep = opened()
    feed(ep, range(30), cameras=("F", "FL"))
    m = meta(ep, ticks=30)
    assert list(m.flags) == []
    assert (m.ticks, dict(m.frames), m.stale_ticks, m.clipped_ticks) == (30, {"F": 30, "FL": 30}, 0, 0)
    assert m.achieved_hz == pytest.approx(20.0) and m.episode_id == "e1" and m.path == "/data/e1.mcap"
    assert m.success and m.start_ns == T0


def test_low_rate_is_flagged_below_the_fraction():
    ep = opened()
    feed(ep, range(10), period=2 * PERIOD)  # 10 Hz for a 20 Hz loop
    assert list(meta(ep, ticks=10).flags) == ["low rate: robot state at 10.00 Hz < 0.9 x 20 Hz"]
    assert list(meta(ep, ticks=10, fraction=0.4).flags) == []


def test_a_lockstep_episode_is_never_rate_flagged():
    # --fast: the sim ticks as fast as the teleop answers; its rate is the machine's, not a fault.
    ep = opened(lockstep=True)
    feed(ep, range(10), period=4 * PERIOD)  # 5 Hz
    m = meta(ep, ticks=10)
    assert m.lockstep and list(m.flags) == []


def test_stale_and_clipped_ticks_are_counted_and_flagged():
    ep = opened()
    feed(ep, range(20), stale={3, 4}, clipped={7})
    m = meta(ep, ticks=20)
    assert (m.stale_ticks, m.clipped_ticks) == (2, 1)
    assert list(m.flags) == [
        "stale: 2 ticks held still without a fresh command (teleop late or missing)",
        "clipped: 1 ticks limited by the safety layer (speed, workspace or gripper range)",
    ]


def test_robot_fault_ticks_are_counted_per_fault_and_flagged_before_stale_ones():
    ep = opened()
    for k, fault in enumerate(["", "protective stop", "protective stop", "connection lost", ""]):
        ep.count("robot/state", RobotState(header=Header(seq=k), tick=k), T0 + k * PERIOD)
        ep.count("robot/applied", AppliedAction(header=Header(seq=k), tick=k, stale=k == 3, fault=fault), 0)
    assert list(meta(ep, ticks=5).flags) == [
        "robot fault: 3 ticks the arm was stopped: protective stop (2 ticks); connection lost (1 ticks)",
        "stale: 1 ticks held still without a fresh command (teleop late or missing)",
    ]


def test_gaps_are_upstream_losses_unless_our_queues_dropped_them():
    ep = opened()
    feed(ep, [k for k in range(20) if k not in (5, 6)])  # seq 5 and 6 never arrive
    m = meta(ep, ticks=20)
    assert dict(m.gaps) == {"robot/state": 1, "robot/applied": 1}
    assert "sequence gaps: messages lost upstream (robot/applied 2, robot/state 2)" in m.flags
    assert "robot/state: 18 states for 20 ticks" in m.flags and "camera F: 18 frames for 20 ticks" in m.flags
    dropped = meta(ep, ticks=20, drops={"robot/state": 2, "robot/applied": 2, "camera/F/image": 0})
    assert not any(f.startswith("sequence gaps") for f in dropped.flags)
    assert "drops: recorder queues overflowed (robot/applied 2, robot/state 2)" in dropped.flags
    assert dict(dropped.drops) == {"robot/state": 2, "robot/applied": 2}


def test_a_sequence_going_back_is_a_publisher_restart():
    ep = opened()
    assert ep.count("robot/state", RobotState(header=Header(seq=10)), T0) is None
    assert ep.count("robot/state", RobotState(header=Header(seq=1)), T0 + PERIOD) == 10
    assert "publisher restart on robot/state: sequence went back 1x" in meta(ep).flags


def test_events_come_first_in_order_and_once():
    ep = opened()
    ep.service_left("teleop")
    assert ep.service_back("teleop") and not ep.service_back("sim")
    ep.note("write failed on robot/state: disk full")
    ep.service_left("teleop")
    assert list(meta(ep).flags)[:3] == [
        "service teleop lost liveliness mid-episode",
        "service teleop restarted mid-episode",
        "write failed on robot/state: disk full",
    ]
    ep.malformed["camera/F/image"] += 3
    assert "malformed payloads (camera/F/image 3)" in meta(ep).flags


def test_the_drivers_whose_commands_it_holds_are_named_once_each():
    ep = opened()
    feed(ep, range(3))
    assert list(meta(ep).command_sources) == []
    for k, source in enumerate(["spacemouse", "policy", "policy", ""]):
        ep.count("teleop/command", EefCommand(tick=k, source=source), T0 + k * PERIOD)
    assert list(meta(ep).command_sources) == ["policy", "spacemouse"]


def test_clock_flags_take_the_quickest_delivery_per_topic():
    ep = opened()
    for k in range(5):
        t = T0 + k * PERIOD
        ep.count("robot/state", RobotState(header=Header(stamp_ns=t, seq=k), tick=k), t, t + 2_000_000)
        # a camera stamped at capture, 120-900 ms before it arrives (an RTSP stream's latency): no clock fault
        ep.count("camera/F/image", object(), t, t + 120_000_000 + k * 200_000_000)
        ep.count("camera/F/calibration", object(), t - 10**10, t)  # a republished copy: not checked
    assert [f for f in meta(ep, ticks=5).flags if f.startswith("clock")] == []
    ahead = opened()
    t = T0
    ahead.count("camera/F/image", object(), t + 25_000_000, t)  # 25 ms ahead: beyond synchronised clocks
    ahead.count("camera/F/image", object(), t + 50, t + 10_000_000)
    ahead.count("robot/state", RobotState(header=Header(stamp_ns=t, seq=0)), t - 600_000_000, t)  # behind
    ahead.count("robot/state", RobotState(header=Header(stamp_ns=t, seq=1)), t - 700_000_000, t)
    flags = [f for f in meta(ahead).flags if f.startswith("clock")]
    assert [f.split(":")[1].split(" ms")[0] for f in flags] == [
        " camera/F/image stamped up to 25",
        " robot/state reached the recorder 600",
    ]


def test_an_episode_without_robot_states_is_flagged_empty_not_slow():
    ep = opened()
    ep.count("camera/F/image", object(), T0, T0 + 1_000_000)
    assert list(meta(ep).flags) == [
        "empty: no robot/state recorded (no robot service or sim publishing it on this bus?)",
        "camera F: 1 frames for 0 ticks",
    ]
