"""The collection session: drives sim, teleop and recorder through N successful episodes.

Per attempt: sim RESET (task, seed) -> recorder START -> sim RUN, which pauses by itself at the
tick limit or once success has held for ``settle_ticks`` (the session's rule, so an episode's end
does not depend on when a request lands) -> watch the task state until the same -> sim PAUSE
(answers the tick count; observations == applied actions) -> recorder STOP with the tick count
on success, DISCARD on an expert failure (reported; the next seed is tried). Everything goes over
Zenoh queries; a service that disappears mid-episode stops the session with a clear error, and
the partial episode is kept, closed as failed and flagged, never deleted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from services.core import topics
from services.core.bus import Bus, Received
from services.core.config import ConfigError
from services.core.rig import load_rig
from services.core.success import SuccessWatch
from services.pb.episode_pb2 import (
    EpisodeCommand,
    EpisodeMeta,
    EpisodeReply,
    EpisodeRequest,
    SimCommand,
    SimControlReply,
    SimControlRequest,
)
from services.pb.sensors_pb2 import TaskState
from services.session.config import SessionConfig

log = logging.getLogger(__name__)


class SessionError(RuntimeError):
    pass


def rig_name(rig: str) -> str:
    """A rig preset's name, or the name a rig file gives (its stem by default)."""
    try:
        return load_rig(rig).name
    except ConfigError:  # not readable here (another host's path): its file name still names it
        return Path(rig).stem


@dataclass
class Attempt:
    seed: int
    episode_id: str
    success: bool
    ticks: int
    seconds: float
    meta: EpisodeMeta | None = None  # set for recorded episodes (successful ones; every one in evaluation)


@dataclass
class SessionResult:
    attempts: list[Attempt] = field(default_factory=list)

    @property
    def recorded(self) -> list[Attempt]:
        return [a for a in self.attempts if a.meta is not None]

    @property
    def failed(self) -> list[Attempt]:
        return [a for a in self.attempts if not a.success]


def describe(attempt: Attempt) -> str:
    if attempt.meta is None:
        return f"seed {attempt.seed}: expert failed after {attempt.ticks} ticks, discarded"
    if not attempt.success:
        m = attempt.meta
        return f"seed {attempt.seed}: FAILED after {attempt.ticks} ticks ({attempt.seconds:.1f} s) -> {m.path}"
    m = attempt.meta
    drops = sum(m.drops.values())
    flags = f" FLAGGED: {'; '.join(m.flags)}" if m.flags else ""
    return (
        f"seed {attempt.seed}: success in {attempt.ticks} ticks ({attempt.seconds:.1f} s, "
        f"{m.achieved_hz:.1f} Hz, {drops} drops) -> {m.path}{flags}"
    )


