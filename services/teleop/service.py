"""The teleop service: answers every RobotState tick with an EefCommand for the same tick.

The zenoh callbacks only store the newest state (a teleop that falls behind skips to the
present rather than answering old ticks), the task states by tick, and the last frames of the
cameras the driver looks at; a worker thread does the thinking. A driver gets, with each state,
each of its cameras' newest frame captured at or before the state (waiting up to
``frame_wait_s`` for one that new: the sim publishes a tick's frames just before its state).
Malformed payloads are counted and logged, never fatal.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict, deque

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from services.core import topics
from services.core.bus import Bus, Received
from services.core.clock import now_ns
from services.core.robot_types import action_msg
from services.core.runtime import refuse_rivals, serve
from services.core.throttle import Throttle
from services.core.validation import Invalid, check
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import EefCommand
from services.pb.sensors_pb2 import RobotState, TaskState
from services.teleop.base import CameraFrame, TeleopDriver
from services.teleop.config import TELEOP_DRIVERS, TeleopConfig

log = logging.getLogger(__name__)


def make_driver(cfg: TeleopConfig) -> TeleopDriver:
    return TELEOP_DRIVERS.build(cfg.driver)


class TeleopService:
    def __init__(self, cfg: TeleopConfig, bus: Bus, driver: TeleopDriver):
        self.cfg = cfg
        self.bus = bus
        self.driver = driver
        self.malformed = Counter()
        self.errors = 0
        self.commands = 0
        self._cv = threading.Condition()
        self._state: RobotState | None = None
        self._tasks: OrderedDict[tuple[str, int], TaskState] = OrderedDict()
        self._episode: str | None = None
        self._seq = 0
        self._pub = bus.publisher(topics.COMMAND)
        bus.subscribe(topics.ROBOT_STATE, self._on_state, on_error=self._on_malformed)
        if driver.needs_task_state:
            bus.subscribe(topics.TASK_STATE, self._on_task, on_error=self._on_malformed)
        self._frames: dict[str, deque[CameraFrame]] = {c: deque(maxlen=8) for c in driver.cameras}
        self._frame_rx: dict[str, int] = {}  # camera -> when its newest frame arrived (ns)
        self._failed = Throttle(log, every_s=1.0)  # a failure repeated every tick: logged once a second, counted
        for cam in driver.cameras:
            bus.subscribe(topics.camera_image(cam), self._on_frame, on_error=self._on_malformed)
        driver.attach(bus)

    def __enter__(self) -> TeleopService:
        refuse_rivals(self.bus, "teleop", {"teleop"})  # (before: both answered every tick)
        self.bus.announce("teleop")
        return self

    def __exit__(self, *exc) -> None:
        self.driver.close()

    def _on_malformed(self, rx: Received, exc: Exception) -> None:
        self.malformed[rx.key] += 1
        log.warning("malformed payload on %s (%d bytes): %s", rx.key, len(rx.payload), exc)

    def _on_state(self, msg: RobotState, rx: Received) -> None:
        try:
            check(msg)  # another schema's payload can parse as a RobotState; it must not drive the arm
        except Invalid as exc:
            self._on_malformed(rx, exc)
            return
        with self._cv:
            self._state = msg
            self._cv.notify_all()

    def _on_task(self, msg: TaskState, rx: Received) -> None:
        try:
            check(msg)
        except Invalid as exc:
            self._on_malformed(rx, exc)
            return
        with self._cv:
            self._tasks[(msg.episode_id, msg.tick)] = msg
            while len(self._tasks) > 64:
                self._tasks.popitem(last=False)
            self._cv.notify_all()

    def _on_frame(self, msg: CompressedImage, rx: Received) -> None:
        name = rx.key.split("/")[1]
        if name not in self._frames or not msg.data:
            return
        with self._cv:
            self._frames[name].append(CameraFrame(bytes(msg.data), msg.timestamp.ToNanoseconds()))
            self._frame_rx[name] = rx.receive_ns
            self._cv.notify_all()

    def _frames_for(self, stamp_ns: int) -> dict[str, CameraFrame]:
        """Each camera's newest frame at or before ``stamp_ns`` (its newest at all if none is that old)."""
        out = {}
        for name, q in self._frames.items():
            older = [f for f in q if f.stamp_ns <= stamp_ns]
            if older or q:
                out[name] = older[-1] if older else q[0]
        return out

    def _next(self, stop: threading.Event) -> tuple[RobotState, TaskState | None, dict[str, CameraFrame]] | None:
        with self._cv:
            while self._state is None:
                if stop.is_set():
                    return None
                self._cv.wait(0.1)
            state, self._state = self._state, None
            stamp = state.header.stamp_ns
            deadline = time.monotonic() + max(self.cfg.task_state_wait_s, self.cfg.frame_wait_s)
            key = (state.episode_id, state.tick)

            def ready() -> bool:
                if self.driver.needs_task_state and key not in self._tasks:
                    return False
                return all(q and q[-1].stamp_ns >= stamp for q in self._frames.values())

            while not ready() and (remaining := deadline - time.monotonic()) > 0:
                self._cv.wait(remaining)
            return state, self._tasks.get(key), self._frames_for(stamp)

    def _check_frames_arrive(self) -> None:
        """ValueError naming each camera that sent nothing for ``max_frame_gap_s``: its newest frame
        is older every tick (unplugged, its service gone), and a policy would drive on it blind."""
        now = now_ns()
        with self._cv:
            gaps = {c: (now - self._frame_rx[c]) / 1e9 for c in self.driver.cameras if c in self._frame_rx}
        stalled = [f"{c} for {gap:.1f} s" for c, gap in gaps.items() if gap > self.cfg.max_frame_gap_s]
        if stalled:
            raise ValueError(
                f"no new frame from camera {', '.join(stalled)} (stalled, unplugged, or its service gone?): "
                "no command until it sends again"
            )

    def run(self, stop: threading.Event) -> None:
        def interrupt() -> None:  # (a lockstep policy waits for its chunk: not past the stop)
            stop.wait()
            self.driver.interrupt()

        threading.Thread(target=interrupt, name="teleop-interrupt", daemon=True).start()
        while not stop.is_set():
            item = self._next(stop)
            if item is None:
                break
            state, task, frames = item
            try:
                if state.episode_id != self._episode:
                    self.driver.reset(task.task if task is not None else "", state.episode_id)
                    self._episode = state.episode_id  # once the reset worked: a failed one is tried again
                missing = [c for c in self.driver.cameras if c not in frames]
                if missing:
                    raise ValueError(f"no frame from camera {', '.join(missing)} yet")
                self._check_frames_arrive()
                delta = self.driver.act(state, task, frames)
            except Exception as exc:  # no command: the robot holds still and flags the tick stale
                self.errors += 1
                self._failed(logging.WARNING, f"teleop driver failed at tick {state.tick} of {state.episode_id}: {exc}")
                continue
            self._seq += 1
            self._pub.put(
                EefCommand(
                    header=Header(stamp_ns=now_ns(), seq=self._seq, frame_id=topics.WORLD_FRAME),
                    tick=state.tick,
                    action=action_msg(delta),
                    source=self.cfg.driver.type,
                )
            )
            self.commands += 1
        log.info(
            "teleop stopped after %d commands (%d errors, %d malformed)",
            self.commands,
            self.errors,
            sum(self.malformed.values()),
        )


def main(cfg: TeleopConfig) -> int:
    driver = make_driver(cfg)  # a driver that cannot be built fails before the bus is opened
    return serve("teleop", cfg.bus, lambda bus: TeleopService(cfg, bus, driver), cfg.driver.type)
