"""Denoising workers: the model compute behind the policy server.

``ModelEngine`` owns one loaded checkpoint on one device. Whatever is queued when a forward pass
starts -- encodes (a view's observation -> its conditioning vector) and denoising steps (a view's
noisy chunk at step k -> its noise prediction) -- is computed in that pass, one per kind; nothing
waits for a batch to fill. It is used two ways:

- ``compute_*`` in the caller's thread: the worker's stream threads. The first caller to find the
  engine idle computes its own job and everyone else's queued so far (flat combining); the others
  find theirs done. No other thread is woken for a step: on a 2-core machine each wake-up of an
  idle thread costs ~0.1-0.3 ms, which is the fan-out's whole budget per step.
- ``encode``/``step``/... returning a Future, computed on the engine's own thread (started on
  first use): the in-process backend of the server, whose event loop must never compute.

The worker service puts it behind ``DenoiseWorker.Denoise``: one bidirectional stream per request
and view, the observation first (encoded once, cached for the stream), then one message per step.
It is a synchronous gRPC server: each stream's messages are read, computed and answered on that
stream's own thread (side by side with a ``grpc.aio`` worker that handed each step to an engine
thread and back: 0.2-0.3 ms less per denoising step on loopback in four runs of five, docs/serving.md).

    python -m services.policy worker --checkpoint runs/lift --listen 127.0.0.1:0

The worker announces ``listening worker <host:port>`` and then ``ready worker <host:port>``,
serves ``grpc.health.v1`` (NOT_SERVING until the model is loaded) and reflection, refuses a
stream whose checkpoint hash is not its own, and takes at most ``max_streams`` streams at once
(more get RESOURCE_EXHAUSTED at once: the server drops that view rather than wait).
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import logging
import os
import socket
import threading
import time
import uuid
from concurrent import futures
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import torch
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio
from grpc_reflection.v1alpha import reflection

from services.core.tensors import from_tensor, to_tensor
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy.checkpoint import LoadedPolicy, checkpoint_sha256, inference_device, load_policy, model_id
from services.policy.config import PRECISIONS, open_to_others
from services.policy.model.fastpath import cast_matmul_weights
from services.policy.transport import EXCLUSIVE_PORT, keepalive_server_options, listen_on, message_size_options

log = logging.getLogger(__name__)

WORKER_SERVICE = "viewscale.v1.DenoiseWorker"
# Initial metadata of every Denoise stream: which worker process took it. Behind an address that
# gRPC balances over several replicas (a DNS name), the server learns from it which of a
# request's views share a replica, and groups only those.
REPLICA_KEY = "viewscale-replica"


BOOT_ID = Path("/proc/sys/kernel/random/boot_id")


def machine_id() -> str:
    """The running kernel's boot id: one value for every process and container on a machine
    (containers share the kernel; their host names differ), another on another host or VM. The
    host name where the kernel does not say (not Linux)."""
    try:
        return BOOT_ID.read_text().strip() or socket.gethostname()
    except OSError:
        return socket.gethostname()


def allowed_cores() -> list[int]:
    """The CPU cores this process may run on (taskset, a container's cpuset), all where unknown."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def accelerator_id(device: torch.device) -> str:
    """A GPU's own id, the same in every process that holds it (its UUID; the index is not:
    CUDA_VISIBLE_DEVICES renumbers devices per process); empty on CPU or where the device has none.

    A MIG slice is a GPU of its own for placement: a process sees one slice, named in
    CUDA_VISIBLE_DEVICES (``MIG-<uuid>``, or ``MIG-GPU-<uuid>/<gi>/<ci>``), and that name is its id.
    Whether torch's UUID tells two slices of one GPU apart is not something to rely on."""
    if device.type != "cuda":
        return ""
    visible = [d.strip() for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")]
    index = device.index or 0
    if index < len(visible) and visible[index].startswith("MIG-"):
        return visible[index]
    # ROCm builds (device type cuda as well) have the property only since 2024's torch
    return str(getattr(torch.cuda.get_device_properties(device), "uuid", "") or "")


@dataclass
class _Job:
    kind: str  # "encode" or "step"
    items: list[tuple]  # one caller's inputs, computed in the same forward pass
    future: Future  # its result: the list of outputs, or the one output when ``single``
    single: bool = False


class ModelEngine:
    """One checkpoint on one device, computing whatever is queued in one batched pass.

    With ``precision`` bf16 the engine casts the policy's matrix-multiply weights to bfloat16 in
    place (``cast_matmul_weights``): give it a policy of its own."""

    def __init__(self, loaded: LoadedPolicy, threads: int = 1, max_batch: int = 64, precision: str = "fp32"):
        self.loaded = loaded
        self.policy = loaded.policy
        self.device = next(self.policy.parameters()).device
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: {' or '.join(PRECISIONS)}")
        inference_device(self.device, precision)  # bf16 on a GPU without it: ValueError
        self.precision = precision  # "bf16": every pass under bfloat16 autocast; outputs float32 either way
        if precision == "bf16":
            cast_matmul_weights(self.policy, torch.bfloat16)
        self.accelerator = accelerator_id(self.device)  # which GPU, for the server's placement
        self.normalizer = loaded.normalizer
        self.sha256 = checkpoint_sha256(loaded.path)
        self.model_id = model_id(loaded.path)
        self.threads = threads
        self.max_batch = max_batch
        self.passes = 0  # forward passes run (steps and encodes)
        self.batched_items = 0  # items they held
        # Jobs wait here until a pass takes them; nobody holds a job outside it while waiting for
        # the pass lock, so a pass takes everything that queued while the previous one ran.
        self._jobs: collections.deque[_Job] = collections.deque()
        self._queued = threading.Condition()
        self._pass = threading.Lock()  # one forward pass at a time, whoever runs it
        self._thread: threading.Thread | None = None  # the engine's own thread, for Future callers
        self._closing = False
        self._configured = threading.local()

    def check_observation(self, frames: np.ndarray, state: np.ndarray) -> None:
        """ValueError naming what is wrong unless frames are (To, H, W, 3) uint8 and state (To, D) float32."""
        c = self.policy.cfg
        want = (c.obs_horizon, *c.image_size, 3)
        if frames.dtype != np.uint8 or frames.shape != want:
            raise ValueError(f"frames must be uint8 {want}, got {frames.dtype} {frames.shape}")
        if state.shape != (c.obs_horizon, c.state_dim):
            raise ValueError(f"state must be float32 {(c.obs_horizon, c.state_dim)}, got {state.shape}")
        if not np.isfinite(state).all():
            raise ValueError("state is not finite")

    def check_chunk(self, x: np.ndarray, k: int) -> None:
        """ValueError unless x is a finite (Tp, Da) chunk and k a training timestep."""
        c = self.policy.cfg
        if x.shape != (c.pred_horizon, c.action_dim):
            raise ValueError(f"x must be float32 {(c.pred_horizon, c.action_dim)}, got {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError("x is not finite")
        if not 0 <= k < c.noise.num_train_timesteps:
            raise ValueError(f"timestep {k} is outside 0..{c.noise.num_train_timesteps - 1}")

    @classmethod
    def open(
        cls, checkpoint: str | Path, device: str = "cpu", threads: int = 1, max_batch: int = 64, precision: str = "fp32"
    ) -> ModelEngine:
        return cls(load_policy(checkpoint, device=device), threads, max_batch, precision)

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16")

    # -- computing in the caller's thread --------------------------------------------------
    def _compute(self, kind: str, items: list[tuple]) -> list[np.ndarray]:
        if getattr(self._configured, "threads", None) != self.threads:
            # torch's intra-op thread count is per thread: a pool thread made before the model
            # loaded (a health check's) would otherwise compute with every core
            torch.set_num_threads(self.threads)
            self._configured.threads = self.threads
        job = _Job(kind, items, Future())
        self._put(job)
        while not job.future.done():
            with self._pass:
                if not job.future.done():  # nobody took it into their pass: run everything queued
                    self._run_queued()
        return job.future.result()

    def _put(self, job: _Job) -> None:
        with self._queued:
            self._jobs.append(job)
            self._queued.notify()

    def compute_encode(self, inputs: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
        """(frames (To, H, W, 3) uint8, state (To, D) float32 normalised) each -> their conds (Dc,)."""
        return self._compute("encode", list(inputs))

    def compute_steps(self, items: list[tuple[np.ndarray, np.ndarray, int]]) -> list[np.ndarray]:
        """(cond (Dc,), x (Tp, 7) float32 in the view's frame, timestep k) each -> their eps (Tp, 7)."""
        return self._compute("step", [(c, x, int(k)) for c, x, k in items])

    # -- submitting to the engine's thread (any thread; for an event loop) -----------------
    def _submit(self, kind: str, items: list[tuple], single: bool) -> Future:
        fut: Future = Future()
        with self._queued:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="model-engine", daemon=True)
                self._thread.start()
        self._put(_Job(kind, items, fut, single))
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
        with self._queued:
            self._closing = True
            self._queued.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10)

    # -- the passes ------------------------------------------------------------------------
    def _run(self) -> None:
        torch.set_num_threads(self.threads)
        while True:
            with self._queued:
                while not self._jobs and not self._closing:
                    self._queued.wait()
                if self._closing and not self._jobs:
                    return
            with self._pass:
                self._run_queued()  # (a caller computing in its own thread may have taken them: then nothing)

    def _run_queued(self) -> None:
        """With the pass lock held: whatever is queued now (up to max_batch items), one pass per kind."""
        jobs: list[_Job] = []
        n = 0
        with self._queued:  # no waiting for more
            while self._jobs and (not jobs or n + len(self._jobs[0].items) <= self.max_batch):
                jobs.append(self._jobs.popleft())
                n += len(jobs[-1].items)
        for kind in ("encode", "step"):
            batch = [j for j in jobs if j.kind == kind and j.future.set_running_or_notify_cancel()]
            if not batch:
                continue
            items = [item for j in batch for item in j.items]
            try:
                results = self._encode(items) if kind == "encode" else self._step(items)
            except Exception as exc:  # a bad batch fails its callers, never the engine
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
        with self._autocast():
            cond = self.policy.encode(obs, state if state.shape[-1] else None)  # (B, Dc)
        return list(cond.float().cpu().numpy())

    @torch.no_grad()
    def _step(self, items: list[tuple]) -> list[np.ndarray]:
        cond = torch.from_numpy(np.stack([it[0] for it in items])).to(self.device)  # (B, Dc)
        x = torch.from_numpy(np.stack([it[1] for it in items]).astype(np.float32)).to(self.device)  # (B, Tp, 7)
        k = torch.tensor([it[2] for it in items], dtype=torch.long, device=self.device)  # (B,)
        with self._autocast():
            eps = self.policy.denoise_step_eps(x, k, cond)  # (B, Tp, 7)
        return list(eps.float().cpu().numpy())


def unconditional_cond(cond: np.ndarray) -> np.ndarray:
    """The condition-dropout input (zeros), as the trainer drops conditions (``cond_dropout``)."""
    return np.zeros_like(cond)


class _Batch:
    def __init__(self) -> None:
        self.items: list[list[tuple]] = []  # each member's inputs
        self.taken = False  # a member is computing it
        self.results: list[list[np.ndarray]] | None = None
        self.error: BaseException | None = None


class ViewGroup:
    """The views of one request on this worker (streams sharing ``DenoiseObservation.group``).

    Each of their encodes, and each of their denoising steps, is computed in one forward pass: the
    member whose input completes the set computes it for all, the others wait for their share. The
    set for a step is the members whose streams are still open (a view the server dropped leaves
    the group when its stream ends); for the encode it is the group's size. The wait is bounded by
    ``wait_s``: past it the members that are there are computed without the rest.
    """

    def __init__(self, size: int, wait_s: float):
        self.size = size
        self.wait_s = wait_s
        self.live = 0  # joined and still open
        self._cond = threading.Condition()
        self._pending: dict[object, _Batch] = {}

    def join(self) -> None:
        with self._cond:
            self.live += 1

    def leave(self) -> None:
        with self._cond:
            self.live -= 1
            self._cond.notify_all()  # a step waiting for this member can go now

    def encode(self, items: list[tuple], compute) -> list[np.ndarray]:
        """This member's observation, encoded in one pass with every member's (the group's size)."""
        return self._together("encode", items, lambda: self.size, compute)

    def step(self, k: int, items: list[tuple], compute) -> list[np.ndarray]:
        """This member's step k, in one pass with the step k of every member still open."""
        return self._together(("step", k), items, lambda: self.live, compute)

    def _together(self, key, items: list[tuple], expected, compute) -> list[np.ndarray]:
        """This member's ``items`` computed in one ``compute`` call with the other members' for ``key``."""
        with self._cond:
            batch = self._pending.setdefault(key, _Batch())
            i = len(batch.items)
            batch.items.append(items)
            end = time.monotonic() + self.wait_s
            while not batch.taken and len(batch.items) < expected():
                left = end - time.monotonic()
                if left <= 0:
                    log.warning(
                        "group %s: computed %d of %d views after waiting %.0f ms",
                        key,
                        len(batch.items),
                        expected(),
                        self.wait_s * 1e3,
                    )
                    break
                self._cond.wait(left)
            lead = not batch.taken
            if lead:
                batch.taken = True
                del self._pending[key]
        if lead:
            try:
                flat = compute([it for member in batch.items for it in member])
                out, j = [], 0
                for member in batch.items:
                    out.append(flat[j : j + len(member)])
                    j += len(member)
                batch.results = out
            except BaseException as exc:  # every member gets the failure
                batch.error = exc
            with self._cond:
                self._cond.notify_all()
        else:
            with self._cond:
                while batch.results is None and batch.error is None:
                    self._cond.wait()
        if batch.error is not None:
            raise batch.error
        return batch.results[i]


class DenoiseWorkerService(policy_pb2_grpc.DenoiseWorkerServicer):
    """``DenoiseWorker`` over a ModelEngine, on a synchronous gRPC server: every stream computes on its own thread."""

    def __init__(self, engine: ModelEngine | None = None, max_streams: int = 256, group_wait_s: float = 0.05):
        self.engine = engine  # None while the model loads: calls are UNAVAILABLE (health says NOT_SERVING)
        self.max_streams = max_streams
        self.group_wait_s = group_wait_s
        self.streams = 0  # Denoise streams opened so far
        self.replica = f"{socket.gethostname()}/{os.getpid()}/{uuid.uuid4().hex[:8]}"
        self.machine = machine_id()  # what it computes on (WorkerInfo): the server's placement auto
        self.cores = allowed_cores()
        self._count = threading.Lock()
        self._groups: dict[str, ViewGroup] = {}

    def _join(self, group: str, size: int) -> ViewGroup:
        with self._count:
            g = self._groups.get(group)
            if g is None:
                g = self._groups[group] = ViewGroup(max(size, 1), self.group_wait_s)
            g.join()
            return g

    def _leave(self, group: str, g: ViewGroup) -> None:
        g.leave()
        with self._count:
            if g.live <= 0 and self._groups.get(group) is g:
                del self._groups[group]

    def _ready(self, context) -> ModelEngine:
        if self.engine is None:
            context.abort(grpc.StatusCode.UNAVAILABLE, "the model is still loading (health: NOT_SERVING)")
        return self.engine

    def GetWorkerInfo(self, request, context) -> policy_pb2.WorkerInfo:
        e = self._ready(context)
        return policy_pb2.WorkerInfo(
            checkpoint_sha256=e.sha256,
            model_id=e.model_id,
            device=str(e.device),
            threads=e.threads,
            max_batch=e.max_batch,
            streams=self.streams,
            passes=e.passes,
            batched_items=e.batched_items,
            max_streams=self.max_streams,
            machine=self.machine,
            cores=self.cores,
            accelerator=e.accelerator,
            precision=e.precision,
        )

    def Denoise(self, request_iterator, context):
        engine = self._ready(context)
        context.send_initial_metadata(((REPLICA_KEY, self.replica),))  # before the first message
        cond = cond_u = None
        view = "?"
        group: ViewGroup | None = None
        group_id = ""
        try:
            for req in request_iterator:
                kind = req.WhichOneof("msg")
                if kind == "observation":
                    o = req.observation
                    view = o.view or "?"
                    if o.checkpoint_sha256 != engine.sha256:
                        context.abort(
                            grpc.StatusCode.FAILED_PRECONDITION,
                            f"worker holds checkpoint {engine.sha256[:12]}, the server "
                            f"{o.checkpoint_sha256[:12] or '(none)'}: start both from the same checkpoint",
                        )
                    if (o.precision or "fp32") != engine.precision:
                        context.abort(
                            grpc.StatusCode.FAILED_PRECONDITION,
                            f"worker computes in {engine.precision}, the server asks for {o.precision or 'fp32'}: "
                            "start both with the same precision",
                        )
                    try:
                        frames = from_tensor(o.frames)
                        state = from_tensor(o.state) if o.state.shape else np.zeros((frames.shape[0], 0), np.float32)
                        state = state.astype(np.float32)
                        engine.check_observation(frames, state)  # before any torch call
                    except ValueError as exc:
                        context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"observation of {view}: {exc}")
                    with self._count:
                        self.streams += 1  # a request's view (a stream opened ahead counts once used)
                    t0 = time.perf_counter()
                    if o.group and group is None:
                        group_id, group = o.group, self._join(o.group, o.group_size)
                    if group is not None:
                        cond = group.encode([(frames, state)], engine.compute_encode)[0]
                    else:
                        cond = engine.compute_encode([(frames, state)])[0]
                    cond_u = unconditional_cond(cond) if o.unconditional else None
                    yield policy_pb2.DenoiseReply(compute_ms=(time.perf_counter() - t0) * 1e3)
                elif kind == "step":
                    if cond is None:
                        context.abort(grpc.StatusCode.FAILED_PRECONDITION, "a step came before the observation")
                    t0 = time.perf_counter()
                    try:
                        x = from_tensor(req.step.x).astype(np.float32)
                        engine.check_chunk(x, req.step.k)
                    except ValueError as exc:
                        context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"step of {view}: {exc}")
                    conds = [cond] if cond_u is None else [cond, cond_u]  # with its unconditional twin: one pass
                    items = [(c, x, req.step.k) for c in conds]
                    if group is not None:
                        eps = group.step(req.step.k, items, engine.compute_steps)
                    else:
                        eps = engine.compute_steps(items)
                    reply = policy_pb2.DenoiseReply(eps=to_tensor(eps[0]), compute_ms=(time.perf_counter() - t0) * 1e3)
                    if cond_u is not None:
                        reply.eps_uncond.CopyFrom(to_tensor(eps[1]))
                    yield reply
                else:
                    context.abort(grpc.StatusCode.INVALID_ARGUMENT, "empty DenoiseRequest")
        except grpc.RpcError:
            # the caller went away mid-stream (it cancels a stream it is done with): nothing to answer
            return
        finally:
            if group is not None:
                self._leave(group_id, group)


