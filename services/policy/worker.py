"""Denoising workers: the model compute behind the policy server.

``ModelEngine`` owns one loaded checkpoint on one device and a compute thread. Callers submit
encodes (a view's observation -> its conditioning vector) and denoising steps (a view's noisy
chunk at step k -> its noise prediction); the thread takes everything queued at that moment --
never waiting for a batch to fill -- and runs it as one forward pass per kind. The in-process
backend of the server calls it directly (all views of a request in one pass); the worker
service puts it behind ``DenoiseWorker.Denoise``: one bidirectional stream per request and
view, the observation first (encoded once, cached for the stream), then one message per step.

    python -m services.policy worker --checkpoint runs/lift --listen 127.0.0.1:0

The worker announces ``ready worker <host:port>``, serves ``grpc.health.v1`` (NOT_SERVING until
the model is loaded) and reflection, and refuses a stream whose checkpoint hash is not its own.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import torch
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio
from grpc_reflection.v1alpha import reflection

from services.core.tensors import from_tensor, to_tensor
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy.checkpoint import LoadedPolicy, checkpoint_sha256, load_policy, model_id

log = logging.getLogger(__name__)

WORKER_SERVICE = "viewscale.v1.DenoiseWorker"


@dataclass
class _Job:
    kind: str  # "encode" or "step"
    items: list[tuple]  # one caller's inputs, computed in the same forward pass
    future: Future  # its result: the list of outputs, or the one output when ``single``
    single: bool = False


class ModelEngine:
    """One checkpoint on one device, computing whatever is queued in one batched pass."""

    def __init__(self, loaded: LoadedPolicy, threads: int = 1, max_batch: int = 64):
        self.loaded = loaded
        self.policy = loaded.policy
        self.device = next(self.policy.parameters()).device
        self.normalizer = loaded.normalizer
        self.sha256 = checkpoint_sha256(loaded.path)
        self.model_id = model_id(loaded.path)
        self.threads = threads
        self.max_batch = max_batch
        self.passes = 0  # forward passes run (steps and encodes)
        self.batched_items = 0  # items they held
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="model-engine", daemon=True)
        self._thread.start()

    @classmethod
    def open(cls, checkpoint: str | Path, device: str = "cpu", threads: int = 1, max_batch: int = 64) -> ModelEngine:
        return cls(load_policy(checkpoint, device=device), threads, max_batch)

    # -- submitting (any thread) -----------------------------------------------------------
    def _submit(self, kind: str, items: list[tuple], single: bool) -> Future:
        fut: Future = Future()
        self._jobs.put(_Job(kind, items, fut, single))
        return fut

    def encode(self, frames: np.ndarray, state: np.ndarray) -> Future:
        """frames (To, H, W, 3) uint8, state (To, D) float32 normalised -> Future of cond (Dc,) float32."""
        return self._submit("encode", [(frames, state)], single=True)

    def encode_many(self, inputs: list[tuple[np.ndarray, np.ndarray]]) -> Future:
        """Several (frames, state) at once -> Future of their conds, in one forward pass."""
        return self._submit("encode", list(inputs), single=False)

    def step(self, cond: np.ndarray, x: np.ndarray, k: int) -> Future:
        """cond (Dc,), x (Tp, 7) float32 in the view's frame, timestep k -> Future of eps (Tp, 7) float32."""
        return self._submit("step", [(cond, x, int(k))], single=True)

    def step_many(self, items: list[tuple[np.ndarray, np.ndarray, int]]) -> Future:
        """Several (cond, x, k) at once -> Future of their eps, in one forward pass (a request's views)."""
        return self._submit("step", [(c, x, int(k)) for c, x, k in items], single=False)

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join(timeout=10)

    # -- the compute thread ----------------------------------------------------------------
    def _run(self) -> None:
        torch.set_num_threads(self.threads)
        while True:
            job = self._jobs.get()
            if job is None:
                return
            jobs, n = [job], len(job.items)
            while n < self.max_batch:  # whatever is queued now: no waiting for more
                try:
                    nxt = self._jobs.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._jobs.put(None)
                    break
                jobs.append(nxt)
                n += len(nxt.items)
            for kind in ("encode", "step"):
                batch = [j for j in jobs if j.kind == kind and j.future.set_running_or_notify_cancel()]
                if not batch:
                    continue
                items = [item for j in batch for item in j.items]
                try:
                    results = self._encode(items) if kind == "encode" else self._step(items)
                except Exception as exc:  # a bad batch fails its callers, never the thread
                    log.exception("%s batch of %d failed", kind, len(items))
                    for j in batch:
                        j.future.set_exception(exc)
                    continue
                self.passes += 1
                self.batched_items += len(items)
                i = 0
                for j in batch:
                    out, i = results[i : i + len(j.items)], i + len(j.items)
                    j.future.set_result(out[0] if j.single else out)

    @torch.no_grad()
    def _encode(self, items: list[tuple]) -> list[np.ndarray]:
        frames = np.stack([it[0] for it in items])  # (B, To, H, W, 3) uint8
        # the normaliser's own map, as the training samples were made (services.trainer.data)
        obs = torch.from_numpy(
            np.ascontiguousarray(self.normalizer.normalize_image(frames).transpose(0, 1, 4, 2, 3))
        ).to(self.device)  # (B, To, 3, H, W)
        state = torch.from_numpy(np.stack([it[1] for it in items])).to(self.device)  # (B, To, D)
        cond = self.policy.encode(obs, state if state.shape[-1] else None)  # (B, Dc)
        return list(cond.float().cpu().numpy())

    @torch.no_grad()
    def _step(self, items: list[tuple]) -> list[np.ndarray]:
        cond = torch.from_numpy(np.stack([it[0] for it in items])).to(self.device)  # (B, Dc)
        x = torch.from_numpy(np.stack([it[1] for it in items]).astype(np.float32)).to(self.device)  # (B, Tp, 7)
        k = torch.tensor([it[2] for it in items], dtype=torch.long, device=self.device)  # (B,)
        eps = self.policy.denoise_step_eps(x, k, cond)  # (B, Tp, 7)
        return list(eps.float().cpu().numpy())


