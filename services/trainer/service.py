"""The training service: trains on request and publishes its progress.

Requests come two ways, handled alike and run one at a time, in order:

- a Zenoh query on ``trainer/request`` (``TrainRequest`` -> ``TrainReply``): TRAIN queues a job,
  CANCEL stops one (it checkpoints where it is), STATUS lists the running and queued jobs;
- a job file dropped in ``jobs_dir``: ``<name>.yaml`` (or ``.json``) holds a training config (the
  same keys as ``viewscale train --config``). It is taken once it has not changed for ``settle_s``
  (a file still being written is not read half-way), renamed ``<name>.yaml.running``, then
  ``.done`` / ``.failed`` / ``.stopped``, with ``<name>.result.json`` beside it; a refused file is
  logged as an error naming it.

Progress goes out on ``trainer/progress`` (``TrainProgress``): QUEUED, then RUNNING about once a
``progress_every_s`` (step, loss, lr, it/s, ETA, validation loss), then DONE, FAILED or STOPPED.
A collection session can send TRAIN when it finishes and follow the run from there.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.core.bus import Bus
from services.core.config import ConfigError, deep_merge, parse_overrides, yaml_mapping
from services.core.runtime import OutputError, exclusive, output_dir, refuse_rivals, wait_for_stop
from services.core.topics import TRAIN_PROGRESS, TRAIN_REQUEST
from services.dataset.store import DatasetError, DatasetStore
from services.pb import trainer_pb2
from services.pb.common_pb2 import Header
from services.trainer.config import TrainConfig, TrainerServiceConfig, train_config_from_dict

log = logging.getLogger("trainer")

# Our part of the bus graph (keys relative to the namespace, like services.core.topics).
SERVICE_NAME = "trainer"

S = trainer_pb2


@dataclass
class Job:
    job_id: str
    cfg: TrainConfig
    file: Path | None = None  # the job file it came from (renamed as it runs)
    stop: threading.Event = field(default_factory=threading.Event)


class TrainerService:
    """Runs queued training jobs on a worker thread until ``stop`` is set."""

    def __init__(self, cfg: TrainerServiceConfig, bus: Bus):
        self.cfg = cfg
        self.bus = bus
        self._queue: queue.Queue[Job] = queue.Queue()
        self._queued: list[Job] = []
        self._running: Job | None = None
        self._lock = threading.Lock()
        self._seq = 0
        self._last_progress = 0.0
        self._stop = threading.Event()
        self._pub = bus.publisher(TRAIN_PROGRESS)
        self._threads: list[threading.Thread] = []

    # -- lifecycle ------------------------------------------------------------------------------
    def __enter__(self) -> TrainerService:
        refuse_rivals(self.bus, SERVICE_NAME, {SERVICE_NAME})  # (before: both queued every TRAIN request)
        self.bus.queryable(TRAIN_REQUEST, self._on_request)
        self._threads.append(threading.Thread(target=self._work, name="trainer-jobs", daemon=True))
        if self.cfg.jobs_dir:
            Path(self.cfg.jobs_dir).mkdir(parents=True, exist_ok=True)
            self._threads.append(threading.Thread(target=self._watch, name="trainer-watch", daemon=True))
        for t in self._threads:
            t.start()
        self.bus.announce(SERVICE_NAME)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            if self._running is not None:
                self._running.stop.set()
        for t in self._threads:
            t.join(timeout=60)

    def run(self, stop: threading.Event) -> None:
        wait_for_stop(stop)

    # -- requests -------------------------------------------------------------------------------
    def _status(self, reply: trainer_pb2.TrainReply) -> trainer_pb2.TrainReply:
        with self._lock:
            reply.running = self._running.job_id if self._running else ""
            reply.queued.extend(j.job_id for j in self._queued)
        return reply

    def _on_request(self, payload: bytes) -> bytes:
        req = S.TrainRequest()
        req.ParseFromString(payload)
        if req.command == S.TRAIN_COMMAND_STATUS:
            return self._status(S.TrainReply(ok=True)).SerializeToString()
        if req.command == S.TRAIN_COMMAND_CANCEL:
            with self._lock:
                jobs = ([self._running] if self._running else []) + self._queued
                hit = [j for j in jobs if j.job_id == req.job_id]
                for j in hit:
                    j.stop.set()
            if not hit:
                return S.TrainReply(ok=False, error=f"no job {req.job_id!r}", job_id=req.job_id).SerializeToString()
            return self._status(S.TrainReply(ok=True, job_id=req.job_id)).SerializeToString()
        data: dict[str, Any] = {}
        if req.data:
            data["data"] = req.data
        if req.out:
            data["out"] = req.out
        if req.preset:
            data["preset"] = req.preset
        if req.steps:
            data["steps"] = int(req.steps)
        try:
            cfg = self._job_config(data, list(req.overrides))
        except (ConfigError, DatasetError) as exc:
            return S.TrainReply(ok=False, error=str(exc)).SerializeToString()
        job = self.submit(cfg, req.job_id or None)
        return self._status(S.TrainReply(ok=True, job_id=job.job_id)).SerializeToString()

    def _job_config(self, data: dict[str, Any], overrides: list[str]) -> TrainConfig:
        merged = deep_merge(parse_overrides(self.cfg.defaults), data)
        merged = deep_merge(merged, parse_overrides(overrides))
        merged.setdefault("progress", False)  # no terminal bar inside a service
        cfg = train_config_from_dict(merged)
        DatasetStore(cfg.data)  # a wrong data folder is refused now, not once the job's turn comes
        return cfg

    def submit(self, cfg: TrainConfig, job_id: str | None = None, file: Path | None = None) -> Job:
        job = Job(job_id or uuid.uuid4().hex[:12], cfg, file)
        with self._lock:
            self._queued.append(job)
        self._queue.put(job)
        self._publish(job, S.TRAIN_STATE_QUEUED)
        log.info("queued job %s: %s -> %s (%s, %d steps)", job.job_id, cfg.data, cfg.out, cfg.preset, cfg.steps)
        return job

    # -- job files ------------------------------------------------------------------------------
    def _watch(self) -> None:
        jobs_dir = Path(self.cfg.jobs_dir)
        seen: dict[Path, tuple[tuple[int, int], float]] = {}  # file -> (size, mtime) and since when
        while not self._stop.is_set():
            now = time.monotonic()
            files = sorted([*jobs_dir.glob("*.yaml"), *jobs_dir.glob("*.yml"), *jobs_dir.glob("*.json")])
            for path in list(seen):
                if path not in files:
                    del seen[path]
            for path in files:
                if path.name.endswith(".result.json"):
                    continue
                try:
                    st = path.stat()
                except OSError:
                    continue
                stamp = (st.st_size, st.st_mtime_ns)
                if path not in seen or seen[path][0] != stamp:
                    seen[path] = (stamp, now)  # (before: taken at once, a file being written half-read)
                if now - seen[path][1] < self.cfg.settle_s:
                    continue
                del seen[path]
                taken = path.with_name(path.name + ".running")
                try:
                    path.rename(taken)  # atomic: a file is taken once
                except OSError:
                    continue
                try:
                    raw = self._read_job(taken, path)
                    cfg = self._job_config(raw, [])
                except (ConfigError, DatasetError, ValueError) as exc:
                    # named as the file was dropped (before: as '<name>.running', gone by then), and
                    # logged (before: only in <name>.result.json and on trainer/progress)
                    error = str(exc) if str(exc).startswith(f"job file {path}") else f"job file {path}: {exc}"
                    log.error("%s (now %s.failed)", error, path.name)
                    self._finish_file(taken, "failed", {"error": error})
                    self._publish(Job(path.stem, TrainConfig(), taken), S.TRAIN_STATE_FAILED, error=error)
                    continue
                self.submit(cfg, path.stem, taken)
            self._stop.wait(self.cfg.poll_s)

    @staticmethod
    def _read_job(taken: Path, path: Path) -> dict[str, Any]:
        """The mapping job file ``path`` (taken: renamed ``taken``) holds; a ConfigError naming it."""
        what = f"job file {path}"
        try:
            text = taken.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{what} cannot be read: {exc}") from None
        if path.suffix != ".json":
            return yaml_mapping(text, what)
        try:
            raw = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"{what} is not valid JSON: {exc}") from None
        if not isinstance(raw, dict):
            raise ConfigError(f"{what} must hold an object at the top level")
        return raw

    @staticmethod
    def _finish_file(taken: Path, outcome: str, result: dict[str, Any]) -> None:
        base = taken.name.removesuffix(".running")
        stem = base.rsplit(".", 1)[0]
        (taken.parent / f"{stem}.result.json").write_text(json.dumps({"outcome": outcome, **result}, indent=2) + "\n")
        taken.rename(taken.with_name(f"{base}.{outcome}"))

    # -- the worker -----------------------------------------------------------------------------
    def _work(self) -> None:
        from services.policy.checkpoint import CheckpointError
        from services.trainer.train import TrainingError, train

        while not self._stop.is_set():
            try:
                job = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            with self._lock:
                self._queued.remove(job)
                self._running = job
            if job.stop.is_set():
                outcome, result = "stopped", {}
                self._publish(job, S.TRAIN_STATE_STOPPED)
            else:
                self._publish(job, S.TRAIN_STATE_RUNNING)
                try:
                    # one training per run folder, as `viewscale train` (which holds the same lock)
                    with output_dir(job.cfg.out, "out"), exclusive(job.cfg.out, "training"):
                        res = train(job.cfg, on_progress=lambda ev, j=job: self._on_progress(j, ev), stop=job.stop)
                    outcome = "stopped" if res.stopped else "done"
                    result = {
                        "step": res.step,
                        "loss": res.loss,
                        "val_loss": res.val_loss,
                        "checkpoint": str(res.checkpoint) if res.checkpoint else None,
                    }
                    state = S.TRAIN_STATE_STOPPED if res.stopped else S.TRAIN_STATE_DONE
                    self._publish(
                        job,
                        state,
                        step=res.step,
                        loss=res.loss,
                        val_loss=res.val_loss,
                        checkpoint=str(res.checkpoint or ""),
                    )
                    log.info("job %s %s at step %d", job.job_id, outcome, res.step)
                except (ConfigError, DatasetError, TrainingError, CheckpointError, OutputError, OSError) as exc:
                    outcome, result = "failed", {"error": str(exc)}
                    self._publish(job, S.TRAIN_STATE_FAILED, error=str(exc))
                    log.error("job %s failed: %s", job.job_id, exc)
                except Exception as exc:  # a bug must not take the service down with it
                    outcome, result = "failed", {"error": f"{type(exc).__name__}: {exc}"}
                    self._publish(job, S.TRAIN_STATE_FAILED, error=result["error"])
                    log.exception("job %s crashed", job.job_id)
            if job.file is not None:
                self._finish_file(job.file, outcome, result)
            with self._lock:
                self._running = None

    def _on_progress(self, job: Job, ev: dict[str, Any]) -> None:
        now = time.monotonic()
        if now - self._last_progress < self.cfg.progress_every_s:
            return
        self._publish(
            job,
            S.TRAIN_STATE_RUNNING,
            step=ev["step"],
            loss=ev.get("loss"),
            val_loss=ev.get("val_loss"),
            lr=ev.get("lr"),
            it_s=ev.get("it_s"),
            samples_s=ev.get("samples_s"),
            eta_s=ev.get("eta_s"),
            data_wait=ev.get("data_wait"),
        )

    def _publish(self, job: Job, state: int, **values: Any) -> None:
        self._last_progress = time.monotonic()
        self._seq += 1
        msg = S.TrainProgress(
            header=Header(stamp_ns=time.time_ns(), seq=self._seq, frame_id=SERVICE_NAME),
            job_id=job.job_id,
            state=state,
            steps=job.cfg.steps,
            out=job.cfg.out,
            val_loss=math.nan,
        )
        for name, value in values.items():
            if value is not None:
                setattr(msg, name, value)
        self._pub.put(msg)


def main(cfg: TrainerServiceConfig) -> int:
    from services.core.runtime import serve

    address = f"{cfg.bus.namespace}/{TRAIN_REQUEST}" + (f" jobs={cfg.jobs_dir}" if cfg.jobs_dir else "")
    return serve(SERVICE_NAME, cfg.bus, lambda bus: TrainerService(cfg, bus), address)