# -- health, reflection, token (shared with the policy server) ----------------------------------

OPEN_METHODS = ("/grpc.health.v1.Health/", "/grpc.reflection.")  # callable without the token (probes, tools)


def bearer_matches(metadata, expected: bytes) -> bool:
    """``authorization: Bearer <token>`` in the call's metadata, compared in constant time."""
    got = dict(metadata or ()).get("authorization", "")
    return hmac.compare_digest(got.encode(), expected)


class WorkerTokenInterceptor(grpc.ServerInterceptor):
    """The synchronous server's bearer-token check: every call but health and reflection."""

    def __init__(self, token: str):
        if not token:
            raise ValueError("empty bearer token")
        self._expected = f"Bearer {token}".encode()

    def intercept_service(self, continuation, details):
        handler = continuation(details)
        if handler is None or details.method.startswith(OPEN_METHODS):
            return handler
        if bearer_matches(details.invocation_metadata, self._expected):
            return handler

        def deny(request, context):
            context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")

        if handler.unary_unary:
            return grpc.unary_unary_rpc_method_handler(deny, handler.request_deserializer, handler.response_serializer)
        return grpc.stream_stream_rpc_method_handler(deny, handler.request_deserializer, handler.response_serializer)


def add_health_and_reflection(server: grpc.aio.Server, services: list[str]) -> health_aio.HealthServicer:
    """grpc.health.v1 (every service NOT_SERVING until the caller says otherwise) and reflection."""
    health_servicer = health_aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = [*services, reflection.SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name]
    reflection.enable_server_reflection(names, server)
    return health_servicer