class Session:
    def __init__(self, cfg: SessionConfig, bus: Bus, progress: Callable[[str], None] = print):
        self.cfg = cfg
        self.bus = bus
        self.progress = progress
        self.rig = rig_name(cfg.rig)  # recorded with each episode and part of its id (a path would not do)
        self._cv = threading.Condition()
        self._episode = ""
        self._success = SuccessWatch(cfg.settle_ticks)
        self._lost: set[str] = set()
        bus.subscribe(topics.TASK_STATE, self._on_task)
        bus.watch_alive(self._on_alive)

    # -- watching (zenoh threads) -------------------------------------------------------
    def _on_task(self, msg: TaskState, _rx: Received) -> None:
        with self._cv:
            if msg.episode_id != self._episode:
                return
            self._success.update(msg.tick, msg.success)
            self._cv.notify_all()

    def _on_alive(self, service: str, alive: bool) -> None:
        if service in self.cfg.services:
            with self._cv:
                (self._lost.discard if alive else self._lost.add)(service)
                self._cv.notify_all()

    # -- requests -----------------------------------------------------------------------
    def _sim(self, command: SimCommand, **fields) -> SimControlReply:
        raw = self.bus.query(topics.SIM_CONTROL, SimControlRequest(command=command, **fields).SerializeToString(), 20.0)
        reply = SimControlReply.FromString(raw)
        if not reply.ok:
            raise SessionError(f"sim refused {SimCommand.Name(command)}: {reply.error}")
        return reply

    def _recorder(self, command: EpisodeCommand, **fields) -> EpisodeReply:
        req = EpisodeRequest(command=command, **fields)
        reply = EpisodeReply.FromString(self.bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), 60.0))
        if not reply.ok:
            raise SessionError(f"recorder refused {EpisodeCommand.Name(command)}: {reply.error}")
        return reply

    # -- one episode --------------------------------------------------------------------
    def _watch(self, episode_id: str) -> None:
        """Follow the task state of ``episode_id`` from its first tick."""
        with self._cv:
            self._episode, self._success = episode_id, SuccessWatch(self.cfg.settle_ticks)

    def _wait_done(self, limit: int) -> None:
        """Until success held for settle_ticks, the tick limit, or a lost service."""
        # Generous wall-clock bound: the loop may run slower than real time on a busy machine.
        budget = 30.0 + 5.0 * limit / self.cfg.control_hz
        deadline = time.monotonic() + budget
        with self._cv:
            while True:
                if self._lost:
                    raise SessionError(f"service(s) lost mid-episode: {', '.join(sorted(self._lost))}")
                if self._success.held or self._success.tick + 1 >= limit:
                    return
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    tick = self._success.tick
                    raise SessionError(f"episode made no progress: tick {tick} of {limit} after {budget:.0f}s")
                self._cv.wait(min(remaining, 0.5))

    def run_episode(self, seed: int) -> Attempt:
        if self.cfg.evaluation:  # the same id for the same scene: runs compare file by file
            episode_id = f"{self.cfg.task}-{self.rig}-eval-s{seed:06d}"
        else:
            stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
            episode_id = f"{self.cfg.task}-{self.rig}-s{seed:05d}-{stamp}"
        self._watch(episode_id)
        t0 = time.monotonic()
        reset = self._sim(SimCommand.SIM_COMMAND_RESET, task=self.cfg.task, seed=seed, episode_id=episode_id)
        self._recorder(
            EpisodeCommand.EPISODE_COMMAND_START,
            episode_id=episode_id,
            task=self.cfg.task,
            seed=seed,
            rig=self.rig,
            control_hz=self.cfg.control_hz,
            lockstep=reset.lockstep,
        )
        try:
            # The sim stops itself at the limit or once success has held: a PAUSE after that tick
            # lands a tick or two late on a busy machine, and episodes must not depend on the load.
            self._sim(SimCommand.SIM_COMMAND_RUN, max_ticks=self.cfg.tick_limit(), settle_ticks=self.cfg.settle_ticks)
            self._wait_done(self.cfg.tick_limit())
            paused = self._sim(SimCommand.SIM_COMMAND_PAUSE)
        except BaseException as exc:
            # Close what was recorded as a failed episode (the recorder flags it) rather than
            # deleting it: an infrastructure fault must not silently lose data.
            try:
                reply = self._recorder(
                    EpisodeCommand.EPISODE_COMMAND_STOP,
                    episode_id=episode_id,
                    success=False,
                    interrupted=str(exc) or type(exc).__name__,
                )
                self.progress(f"episode {episode_id} interrupted ({exc}); kept as failed: {reply.meta.path}")
            except Exception as stop_exc:
                log.warning("could not close interrupted episode %s: %s", episode_id, stop_exc)
            raise
        seconds = time.monotonic() - t0
        # The success that ended the episode counts, even if the object slips in the tick or two
        # before the pause lands; at the tick limit, the state at the pause decides.
        success = self._success.held or bool(paused.success)
        attempt = Attempt(seed, episode_id, success, int(paused.ticks), seconds)
        if success or self.cfg.evaluation:
            reply = self._recorder(
                EpisodeCommand.EPISODE_COMMAND_STOP, episode_id=episode_id, success=success, ticks=paused.ticks
            )
            attempt.meta = reply.meta
        else:
            self._recorder(EpisodeCommand.EPISODE_COMMAND_DISCARD, episode_id=episode_id)
        return attempt

    def warm_up(self) -> None:
        """Run a few unrecorded ticks so the first episode does not pay for cold starts
        (first renders and JPEG encodes, zenoh routes, the expert's first call)."""
        self._watch("warmup")
        self._sim(SimCommand.SIM_COMMAND_RESET, task=self.cfg.task, seed=self.cfg.seed, episode_id="warmup")
        self._sim(SimCommand.SIM_COMMAND_RUN, max_ticks=self.cfg.warmup_ticks, settle_ticks=self.cfg.settle_ticks)
        try:
            self._wait_done(self.cfg.warmup_ticks)
        finally:
            self._sim(SimCommand.SIM_COMMAND_PAUSE)

    def run(self) -> SessionResult:
        cfg = self.cfg
        self.progress(f"waiting for services: {', '.join(cfg.services)}")
        self.bus.wait_alive(cfg.services, timeout=cfg.wait_services_s)
        if cfg.warmup_ticks:
            self.warm_up()
        result = self.result = SessionResult()  # (what has run so far, should the run be interrupted)
        max_attempts = cfg.episodes if cfg.evaluation else cfg.max_attempts or 3 * cfg.episodes
        seed = cfg.seed
        while len(result.recorded) < cfg.episodes:
            if len(result.attempts) >= max_attempts:
                raise SessionError(
                    f"only {len(result.recorded)} of {cfg.episodes} episodes succeeded in {max_attempts} attempts "
                    f"(failed seeds: {[a.seed for a in result.failed]})"
                )
            attempt = self.run_episode(seed)
            result.attempts.append(attempt)
            self.progress(
                f"[{len(result.attempts if cfg.evaluation else result.recorded)}/{cfg.episodes}] "
                f"{cfg.task} {describe(attempt)}"
            )
            seed += 1
        return result


def summary(result: SessionResult) -> str:
    rec = result.recorded
    flagged = [a for a in rec if a.meta.flags]
    lines = [f"recorded {len(rec)} episodes in {len(result.attempts)} attempts"]
    if result.failed:
        lines.append(f"expert failures (discarded): seeds {', '.join(str(a.seed) for a in result.failed)}")
    if rec:
        hz = sum(a.meta.achieved_hz for a in rec) / len(rec)
        lines.append(
            f"ticks per episode: {min(a.ticks for a in rec)}..{max(a.ticks for a in rec)}, "
            f"mean achieved rate {hz:.1f} Hz, drops {sum(sum(a.meta.drops.values()) for a in rec)}"
        )
    lines.append(
        f"flagged episodes: {len(flagged)}" + "".join(f"\n  {a.meta.path}: {'; '.join(a.meta.flags)}" for a in flagged)
    )
    return "\n".join(lines)


def main(cfg: SessionConfig) -> int:
    with Bus(cfg.bus) as bus:
        try:
            result = Session(cfg, bus).run()
        except (SessionError, TimeoutError) as exc:
            print(f"error: {exc}", flush=True)
            return 1
    print(summary(result), flush=True)
    return 0