def unconditional_cond(cond: np.ndarray) -> np.ndarray:
    """The condition-dropout input (zeros), as the trainer drops conditions (``cond_dropout``)."""
    return np.zeros_like(cond)


class DenoiseWorkerService(policy_pb2_grpc.DenoiseWorkerServicer):
    """``DenoiseWorker`` over a ModelEngine; every stream's compute runs on the engine's thread."""

    def __init__(self, engine: ModelEngine | None = None):
        self.engine = engine  # None while the model loads: calls are UNAVAILABLE (health says NOT_SERVING)
        self.streams = 0  # Denoise streams opened so far

    async def _ready(self, context) -> ModelEngine:
        if self.engine is None:
            await context.abort(grpc.StatusCode.UNAVAILABLE, "the model is still loading (health: NOT_SERVING)")
        return self.engine

    async def GetWorkerInfo(self, request, context) -> policy_pb2.WorkerInfo:
        e = await self._ready(context)
        return policy_pb2.WorkerInfo(
            checkpoint_sha256=e.sha256,
            model_id=e.model_id,
            device=str(e.device),
            threads=e.threads,
            max_batch=e.max_batch,
            streams=self.streams,
        )

    async def Denoise(self, request_iterator, context):
        await self._ready(context)
        self.streams += 1
        cond = cond_u = None
        view = "?"
        while True:
            # context.read()/write() rather than iterating and yielding: one hop less per message
            # through grpc.aio's async-generator adapters (measured per denoising step).
            req = await context.read()
            if req is grpc.aio.EOF:
                return
            kind = req.WhichOneof("msg")
            if kind == "observation":
                o = req.observation
                view = o.view or "?"
                if o.checkpoint_sha256 != self.engine.sha256:
                    await context.abort(
                        grpc.StatusCode.FAILED_PRECONDITION,
                        f"worker holds checkpoint {self.engine.sha256[:12]}, the server "
                        f"{o.checkpoint_sha256[:12] or '(none)'}: start both from the same checkpoint",
                    )
                try:
                    frames = from_tensor(o.frames)
                    state = from_tensor(o.state) if o.state.shape else np.zeros((frames.shape[0], 0), np.float32)
                except ValueError as exc:
                    await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"observation of {view}: {exc}")
                cond = await asyncio.wrap_future(self.engine.encode(frames, state.astype(np.float32)))
                cond_u = unconditional_cond(cond) if o.unconditional else None
                await context.write(policy_pb2.DenoiseReply())
            elif kind == "step":
                if cond is None:
                    await context.abort(grpc.StatusCode.FAILED_PRECONDITION, "a step came before the observation")
                try:
                    x = from_tensor(req.step.x).astype(np.float32)
                except ValueError as exc:
                    await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"step of {view}: {exc}")
                t0 = time.perf_counter()
                conds = [cond] if cond_u is None else [cond, cond_u]  # with its unconditional twin: one pass
                eps = await asyncio.wrap_future(self.engine.step_many([(c, x, req.step.k) for c in conds]))
                reply = policy_pb2.DenoiseReply(eps=to_tensor(eps[0]), compute_ms=(time.perf_counter() - t0) * 1e3)
                if cond_u is not None:
                    reply.eps_uncond.CopyFrom(to_tensor(eps[1]))
                await context.write(reply)
            else:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "empty DenoiseRequest")