async def set_serving(health_servicer: health_aio.HealthServicer, services: list[str], serving: bool) -> None:
    status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
    for name in ["", *services]:
        await health_servicer.set(name, status)


def server_credentials(tls) -> grpc.ServerCredentials | None:
    if not tls.enabled:
        return None
    return grpc.ssl_server_credentials([(Path(tls.key).read_bytes(), Path(tls.cert).read_bytes())])


# -- the worker process -------------------------------------------------------------------------


async def serve_worker(cfg, stop: asyncio.Event, announce=print) -> int:
    """Run one worker until ``stop``: listen (NOT_SERVING), load the model, SERVING.

    The gRPC server is the synchronous one (its own threads: a thread per open stream); this
    coroutine only loads the model off the loop and waits for the stop signal."""
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=cfg.max_streams, thread_name_prefix="denoise"),
        interceptors=[WorkerTokenInterceptor(cfg.token)] if cfg.token else [],
        options=[
            *message_size_options(cfg.max_message_mb),
            *keepalive_server_options(),  # the policy server's pings (services.policy.transport)
            *EXCLUSIVE_PORT,  # a port another process holds: an error, not shared
        ],
        maximum_concurrent_rpcs=cfg.max_streams,
    )
    service = DenoiseWorkerService(max_streams=cfg.max_streams, group_wait_s=cfg.group_wait_ms / 1e3)
    policy_pb2_grpc.add_DenoiseWorkerServicer_to_server(service, server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = [WORKER_SERVICE, reflection.SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name]
    reflection.enable_server_reflection(names, server)

    def serving(on: bool) -> None:
        status = health_pb2.HealthCheckResponse.SERVING if on else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", WORKER_SERVICE):
            health_servicer.set(name, status)

    serving(False)
    creds = server_credentials(cfg.tls)
    port = listen_on(server, cfg.listen, creds)
    host = cfg.listen.rsplit(":", 1)[0]
    address = f"{host}:{port}"
    server.start()
    announce(f"listening worker {address}")
    if open_to_others(cfg.listen) and not cfg.token:
        log.warning(
            "%s is open beyond loopback with no token: whoever reaches it can run denoising passes "
            "(set VIEWSCALE_TOKEN, here and in the server)",
            address,
        )
    loop = asyncio.get_running_loop()
    try:
        engine = await loop.run_in_executor(
            None, ModelEngine.open, cfg.checkpoint, cfg.device, cfg.threads, cfg.max_batch, cfg.precision
        )
        service.engine = engine
        serving(True)
        log.info(
            "worker %s serving %s on %s (%d threads, precision %s)",
            address,
            engine.model_id,
            engine.device,
            engine.threads,
            engine.precision,
        )
        announce(f"ready worker {address}")
        await stop.wait()
        serving(False)
    finally:
        await loop.run_in_executor(None, lambda: server.stop(grace=1.0).wait())
    engine.close()
    return 0
