"""The sim service: a MuJoCo world speaking exactly the hardware topics.

It runs the robot service's control loop over a simulated arm, with the rig's simulated
cameras as observers, so each tick publishes JPEG frames for every camera, the robot state,
and -- sim only -- the privileged task state for scripted experts. Calibration and camera poses
go out at start-up, on every reset, and every ``calibration_period_s``.

Episode control is the queryable ``sim/control`` (SimControlRequest): RESET loads a task and
seed without ticking, RUN starts ticking (up to its ``max_ticks`` or until the task's success has
held ``settle_ticks``, where the loop pauses by itself, so where an episode ends does not depend on
when a PAUSE lands), PAUSE finishes the current tick and stops. Requests
are executed on the loop's own thread between ticks, because the renderer's GL context
belongs to the thread that created it.
"""

from __future__ import annotations

import logging
import queue
import threading
from concurrent.futures import Future

from services.camera.publisher import CameraPublisher
from services.core import topics
from services.core.bus import Bus
from services.core.clock import Rate, now_ns
from services.core.config import ConfigError
from services.core.rig import load_rig
from services.core.runtime import refuse_rivals, serve
from services.core.success import SuccessWatch
from services.core.validation import Invalid, check_sim_request, decode_strict
from services.pb.common_pb2 import Header
from services.pb.episode_pb2 import SimCommand, SimControlReply, SimControlRequest
from services.pb.sensors_pb2 import ObjectPose, TaskState
from services.robot.loop import ControlLoop
from services.robot.safety import Safety
from sim.backends import SimCamera, SimRobot
from sim.config import SimConfig
from sim.scene import RenderError
from sim.world import TASKS, SimWorld

log = logging.getLogger(__name__)


def task_state_msg(world: SimWorld, tick: int, stamp_ns: int, seq: int, seed: int, episode_id: str) -> TaskState:
    """The privileged task state of ``world`` now (object poses, success)."""
    msg = TaskState(
        header=Header(stamp_ns=stamp_ns, seq=seq, frame_id=topics.WORLD_FRAME),
        tick=tick,
        task=world.task,
        seed=seed,
        episode_id=episode_id,
        success=bool(world.success()),
    )
    for name, pose in world.objects().items():
        msg.objects.append(
            ObjectPose(name=name, pos=[float(v) for v in pose.pos], quat_wxyz=[float(v) for v in pose.quat_wxyz])
        )
    return msg