def add_health_and_reflection(server: grpc.aio.Server, services: list[str]) -> health_aio.HealthServicer:
    """grpc.health.v1 (every service NOT_SERVING until the caller says otherwise) and reflection."""
    health = health_aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health, server)
    names = [*services, reflection.SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name]
    reflection.enable_server_reflection(names, server)
    return health


async def set_serving(health: health_aio.HealthServicer, services: list[str], serving: bool) -> None:
    status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
    for name in ["", *services]:
        await health.set(name, status)


# -- the worker process -------------------------------------------------------------------------


def server_credentials(tls) -> grpc.ServerCredentials | None:
    if not tls.enabled:
        return None
    return grpc.ssl_server_credentials([(Path(tls.key).read_bytes(), Path(tls.cert).read_bytes())])


async def serve_worker(cfg, stop: asyncio.Event, announce=print) -> int:
    """Run one worker until ``stop``: listen (NOT_SERVING), load the model, SERVING."""
    from services.policy.server import BearerTokenInterceptor

    interceptors = [BearerTokenInterceptor(cfg.token)] if cfg.token else []
    size = cfg.max_message_mb << 20
    server = grpc.aio.server(
        interceptors=interceptors,
        options=[("grpc.max_receive_message_length", size), ("grpc.max_send_message_length", size)],
    )
    service = DenoiseWorkerService()
    policy_pb2_grpc.add_DenoiseWorkerServicer_to_server(service, server)
    health = add_health_and_reflection(server, [WORKER_SERVICE])
    await set_serving(health, [WORKER_SERVICE], False)
    creds = server_credentials(cfg.tls)
    port = server.add_secure_port(cfg.listen, creds) if creds else server.add_insecure_port(cfg.listen)
    host = cfg.listen.rsplit(":", 1)[0]
    address = f"{host}:{port}"
    await server.start()
    announce(f"listening worker {address}")
    loop = asyncio.get_running_loop()
    engine = await loop.run_in_executor(None, ModelEngine.open, cfg.checkpoint, cfg.device, cfg.threads, cfg.max_batch)
    service.engine = engine
    await set_serving(health, [WORKER_SERVICE], True)
    log.info("worker %s serving %s on %s (%d threads)", address, engine.model_id, engine.device, engine.threads)
    announce(f"ready worker {address}")
    await stop.wait()
    await set_serving(health, [WORKER_SERVICE], False)
    await server.stop(grace=1.0)
    engine.close()
    return 0
