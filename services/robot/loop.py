"""The control loop every robot source runs, real or simulated.

One tick k:
  1. observe: read the driver; observers publish what belongs to tick k (camera frames, task
     state), then RobotState(tick=k) goes out last, so a teleop that reacts to the state finds
     the tick's other messages already sent;
  2. wait for the EefCommand answering tick k, until a deadline: in real time a fraction of
     the period from the tick's start, but never less than ``min_command_wait`` of a period
     after the state went out (slow rendering must not starve the teleop: a late tick beats
     a stale action); in lockstep ``command_timeout_s``;
  3. hand it to the safety layer (``services.robot.safety``), which executes it within the
     workspace and speed limits -- or holds still with the last gripper target if none came
     (flagged ``stale``), or sends nothing while the driver reports a fault (``fault``) -- and
     publish AppliedAction(tick=k): the action that really ran between state k and k+1, with
     the limits that changed it and the fault that stopped the arm.
So an episode always has exactly one applied action per observation, which is what
demonstrations are made of.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

from services.core import topics
from services.core.bus import Bus, Received
from services.core.clock import Rate, now_ns
from services.core.robot_types import EefDelta, action_from_msg, action_msg, state_msg
from services.core.throttle import Throttle
from services.core.validation import check
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefCommand
from services.robot.safety import Safety

log = logging.getLogger(__name__)

Observer = Callable[[int, int], None]  # (tick, capture stamp_ns)


class ControlLoop:
    def __init__(
        self,
        bus: Bus,
        robot: Safety,
        control_hz: float,
        realtime: bool = True,
        command_timeout_s: float = 0.5,
        command_wait_fraction: float = 0.8,
        observers: list[Observer] | None = None,
        min_command_wait: float = 0.25,
    ):
        self.robot = robot  # the driver behind the safety layer
        self.control_hz = control_hz
        self.realtime = realtime
        self.command_timeout_s = command_timeout_s
        self.command_wait_fraction = command_wait_fraction
        self.min_command_wait = min_command_wait
        self._tick_start = 0.0  # monotonic time the tick's observation began
        self._published_at = 0.0  # monotonic time the tick's state went out
        self.observers = list(observers or [])
        self.tick = 0
        self.episode_id = ""
        self.stale_ticks = 0
        self.clipped_ticks = 0  # ticks whose command the safety layer changed
        self.fault_ticks = 0  # ticks the arm could not move (a driver fault: protective stop, lost connection)
        self.rejected = Counter()  # reason -> count of commands we could not use
        self._say = Throttle(log)  # a rejected or malformed command every tick: not a line every tick
        self._seq = 0
        self._cv = threading.Condition()
        self._latest: tuple[int, EefDelta] | None = None  # (tick, validated action)
        self._released = False  # the service is stopping: no tick waits for a command any more
        self._state_pub = bus.publisher(topics.ROBOT_STATE)
        self._applied_pub = bus.publisher(topics.APPLIED_ACTION)
        bus.subscribe(topics.COMMAND, self._on_command, on_error=self._on_malformed)

    # -- commands (zenoh thread) --------------------------------------------------------
    def _on_command(self, msg: EefCommand, rx: Received) -> None:
        # Validate on arrival: a bad command (a payload of another schema can parse as an
        # EefCommand) is counted and dropped, and cannot displace the tick's good command.
        try:
            check(msg)  # the same checks as the recorder's: bounded steps, finite values, bounded strings
            delta = action_from_msg(msg.action)
        except ValueError as exc:
            self.rejected["invalid"] += 1
            # (before: a line per command, 20 a second from a teleop that sent such every tick)
            self._say(logging.WARNING, f"rejected command on {rx.key} for tick {msg.tick}: {exc}")
            return
        with self._cv:
            self._latest = (msg.tick, delta)
            self._cv.notify_all()

    def _on_malformed(self, rx: Received, exc: Exception) -> None:
        self.rejected["malformed"] += 1
        self._say(logging.WARNING, f"malformed payload on {rx.key} ({len(rx.payload)} bytes): {exc}")

    def _wait_command(self, tick: int, deadline: float) -> EefDelta | None:
        with self._cv:
            while True:
                if self._latest is not None and self._latest[0] == tick:
                    return self._latest[1]
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._released:
                    return None
                self._cv.wait(remaining)

    def release_on(self, stop: threading.Event) -> None:
        """Once ``stop`` is set, a tick waiting for its command holds at once instead of at its
        deadline: in lockstep that may be minutes away (``viewscale eval`` waits 120 s for a slow
        policy), and a service stopped mid-episode, its teleop gone, would wait it out (before: the
        session's 20 s for a stop, then SIGKILL)."""

        def release() -> None:
            stop.wait()
            with self._cv:
                self._released = True
                self._cv.notify_all()

        threading.Thread(target=release, name="release-on-stop", daemon=True).start()

    # -- one tick -----------------------------------------------------------------------
    def begin_episode(self, episode_id: str) -> None:
        self.tick = 0
        self.episode_id = episode_id
        self.stale_ticks = 0
        self.clipped_ticks = 0
        self.fault_ticks = 0
        self.robot.begin_episode()
        with self._cv:
            self._latest = None

    def step(self) -> None:
        """One whole tick: observe, then act."""
        self.observe()
        self.act()

    def observe(self) -> None:
        """Publish the tick's observation."""
        self._tick_start = time.monotonic()
        stamp = now_ns()
        snapshot = self.robot.read()
        for observer in self.observers:
            observer(self.tick, stamp)
        self._seq += 1
        self._state_pub.put(state_msg(snapshot, self.tick, stamp, self._seq, self.episode_id))
        self._published_at = time.monotonic()

    def act(self) -> None:
        """Wait for the tick's command, execute it (or hold), publish what ran."""
        if self.realtime:
            period = 1.0 / self.control_hz
            deadline = max(
                self._tick_start + self.command_wait_fraction * period,
                self._published_at + self.min_command_wait * period,
            )
        else:
            deadline = self._published_at + self.command_timeout_s
        ran = self.robot.apply(self._wait_command(self.tick, deadline))
        self.stale_ticks += ran.stale
        self.clipped_ticks += bool(ran.limits)
        self.fault_ticks += bool(ran.fault)
        self._applied_pub.put(
            AppliedAction(
                header=Header(stamp_ns=now_ns(), seq=self._seq, frame_id=topics.WORLD_FRAME),
                tick=self.tick,
                action=action_msg(ran.action),
                stale=ran.stale,
                limits=list(ran.limits),
                fault=ran.fault,
            )
        )
        self.tick += 1

    def run(self, stop: threading.Event) -> None:
        """Tick from now until ``stop`` (the standalone robot service's loop)."""
        self.release_on(stop)
        rate = Rate(self.control_hz)
        while not stop.is_set():
            self.step()
            if self.realtime:
                rate.sleep()
        log.info(
            "control loop stopped at tick %d (%d stale ticks, %d clipped, %d faulted)",
            self.tick,
            self.stale_ticks,
            self.clipped_ticks,
            self.fault_ticks,
        )