class SimService:
    def __init__(self, cfg: SimConfig, bus: Bus):
        self.cfg = cfg
        self.bus = bus
        self.rig = load_rig(cfg.rig)
        self.world = SimWorld(cfg.task, self.rig, cfg.width, cfg.height, cfg.control_hz)
        self.world.reset(cfg.seed)
        self.seed = cfg.seed
        self.robot = SimRobot(self.world)
        self.camera = SimCamera(self.world, cfg.width, cfg.height)
        self.cameras = CameraPublisher(bus, self.camera, cfg.jpeg_quality)
        self._task_pub = bus.publisher(topics.TASK_STATE)
        self._task_seq = 0
        self.loop = ControlLoop(
            bus,
            Safety(self.robot, cfg.safety, cfg.control_hz),
            cfg.control_hz,
            cfg.realtime,
            cfg.command_timeout_s,
            cfg.command_wait_fraction,
            observers=[self._observe],
        )
        self.running = False
        # Set by RUN, cleared by RESET: the loop pauses itself at this tick count (0: no limit) or once
        # the task's success has held for the watch's settle ticks (None: it runs on).
        self.max_ticks = 0
        self.success: SuccessWatch | None = None
        self._jobs: queue.Queue[tuple[SimControlRequest, Future]] = queue.Queue()
        self._stop = threading.Event()
        self._calib_thread = threading.Thread(target=self._calibration_loop, name="calibration", daemon=True)
        bus.queryable(topics.SIM_CONTROL, self._on_control)

    # -- lifecycle ----------------------------------------------------------------------
    def __enter__(self) -> SimService:
        refuse_rivals(self.bus, "sim", {"sim", "robot", "camera"})  # (before: a sim on a lab's bus was taken)
        try:  # a frame now, on the thread that renders every tick: no GL, no start (before: the first
            self.world.render()  # tick raised, and a session waited for a sim that never answered)
        except RenderError as exc:
            raise ConfigError(str(exc)) from None
        self.cameras.publish_calibration(now_ns())
        self._calib_thread.start()
        self.bus.announce("sim")
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._calib_thread.join(timeout=2)
        self.world.close()

    def _calibration_loop(self) -> None:
        while not self._stop.wait(self.cfg.calibration_period_s):
            self.cameras.publish_calibration(now_ns())

    # -- per-tick observation (loop thread) ---------------------------------------------
    def _observe(self, tick: int, stamp_ns: int) -> None:
        self.cameras.publish_frames(self.camera.grab(stamp_ns))
        self._task_seq += 1
        msg = task_state_msg(self.world, tick, stamp_ns, self._task_seq, self.seed, self.loop.episode_id)
        if self.success is not None:
            self.success.update(tick, msg.success)
        self._task_pub.put(msg)

    # -- episode control ----------------------------------------------------------------
    def _on_control(self, payload: bytes) -> bytes:
        """Zenoh thread: hand the request to the loop thread and wait for its answer."""
        try:
            req = decode_strict(SimControlRequest, payload)  # another type's bytes leave unknown fields
            check_sim_request(req, TASKS)
        except Invalid as exc:  # answer, never raise into zenoh
            log.warning("refused a control request (%d bytes): %s", len(payload), str(exc))
            return SimControlReply(ok=False, error=f"malformed SimControlRequest: {exc}").SerializeToString()
        done: Future = Future()
        self._jobs.put((req, done))
        timeout = 10.0 + self.cfg.command_timeout_s + 2.0 / self.cfg.control_hz
        try:
            return done.result(timeout=timeout).SerializeToString()
        except TimeoutError:
            return SimControlReply(ok=False, error=f"sim did not answer within {timeout:.0f}s").SerializeToString()

    def _execute(self, req: SimControlRequest) -> SimControlReply:
        if req.command == SimCommand.SIM_COMMAND_RESET:
            if req.task and req.task not in TASKS:
                return SimControlReply(ok=False, error=f"unknown task {req.task!r}; tasks: {', '.join(TASKS)}")
            task = req.task or self.world.task
            if task != self.world.task:
                self._load(task)
            self.running = False
            self.max_ticks, self.success = 0, None
            self.world.reset(int(req.seed))
            self.seed = int(req.seed)
            self.loop.begin_episode(req.episode_id)
            self.cameras.publish_calibration(now_ns())
            log.info("reset task=%s seed=%d episode=%s", task, req.seed, req.episode_id)
            return SimControlReply(ok=True, ticks=0, success=bool(self.world.success()), lockstep=not self.cfg.realtime)
        if req.command == SimCommand.SIM_COMMAND_RUN:
            if req.HasField("max_ticks"):
                self.max_ticks = int(req.max_ticks)
            if req.HasField("settle_ticks") and (self.success is None or self.success.settle_ticks != req.settle_ticks):
                self.success = SuccessWatch(req.settle_ticks)  # watches from the next tick on
            self.running = not self._done()
            return SimControlReply(ok=True, ticks=self.loop.tick)
        if req.command == SimCommand.SIM_COMMAND_PAUSE:
            self.running = False
            return SimControlReply(ok=True, ticks=self.loop.tick, success=bool(self.world.success()))
        return SimControlReply(ok=False, error=f"unknown sim command {req.command}")

    def _done(self) -> bool:
        return 0 < self.max_ticks <= self.loop.tick or (self.success is not None and self.success.held)

    def _load(self, task: str) -> None:
        """Swap in a world for another task (the renderer must be created on this thread)."""
        old = self.world
        self.world = SimWorld(task, self.rig, self.cfg.width, self.cfg.height, self.cfg.control_hz)
        self.robot.world = self.world
        self.camera.world = self.world
        old.close()

    def _serve_jobs(self, wait: float) -> None:
        try:
            req, done = self._jobs.get(timeout=wait) if wait > 0 else self._jobs.get_nowait()
        except queue.Empty:
            return
        try:
            done.set_result(self._execute(req))
        except Exception as exc:
            log.exception("sim control request failed")
            done.set_result(SimControlReply(ok=False, error=f"{type(exc).__name__}: {exc}"))

    # -- the loop -----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        self.loop.release_on(stop)
        rate = Rate(self.cfg.control_hz)
        was_running = False
        while not stop.is_set():
            # Control requests run here, between ticks: PAUSE lands after a complete tick.
            self._serve_jobs(0 if self.running else 0.1)
            if not self.running:
                was_running = False
                continue
            if not was_running:
                rate.reset()
                was_running = True
            self.loop.step()
            if self._done():  # the episode's last tick is complete: no next observation
                self.running = False
                why = "its success held" if self.success is not None and self.success.held else "its tick limit"
                log.info("episode %s: paused after %d ticks at %s", self.loop.episode_id, self.loop.tick, why)
                continue
            if self.cfg.realtime:
                rate.sleep()
        log.info(
            "sim stopped at tick %d (%d stale ticks, %d rejected commands)",
            self.loop.tick,
            self.loop.stale_ticks,
            sum(self.loop.rejected.values()),
        )


def main(cfg: SimConfig) -> int:
    return serve("sim", cfg.bus, lambda bus: SimService(cfg, bus), f"{cfg.task}/{cfg.rig}/{cfg.width}x{cfg.height}")
