"""The recorder: every session topic into one MCAP file per episode, never blocking a publisher.

Threads and ownership:
- zenoh callbacks only route a sample into its channel's bounded queue (``put_nowait``); a full
  queue drops the sample and counts it. Outside an episode only calibration and pose are queued
  (they are cached so each episode file starts self-contained).
- one writer thread owns everything else: it validates payloads (``validate.parse``), keeps the
  episode's counters, writes the file, and runs episode commands. The control queryable posts
  START/STOP/DISCARD/STATUS to it and waits for the answer, so the file has a single writer and a
  STOP never races a message that arrived before it.
- liveliness changes of other services are queued as events and flag the open episode.

STOP waits (up to ``stop_grace_s``) until the file holds the ``ticks`` robot states, frames,
applied actions and task states the source says it published, then writes what is queued, the
metadata, and closes. SIGTERM (``close``) writes what is queued and closes the open episode
flagged ``interrupted``.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import Message

from services.core.bus import Bus, Received
from services.core.clock import now_ns
from services.core.runtime import exclusive, refuse_rivals, serve, wait_for_stop
from services.core.topics import (
    APPLIED_ACTION,
    EPISODE,
    EPISODE_CONTROL,
    ROBOT_STATE,
    TASK_STATE,
    Topic,
    topic_for_key,
)
from services.core.validation import Context, Invalid, capture_ns, check_episode_request, decode_strict, parse
from services.pb.episode_pb2 import (
    EPISODE_COMMAND_DISCARD,
    EPISODE_COMMAND_START,
    EPISODE_COMMAND_STATUS,
    EPISODE_COMMAND_STOP,
    EpisodeMeta,
    EpisodeReply,
    EpisodeRequest,
)
from services.recorder.config import RecorderConfig
from services.recorder.episode import EpisodeCounts, camera_of, episode_meta, fmt_counts, is_calibration
from services.recorder.writer import (
    EPISODE_CHANNEL,
    EPISODE_RECORD,
    PART_SUFFIX,
    START_RECORD,
    EpisodeWriter,
    episode_path,
    meta_to_record,
    start_record,
)

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted"
_BATCH = 32  # items taken from one channel queue per round, so no channel starves the others
# One message per tick when the source publishes them at all (a real robot has no task state).
_OPTIONAL_PER_TICK = (APPLIED_ACTION.key, TASK_STATE.key)
_LOG_FIRST = 3  # malformed payloads logged in full per topic and episode; then every 100th
# Cameras republish calibration at ~1 Hz: one cached longer than this before START is from a
# camera that may be gone, so it does not make the episode expect frames from that camera.
_FRESH_CALIBRATION_NS = 5_000_000_000


@dataclass
class _Episode(EpisodeCounts):
    """The open episode: its counters (``recorder/episode.py``), its file, and a write error if one
    happened (then nothing more is written). Touched by the writer thread only."""

    writer: EpisodeWriter | None = None
    error: str = ""


class Recorder:
    """Context manager: subscribes, serves episode control and writes until closed."""

    def __init__(self, cfg: RecorderConfig, bus: Bus, name: str = "recorder"):
        self.cfg = cfg
        self.bus = bus
        self.name = name
        self.out_dir = Path(cfg.out_dir)
        self._queues: dict[str, queue.Queue[Received]] = {}
        self._topics: dict[str, Topic | None] = {}
        self._recording = False  # read by zenoh callbacks: queue every topic, not just calibration
        self._drops: Counter[str] = Counter()
        self._drop_lock = threading.Lock()
        self._unknown: Counter[str] = Counter()
        self._idle_malformed: Counter[str] = Counter()
        self._image_sizes: dict[str, tuple[int, int]] = {}  # camera -> calibrated (width, height)
        self.refused_requests = 0  # control requests of the wrong type or with bad values
        self._calibration: dict[str, tuple[Received, Message]] = {}  # key -> latest good sample
        self._commands: queue.SimpleQueue[tuple[Callable[[], EpisodeReply | None], Future]] = queue.SimpleQueue()
        self._alive_events: queue.SimpleQueue[tuple[str, bool, int]] = queue.SimpleQueue()
        self._live: set[str] = set()  # the services whose liveliness tokens are on the bus now
        self._live_lock = threading.Lock()
        self._wake = threading.Event()
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder-writer", daemon=True)
        self._episode: _Episode | None = None
        self._stopping: tuple[EpisodeRequest, Future, float] | None = None  # STOP waiting for its ticks
        self._last_meta = EpisodeMeta()  # the last closed episode, for STATUS when idle
        self._started = (EpisodeMeta(), 0.0)  # the open episode's start announcement, and when it was last made
        self._publisher = None
        self._held = contextlib.ExitStack()  # the out_dir's lock, while open

    # -- lifecycle --------------------------------------------------------------------------
    def __enter__(self) -> Recorder:
        # one recorder per bus: a second one answers every episode request too, and records every
        # episode again into its own folder (before: both did, each reply from either one)
        refuse_rivals(self.bus, self.name, {self.name})
        self.out_dir.mkdir(parents=True, exist_ok=True)
        # one recorder per folder: a second one (another session on the same --out) would take
        # its episodes' ids, and flag the first one's open .part as left over from a crash
        self._held.enter_context(exclusive(self.out_dir, "recorder"))
        for part in sorted(self.out_dir.glob("*.mcap" + PART_SUFFIX)):
            log.warning(
                "partial episode %s from an earlier run; recover it with `python -m services.recorder.recover %s`",
                part,
                part,
            )
        self._publisher = self.bus.publisher(EPISODE)
        self._thread.start()
        self.bus.subscribe_raw("**", self._on_sample)
        self.bus.queryable(EPISODE_CONTROL, self._on_control)
        self.bus.watch_alive(self._on_alive)
        # Announce last: whoever sees the token can rely on the subscription being in place. It
        # goes when the recorder closes (not with the bus): the bus is free for another recorder.
        self._held.callback(self.bus.presence(self.name).undeclare)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def cached_calibration(self) -> list[str]:
        """Keys of the calibration and pose samples cached for the next episode's start."""
        return sorted(self._calibration)

    def run(self, stop: threading.Event) -> None:
        wait_for_stop(stop)

    def close(self) -> None:
        """Write everything queued and close the open episode (flagged interrupted if not stopped)."""
        try:
            self._close()
        finally:
            self._held.close()  # (once: a second close finds it empty)

    def _close(self) -> None:
        if not self._thread.is_alive():
            return
        self._halt.set()
        self._wake.set()
        self._thread.join()
        # The writer thread is gone: this thread is now the only one touching the episode.
        self._run_commands()
        if self._stopping is not None:
            req, fut, _ = self._stopping
            self._stopping = None
            fut.set_result(self._finish_stop(req))
        elif self._episode is not None:
            ep = self._episode
            log.warning("closing episode %s before STOP: flagged %s", ep.meta.episode_id, INTERRUPTED)
            ep.note(f"{INTERRUPTED}: the recorder was stopped before the episode's STOP")
            self._close_episode(success=False, ticks=0)

    # -- zenoh callbacks: enqueue only ------------------------------------------------------
    def _on_sample(self, rx: Received) -> None:
        key = rx.key
        q = self._queues.get(key)
        if q is None:
            topic = self._topics.get(key)
            if topic is None and key not in self._topics:
                topic = topic_for_key(key)
                self._topics[key] = None if topic is None or topic.key == EPISODE.key else topic
                topic = self._topics[key]
            if topic is None:
                self._unknown[key] += 1
                if self._unknown[key] == 1:
                    log.debug("ignoring key outside the session graph: %s", key)
                return
            q = self._queues.setdefault(key, queue.Queue(self.cfg.queue_size))
        if not self._recording and not is_calibration(key):
            return
        try:
            q.put_nowait(rx)
        except queue.Full:
            with self._drop_lock:
                self._drops[key] += 1
                n = self._drops[key]
            if n == 1 or n % 100 == 0:
                log.warning(
                    "recorder cannot keep up: %d samples dropped on %s (queue of %d full)", n, key, self.cfg.queue_size
                )
            return
        self._wake.set()

    def _on_alive(self, service: str, alive: bool) -> None:
        with self._live_lock:
            (self._live.add if alive else self._live.discard)(service)
        if service != self.name:
            self._alive_events.put((service, alive, now_ns()))
            self._wake.set()

    def _on_control(self, payload: bytes) -> bytes:
        try:
            req = decode_strict(EpisodeRequest, payload)  # another type's bytes leave unknown fields
            check_episode_request(req, self.cfg.max_episode_ticks)
        except Invalid as exc:
            self.refused_requests += 1
            log.warning("refused a control request (%d bytes): %s", len(payload), str(exc))
            return EpisodeReply(
                ok=False, error=f"malformed EpisodeRequest ({len(payload)} bytes): {exc}", recording=self._recording
            ).SerializeToString()
        return self.request(req).SerializeToString()

    # -- control ----------------------------------------------------------------------------
    def request(self, req: EpisodeRequest, timeout: float | None = None) -> EpisodeReply:
        """Run one episode command on the writer thread and return its reply (never raises)."""
        handlers = {
            EPISODE_COMMAND_START: self._start,
            EPISODE_COMMAND_STOP: self._stop,
            EPISODE_COMMAND_DISCARD: self._discard,
            EPISODE_COMMAND_STATUS: self._status,
        }
        handler = handlers.get(req.command)
        if handler is None:
            return EpisodeReply(ok=False, error=f"unknown episode command {req.command}", recording=self._recording)
        if self._halt.is_set():
            return EpisodeReply(ok=False, error="recorder is shutting down", recording=self._recording)
        fut: Future = Future()
        self._commands.put((lambda: handler(req, fut), fut))
        self._wake.set()
        wait = timeout if timeout is not None else self.cfg.stop_grace_s + 30.0
        try:
            return fut.result(timeout=wait)
        except FutureTimeout:
            return EpisodeReply(
                ok=False, error=f"recorder did not answer within {wait:.0f}s", recording=self._recording
            )
        except Exception as exc:
            log.exception("episode command %s failed", req.command)
            return EpisodeReply(ok=False, error=f"{type(exc).__name__}: {exc}", recording=self._recording)

    def _error(self, text: str) -> EpisodeReply:
        return EpisodeReply(ok=False, error=text, recording=self._episode is not None)

    def _check_id(self, req: EpisodeRequest) -> EpisodeReply | None:
        ep = self._episode
        if ep is None:
            return self._error("not recording")
        if req.episode_id and req.episode_id != ep.meta.episode_id:
            return self._error(f"unknown episode id {req.episode_id!r} (recording {ep.meta.episode_id!r})")
        return None

    def _start(self, req: EpisodeRequest, fut: Future) -> EpisodeReply:
        if self._episode is not None:
            return self._error(f"already recording episode {self._episode.meta.episode_id!r}; STOP or DISCARD it first")
        try:
            path = episode_path(self.out_dir, req.episode_id)
        except ValueError as exc:
            return self._error(str(exc))
        part = path.with_name(path.name + PART_SUFFIX)
        if path.exists() or part.exists():
            return self._error(f"episode {req.episode_id!r} already exists at {path if path.exists() else part}")
        start_ns = now_ns()
        try:
            writer = EpisodeWriter(path, self.cfg.chunk_size, self.cfg.flush_interval_s)
        except OSError as exc:
            return self._error(f"cannot create {part}: {exc}")
        with self._drop_lock:
            self._drops.clear()
        ep = _Episode.start(req, str(writer.path), start_ns)
        ep.writer = writer
        try:
            writer.add_metadata(START_RECORD, start_record(ep.meta))
        except OSError as exc:
            writer.abort()
            return self._error(f"cannot write {part}: {exc}")
        self._episode = ep
        self._recording = True
        for key, (rx, msg) in sorted(self._calibration.items()):
            self._write(ep, key, rx, msg)
        # Stale ones are written for completeness, but the camera may be gone: expect no frames from it.
        ep.cameras = {
            camera_of(key)
            for key, (rx, _) in self._calibration.items()
            if start_ns - rx.receive_ns <= _FRESH_CALIBRATION_NS
        }
        log.info(
            "episode %s started: task %s seed %d rig %s at %.1f Hz -> %s",
            req.episode_id,
            req.task,
            req.seed,
            req.rig,
            req.control_hz,
            writer.part_path,
        )
        meta = self._meta(ep)
        del meta.flags[:]  # (nothing is recorded yet: what a closed episode is flagged for says nothing)
        meta.end_ns = 0  # open
        self._started = (EpisodeMeta(), time.monotonic())
        self._started[0].CopyFrom(meta)
        self._announce(meta)  # a robot service names it in its states from now on
        with self._live_lock:
            arm = self._live & {"robot", "sim"}
        if not arm:  # (before: an episode of no arm state was recorded, and said so only at STOP)
            meta.flags.append(
                f"no robot service or sim on this bus (namespace {self.bus.cfg.namespace!r}): the episode "
                "records no arm state until one starts"
            )
        return EpisodeReply(ok=True, recording=True, meta=meta)

    def _stop(self, req: EpisodeRequest, fut: Future) -> EpisodeReply | None:
        bad = self._check_id(req)
        if bad is not None:
            return bad
        if self._stopping is not None:
            return self._error("a STOP is already in progress")
        # Answered later by _poll_stop, once the ticks are in or the grace period is over.
        self._stopping = (req, fut, time.monotonic() + self.cfg.stop_grace_s)
        self._poll_stop()
        return None

    def _poll_stop(self) -> None:
        if self._stopping is None:
            return
        req, fut, deadline = self._stopping
        ep = self._episode
        if ep is not None and not self._has_ticks(ep, req.ticks) and time.monotonic() < deadline:
            return
        self._stopping = None
        fut.set_result(self._finish_stop(req))

    def _has_ticks(self, ep: _Episode, ticks: int) -> bool:
        """Every per-tick message of ``ticks`` is accounted for, written or dropped: the robot
        states, the frames of every camera, and the applied actions and task states if the source
        publishes them (the applied action of the last tick goes out after its state and frames,
        so waiting for states alone could close the file one action short)."""
        with self._drop_lock:
            drops = dict(self._drops)

        # Malformed samples do not count: they may be extra, and then good ticks are still on the way.
        def seen(key: str) -> int:
            return ep.written[key] + drops.get(key, 0)

        keys = [ROBOT_STATE.key, *(k for k in _OPTIONAL_PER_TICK if seen(k))]
        keys += [f"camera/{c}/image" for c in ep.cameras]
        return all(seen(k) >= ticks for k in keys)

    def _finish_stop(self, req: EpisodeRequest) -> EpisodeReply:
        if self._episode is None:  # discarded meanwhile
            return self._error("episode was discarded before STOP completed")
        if req.interrupted:
            self._episode.note(f"{INTERRUPTED}: {req.interrupted}")
        return self._close_episode(success=req.success, ticks=req.ticks)

    def _discard(self, req: EpisodeRequest, fut: Future) -> EpisodeReply:
        ep = self._episode
        if ep is None:
            # Not recording: discard a finished episode's file.
            if not req.episode_id:  # (before: "invalid episode id ''")
                return self._error("not recording; a DISCARD with an episode id deletes that finished episode")
            try:
                path = episode_path(self.out_dir, req.episode_id)
            except ValueError as exc:
                return self._error(str(exc))
            if not path.exists():
                return self._error(f"unknown episode id {req.episode_id!r}: no {path}")
            path.unlink()
            log.info("episode %s discarded: deleted %s", req.episode_id, path)
            return EpisodeReply(ok=True, recording=False)
        bad = self._check_id(req)
        if bad is not None:
            return bad
        if self._stopping is not None:
            _, stop_fut, _ = self._stopping
            self._stopping = None
            stop_fut.set_result(self._error("episode was discarded before STOP completed"))
        self._recording = False
        meta = self._meta(ep)
        ep.writer.abort()
        self._episode = None
        log.info("episode %s discarded: deleted %s", ep.meta.episode_id, ep.writer.part_path)
        meta.path = ""
        self._announce(meta)  # (closed, no file: a robot service's states name it no more)
        return EpisodeReply(ok=True, recording=False, meta=meta)

    def _announce(self, meta: EpisodeMeta) -> None:
        """``meta`` on ``recorder/episode``: an episode started (end_ns 0, again every second while
        it records, for a robot service started since), closed, or discarded (no path)."""
        try:
            self._publisher.put(meta)
        except Exception:  # the episode records all the same; a bus problem must not fail a command
            log.exception("could not announce episode %s", meta.episode_id)

    def _status(self, req: EpisodeRequest, fut: Future) -> EpisodeReply:
        ep = self._episode
        if ep is None:
            return EpisodeReply(ok=True, recording=False, meta=self._last_meta)
        return EpisodeReply(ok=True, recording=True, meta=self._meta(ep))

    # -- writer thread ----------------------------------------------------------------------
    def _run(self) -> None:
        busy = False
        while not self._halt.is_set():
            if not busy:
                self._wake.wait(timeout=0.05)
                self._wake.clear()
            try:
                self._run_commands()
                self._run_alive_events()
                busy = self._drain(_BATCH) > 0
                self._poll_stop()
                if self._episode is not None and not self._episode.error:
                    self._episode.writer.maybe_flush()
                if self._episode is not None and time.monotonic() - self._started[1] > 1.0:
                    self._started = (self._started[0], time.monotonic())
                    self._announce(self._started[0])
            except Exception:  # the writer thread must outlive any single bad step
                log.exception("recorder writer step failed")
                busy = False

    def _run_commands(self) -> None:
        while True:
            try:
                run, fut = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                reply = run()
            except Exception as exc:
                log.exception("episode command failed")
                reply = self._error(f"{type(exc).__name__}: {exc}")
            if reply is not None:
                fut.set_result(reply)

    def _run_alive_events(self) -> None:
        while True:
            try:
                service, alive, stamp = self._alive_events.get_nowait()
            except queue.Empty:
                return
            ep = self._episode
            if ep is None or stamp < ep.start_ns:
                continue
            if not alive:
                ep.service_left(service)
                log.warning("episode %s: service %s lost liveliness", ep.meta.episode_id, service)
            elif ep.service_back(service):
                log.warning("episode %s: service %s is back", ep.meta.episode_id, service)

    def _drain(self, per_queue: int | None) -> int:
        """Process up to ``per_queue`` samples of every channel (None: what each holds now)."""
        done = 0
        for key, q in list(self._queues.items()):
            n = q.qsize() if per_queue is None else per_queue
            for _ in range(n):
                try:
                    rx = q.get_nowait()
                except queue.Empty:
                    break
                try:
                    self._process(key, rx)
                except Exception as exc:  # a recorder bug on one sample must not lose the others
                    log.exception("recorder failed on a sample of %s", key)
                    if self._episode is not None:
                        self._episode.note(f"recorder error on {key}: {type(exc).__name__}: {exc}")
                done += 1
        return done

    def _process(self, key: str, rx: Received) -> None:
        topic = self._topics[key]
        ep = self._episode
        ctx = Context(episode_id=ep.meta.episode_id if ep is not None else "", image_sizes=self._image_sizes)
        try:
            msg = parse(topic, rx.payload, self.cfg.decode_images, ctx)
        except Invalid as exc:
            self._malformed(key, rx, exc)
            return
        calibration = is_calibration(key)
        if calibration:
            self._calibration[key] = (rx, msg)
            if key.endswith("/calibration"):  # frames must match it from now on
                self._image_sizes[camera_of(key)] = (int(msg.width), int(msg.height))
        ep = self._episode
        if ep is None or (rx.receive_ns < ep.start_ns and not calibration):
            return  # arrived before the episode started
        self._write(ep, key, rx, msg)

    def _malformed(self, key: str, rx: Received, exc: Invalid) -> None:
        ep = self._episode
        in_episode = ep is not None and rx.receive_ns >= ep.start_ns
        counts = ep.malformed if in_episode else self._idle_malformed
        counts[key] += 1
        if in_episode:
            ep.malformed_reasons[(key, exc.reason)] += 1
        n = counts[key]
        if n <= _LOG_FIRST or n % 100 == 0:
            log.warning("malformed payload on %s (%d bytes, #%d): %s", key, len(rx.payload), n, exc)

    def _write(self, ep: _Episode, key: str, rx: Received, msg: Message) -> None:
        if ep.error:
            return
        topic = self._topics.get(key) or topic_for_key(key)
        stamp = capture_ns(msg)
        try:
            ep.writer.write(topic.mcap_topic, topic.msg_type, rx.payload, rx.receive_ns, stamp)
        except (OSError, ValueError) as exc:
            ep.error = f"write failed on {key}: {exc}"
            ep.note(ep.error)
            log.error("episode %s: %s; writing stops, the partial file is kept", ep.meta.episode_id, ep.error)
            return
        last = ep.count(key, msg, stamp, rx.receive_ns)
        if last is not None:
            log.warning(
                "episode %s: sequence on %s went back from %d (publisher restart?)", ep.meta.episode_id, key, last
            )

    # -- metadata and closing ---------------------------------------------------------------
    def _meta(self, ep: _Episode, ticks: int = 0, success: bool = False) -> EpisodeMeta:
        """The episode's facts so far, with every reason it is suspect in ``flags``."""
        with self._drop_lock:
            drops = dict(self._drops)
        return episode_meta(
            ep, drops=drops, ticks=ticks, success=success, end_ns=now_ns(), min_rate_fraction=self.cfg.min_rate_fraction
        )

    def _close_episode(self, success: bool, ticks: int) -> EpisodeReply:
        """Write what is queued, the final metadata, and close the file."""
        ep = self._episode
        assert ep is not None
        self._recording = False
        self._drain(None)
        self._run_alive_events()
        meta = self._meta(ep, ticks=ticks, success=success)
        self._episode = None
        try:
            if ep.error:
                raise OSError(ep.error)
            stamp = now_ns()
            ep.writer.write_message(EPISODE_CHANNEL, meta, stamp, stamp)
            ep.writer.flush()  # the final EpisodeMeta reaches the disk before the record that repeats it
            ep.writer.add_metadata(EPISODE_RECORD, meta_to_record(meta))
            ep.writer.close()
        except (OSError, ValueError) as exc:
            ep.writer.abandon()
            log.error(
                "episode %s could not be closed: %s; %s is kept for recovery", meta.episode_id, exc, ep.writer.part_path
            )
            return EpisodeReply(
                ok=False,
                recording=False,
                meta=meta,
                error=f"could not close {ep.writer.part_path}: {exc}; recover it with "
                f"`python -m services.recorder.recover {ep.writer.part_path}`",
            )
        self._last_meta = meta
        level = logging.WARNING if meta.flags else logging.INFO
        log.log(
            level,
            "episode %s closed: %d states, %.2f Hz, frames {%s}%s -> %s",
            meta.episode_id,
            ep.written[ROBOT_STATE.key],
            meta.achieved_hz,
            fmt_counts(dict(meta.frames)),
            "".join(f"\n  flag: {f}" for f in meta.flags),
            ep.writer.path,
        )
        self._announce(meta)  # (the file is closed: a bus problem does not turn this into a failure)
        return EpisodeReply(ok=True, recording=False, meta=meta)


def main(cfg: RecorderConfig) -> int:
    return serve("recorder", cfg.bus, lambda bus: Recorder(cfg, bus), str(cfg.out_dir))
