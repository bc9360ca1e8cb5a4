"""The policy server: ``Policy.GetAction`` over gRPC, composing views at every denoising step.

    viewscale serve --checkpoint runs/lift --listen 127.0.0.1:50051 --views F,FL,FR --workers 3

One ``grpc.aio`` server. A GetAction request is validated field by field (``observation.parse``:
INVALID_ARGUMENT naming the field, before any torch call), its frames decoded and resized off the
event loop, and then sampled with ``sample_composed``: the shared noisy chunk goes to every view
at each DDIM step, the views' noise predictions come back, are composed
(``services.policy.aggregation``) and one scheduler step is taken. Where the views are computed
is a backend behind one interface:

- ``LocalDenoiser``: a ModelEngine in this process, every view of a request in one forward pass;
- ``RemoteDenoiser``: one ``DenoiseWorker.Denoise`` stream per view to worker processes (local
  ones it started, given addresses, or one DNS name balanced round-robin over its replicas),
  placed by ``WorkerPool.place`` (pack, spread, auto). Each step has a deadline from the
  request's; a worker that is down, late or refusing is skipped for the rest of the request,
  its views moved once to another healthy worker (else dropped; the reply says ``degraded`` and
  why), and it rests in a circuit breaker until its health check says SERVING again. No view
  left: UNAVAILABLE.

Sessions (one per robot) keep their noise generator and scheduler; a newer request of a session
cancels its older one (ABORTED). Health (NOT_SERVING until the model or the workers are ready)
and reflection are served; an optional bearer token (interceptor, constant-time compare) and
TLS protect the rest.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import dataclasses
import ipaddress
import logging
import statistics
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import grpc
import numpy as np
import torch
from grpc_health.v1 import health_pb2, health_pb2_grpc

from services.core.action_spaces import eef_chunk_to_base, from_space
from services.core.geometry import quat_wxyz_to_matrix
from services.core.rig import camera_gap, load_rig
from services.core.robot_types import EefDelta, action_msg
from services.core.runtime import child_env
from services.core.tensors import from_tensor, to_tensor
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy import POLICY_PROTO_VERSION
from services.policy.aggregation import (
    CompositionError,
    check_orthogonal,
    compose,
    compose_with_unconditional,
    relative_transforms,
    to_view,
    view_transform,
)
from services.policy.checkpoint import checkpoint_sha256, model_config, model_id, read_info
from services.policy.config import MAX_REACH_M, PLACEMENTS, open_to_others
from services.policy.model.diffusion import make_inference_scheduler
from services.policy.model.policy import NoiseConfig
from services.policy.observation import (
    CameraSpec,
    InvalidRequest,
    Parsed,
    PolicySpec,
    check_session_id,
    model_inputs,
    parse,
)
from services.policy.transport import (
    EXCLUSIVE_PORT,
    keepalive_channel_options,
    keepalive_server_options,
    listen_on,
    message_size_options,
)
from services.policy.worker import (
    OPEN_METHODS,
    REPLICA_KEY,
    WORKER_SERVICE,
    ModelEngine,
    bearer_matches,
    unconditional_cond,
)

log = logging.getLogger(__name__)

POLICY_SERVICE = policy_pb2.DESCRIPTOR.services_by_name["Policy"].full_name  # "viewscale.v1.Policy"
DEFAULT_TIMEOUT_S = 5.0  # a GetAction without a deadline gets this one


class Unavailable(RuntimeError):
    """No view could be computed."""


class Superseded(RuntimeError):
    """A newer request of the same session (or a reset) took over: this one stops between steps."""


class NotFinite(RuntimeError):
    """The model predicted a noise that is not finite: no chunk is made of it."""


# -- the composed sampler, for any backend ------------------------------------------------------


class Denoiser(Protocol):
    """Where the views of one request are computed."""

    async def open(
        self, inputs: dict[str, tuple[np.ndarray, np.ndarray]], unconditional: bool, deadline: float
    ) -> None: ...

    async def step(
        self, k: int, xs: dict[str, np.ndarray], deadline: float
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]: ...

    @property
    def alive(self) -> list[str]: ...

    @property
    def dropped(self) -> dict[str, str]: ...

    @property
    def moved(self) -> dict[str, str]: ...

    async def move(self, deadline: float) -> list[str]:
        """Re-open the views lost since the last call elsewhere (observation again); the ones re-opened."""
        ...

    async def close(self) -> None: ...


@dataclass
class SampleResult:
    chunk: np.ndarray  # (Tp, 7) normalised, in the reference view's frame
    reference: str
    views_used: list[str]
    dropped: dict[str, str]  # view -> why
    moved: dict[str, str] = field(default_factory=dict)  # view -> where to, and why
    step_ms: list[float] = field(default_factory=list)
    encode_ms: float = 0.0


async def sample_composed(
    denoiser: Denoiser,
    inputs: dict[str, tuple[np.ndarray, np.ndarray]],
    spec: PolicySpec,
    order: list[str],
    gammas: dict[str, float],
    scheduler,
    x_T: np.ndarray,
    deadline: float,
    unconditional: bool = False,
    superseded: Callable[[], str | None] = lambda: None,
) -> SampleResult:
    """The composed DDIM loop (module docstring of services.policy.aggregation), deadline in monotonic s."""
    transforms = {
        v: view_transform(spec.action_space, spec.cameras[v].R_ext if spec.action_space == "camera" else None)
        for v in inputs
    }
    ref, G = relative_transforms(transforms, order)
    steps = scheduler.timesteps.tolist()

    # The encode and each step get an equal share of the time left, with one share more kept back
    # for moving views whose worker fails or is late (a retry gets that share too). Without the
    # reserve, the last step's share would be all the time left: a worker stuck there would hold
    # the request to its deadline with no time to move.
    parts_left = len(steps) + 1

    def share(retry: bool = False) -> float:
        return time.monotonic() + (deadline - time.monotonic()) / (parts_left + (0 if retry else 1))

    t0 = time.perf_counter()
    result = SampleResult(x_T, ref, [], {})
    await denoiser.open(inputs, unconditional, share())
    await denoiser.move(share(retry=True))  # views whose worker failed or was late: to another one
    parts_left -= 1
    result.encode_ms = (time.perf_counter() - t0) * 1e3
    x = torch.from_numpy(x_T[None].astype(np.float32))  # (1, Tp, 7) in the reference view's frame
    for k in steps:
        why = superseded()
        if why:
            raise Superseded(why)
        if not denoiser.alive:
            raise Unavailable("no view left: " + "; ".join(f"{v}: {w}" for v, w in denoiser.dropped.items()))
        t = time.perf_counter()
        xs = {v: to_view(x[0].numpy(), G[v]) for v in denoiser.alive}
        eps, eps_u = await denoiser.step(int(k), xs, share())
        if len(eps) < len(xs):  # a worker failed or was late: its views to another, with a fresh share
            retry_deadline = share(retry=True)
            moved = await denoiser.move(retry_deadline)
            if moved:
                more, more_u = await denoiser.step(int(k), {v: xs[v] for v in moved}, retry_deadline)
                eps.update(more)
                eps_u.update(more_u)
        if not eps:
            raise Unavailable(
                f"no view answered step {k}: " + "; ".join(f"{v}: {w}" for v, w in denoiser.dropped.items())
            )
        bad = [
            v
            for v in order
            if (v in eps and not np.isfinite(eps[v]).all()) or (v in eps_u and not np.isfinite(eps_u[v]).all())
        ]
        if bad:  # a chunk made of it would be NaN: a robot must never be sent one
            raise NotFinite(f"the model's noise prediction for {', '.join(bad)} at step {k} is not finite")
        if unconditional:
            e = compose_with_unconditional(eps, eps_u, G, {v: 1.0 for v in eps}, order)
        else:
            e = compose(eps, G, gammas, order)
        x = scheduler.step(torch.from_numpy(np.asarray(e, dtype=np.float32)[None]), int(k), x).prev_sample
        parts_left -= 1
        result.step_ms.append((time.perf_counter() - t) * 1e3)
    result.chunk = x[0].numpy()
    result.views_used = [v for v in order if v in denoiser.alive]
    result.dropped = dict(denoiser.dropped)
    result.moved = dict(denoiser.moved)
    return result


class LocalDenoiser:
    """Every view in this process, one batched forward pass per step (one ModelEngine)."""

    def __init__(self, engine: ModelEngine):
        self.engine = engine
        self._cond: dict[str, np.ndarray] = {}
        self._uncond = False

    @property
    def alive(self) -> list[str]:
        return list(self._cond)

    @property
    def dropped(self) -> dict[str, str]:
        return {}

    @property
    def moved(self) -> dict[str, str]:
        return {}

    async def move(self, deadline: float) -> list[str]:
        return []  # nothing is ever lost here

    async def open(self, inputs, unconditional, deadline) -> None:
        views = list(inputs)
        conds = await asyncio.wrap_future(self.engine.encode_many([inputs[v] for v in views]))  # one pass
        self._cond = dict(zip(views, conds))
        self._uncond = unconditional

    async def step(self, k, xs, deadline):
        views = list(xs)
        items = [(self._cond[v], xs[v], k) for v in views]
        if self._uncond:
            items += [(unconditional_cond(self._cond[v]), xs[v], k) for v in views]
        out = await asyncio.wrap_future(self.engine.step_many(items))  # every view (and twin) in one pass
        eps = dict(zip(views, out[: len(views)]))
        return eps, dict(zip(views, out[len(views) :]))

    async def close(self) -> None:
        pass


# -- workers: addresses, health, circuit breaker ------------------------------------------------


@dataclass
class WorkerHandle:
    address: str
    channel: grpc.aio.Channel
    stub: policy_pb2_grpc.DenoiseWorkerStub
    healthy: bool = False  # admitted: health SERVING and the same checkpoint
    reason: str = "not checked yet"
    streams: int = 0  # open streams (for spreading views)
    balanced: bool = False  # gRPC may spread its streams over several replicas (may_balance)
    device: str = ""  # its model's device (WorkerInfo), once admitted
    machine: str = ""  # the machine it runs on (WorkerInfo: the kernel's boot id), once admitted
    cores: frozenset[int] = frozenset()  # the CPU cores it may run on (WorkerInfo), once admitted
    accelerator: str = ""  # its GPU's own id (WorkerInfo: a CUDA UUID), once admitted; "" on CPU

    def competes_with(self, other: WorkerHandle) -> bool:
        """Whether the two compute on the same thing: CPU workers on one machine whose cores
        overlap (or that did not say which), GPU workers on one machine with the same GPU. A GPU
        worker that did not say which GPU it holds competes with none."""
        if self.machine != other.machine:
            return False
        if self.device == "cpu" and other.device == "cpu":
            return not (self.cores and other.cores) or bool(self.cores & other.cores)
        if self.device == "cpu" or other.device == "cpu":
            return False
        return bool(self.accelerator) and self.accelerator == other.accelerator


def describe_cores(cores: frozenset[int]) -> str:
    """{0, 1, 2, 5} -> '0-2,5'."""
    runs: list[list[int]] = []
    for c in sorted(cores):
        if runs and c == runs[-1][-1] + 1:
            runs[-1].append(c)
        else:
            runs.append([c])
    return ",".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)


def may_balance(address: str) -> bool:
    """Whether gRPC may spread the calls to ``address`` over several servers: a name that can
    resolve to several (``dns:///name:port``, a host name) or a list (``ipv4:A:P,B:P``). An IP
    literal or a unix socket is one server."""
    if address.startswith(("unix:", "unix-abstract:")):
        return False
    if address.startswith(("ipv4:", "ipv6:")):
        return "," in address
    if address.startswith("dns:"):
        return True
    try:
        ipaddress.ip_address(address.rsplit(":", 1)[0].strip("[]"))
    except ValueError:
        return True
    return False


class Mismatch(RuntimeError):
    """A worker that answers but computes otherwise than the server asks (checkpoint, precision)."""


class WorkerPool:
    """The workers the server fans out to; a background task re-admits the ones that recover."""

    def __init__(
        self,
        addresses: list[str],
        sha256: str,
        credentials: grpc.ChannelCredentials | None = None,
        token: str | None = None,
        check_period_s: float = 0.5,
        placement: str = "auto",
        keepalive_s: float = 5.0,
        precision: str = "fp32",
    ):
        if not addresses:
            raise ValueError("no worker addresses")
        if placement not in PLACEMENTS:
            raise ValueError(f"placement {placement!r}: one of {', '.join(PLACEMENTS)}")
        self.placement = placement
        self.sha256 = sha256
        # workers must compute as this says (WorkerInfo.precision; each stream's observation asks again)
        self.precision = precision
        self.check_period_s = check_period_s
        self._metadata = (("authorization", f"Bearer {token}"),) if token else None
        self.workers: list[WorkerHandle] = []
        options = [
            ("grpc.lb_policy_name", "round_robin"),
            *message_size_options(16),
            # a worker back after a restart is reconnected within 5 s (grpc's default backoff
            # grows to 2 minutes while it is down)
            ("grpc.max_reconnect_backoff_ms", 5000),
            # A connection whose peer stopped answering (a frozen process, a host cut off: the
            # socket stays open) is closed after a ping goes unanswered, so the balancer leaves it.
            *keepalive_channel_options(keepalive_s),
            # A name is resolved again when a connection of it fails, but by default not within
            # 30 s of the last time: a replica killed when the server knew no other (it resolved
            # before the others were up, or they were added since) left the whole address
            # UNAVAILABLE that long, live replicas or not. Measured with compose (one replica
            # killed just after a second was added): 25 s and 97 requests refused; with this and
            # the streams waiting for a ready replica (RemoteDenoiser._open), answers again after
            # 1.2 s, 0 or 1 request refused (100 ms instead of 1000 gave the same)
            ("grpc.dns_min_time_between_resolutions_ms", 1000),
        ]
        for addr in addresses:
            ch = (
                grpc.aio.secure_channel(addr, credentials, options=options)
                if credentials
                else grpc.aio.insecure_channel(addr, options=options)
            )
            handle = WorkerHandle(addr, ch, policy_pb2_grpc.DenoiseWorkerStub(ch), balanced=may_balance(addr))
            self.workers.append(handle)
        self._task: asyncio.Task | None = None
        self._changed = asyncio.Event()

    async def start(self) -> None:
        await self.check_all()
        self._task = asyncio.create_task(self._watch())

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(self.check_period_s)
            await self.check_all(only_unhealthy=True)

    async def check(self, w: WorkerHandle) -> None:
        try:
            health = await health_pb2_grpc.HealthStub(w.channel).Check(
                health_pb2.HealthCheckRequest(service=WORKER_SERVICE), timeout=1.0
            )
            if health.status != health_pb2.HealthCheckResponse.SERVING:
                raise RuntimeError(f"health {health_pb2.HealthCheckResponse.ServingStatus.Name(health.status)}")
            info = await w.stub.GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=1.0, metadata=self._metadata)
            if info.checkpoint_sha256 != self.sha256:
                raise Mismatch(f"holds checkpoint {info.checkpoint_sha256[:12]}, not {self.sha256[:12]}")
            if (info.precision or "fp32") != self.precision:
                raise Mismatch(f"computes in {info.precision or 'fp32'}, the server's setting is {self.precision}")
        except (grpc.aio.AioRpcError, RuntimeError) as exc:
            reason = exc.details() if isinstance(exc, grpc.aio.AioRpcError) else str(exc)
            if w.healthy:
                log.warning("worker %s left: %s", w.address, reason)
            elif isinstance(exc, Mismatch) and reason != w.reason:  # set up unlike the server: say so, once
                log.warning("worker %s not admitted: %s", w.address, reason)
            w.healthy, w.reason = False, reason or "unreachable"
            return
        w.machine, w.cores, w.accelerator = info.machine, frozenset(info.cores), info.accelerator
        if not w.healthy:
            where = info.device
            if info.device == "cpu" and info.cores:
                where += f" cores {describe_cores(w.cores)} of machine {info.machine[:8] or '?'}"
            elif info.accelerator:
                where += f" {info.accelerator} of machine {info.machine[:8] or '?'}"
            log.info("worker %s admitted (%s)", w.address, where)
            self._changed.set()
        w.healthy, w.reason, w.device = True, "", info.device

    async def check_all(self, only_unhealthy: bool = False) -> None:
        await asyncio.gather(*(self.check(w) for w in self.workers if not (only_unhealthy and w.healthy)))

    def trip(self, w: WorkerHandle, reason: str) -> None:
        """A failure in a request: out until its health check admits it again. Not an address
        balanced over several replicas: gRPC's balancer stops using a replica whose connection
        fails, and taking the address out would take the live replicas with it."""
        if w.balanced:
            log.warning("worker %s (one of its replicas): %s", w.address, reason)
            return
        if w.healthy:
            log.warning("worker %s tripped: %s", w.address, reason)
        w.healthy, w.reason = False, reason

    @property
    def healthy(self) -> list[WorkerHandle]:
        return [w for w in self.workers if w.healthy]

    def units(self) -> list[list[WorkerHandle]]:
        """The healthy workers, grouped by what they compute on (list order kept): the views a
        request puts on one group go to one worker of it, and the groups compute side by side.

        ``pack``: one group; ``spread``: a group per worker; ``auto``: a group per set of workers
        that compete (``competes_with``: one machine, and overlapping CPU cores or the same GPU:
        there, passes of several workers would only take turns on the same cores or GPU).
        """
        healthy = self.healthy
        if self.placement == "pack":
            return [healthy] if healthy else []
        if self.placement == "spread":
            return [[w] for w in healthy]
        units: list[list[WorkerHandle]] = []
        for w in healthy:
            joined = [u for u in units if any(w.competes_with(o) for o in u)]
            units = [u for u in units if not any(u is j for j in joined)]
            units.append([x for u in joined for x in u] + [w])
        order = {id(w): i for i, w in enumerate(healthy)}
        for u in units:
            u.sort(key=lambda w: order[id(w)])
        return sorted(units, key=lambda u: order[id(u[0])])

    def place(self, views: list[str]) -> dict[str, WorkerHandle]:
        """A worker for each view of a request (views left out: no healthy worker).

        Each view goes to the group (``units``) not yet given one of the request's views whose
        least-loaded worker has the fewest open streams, or, once every group has one, to the
        least-loaded worker the request already uses; within a group, a request's views share
        one worker, which computes them in one forward pass per step. So ``pack`` puts them all
        on the least-loaded worker, ``spread`` each on the least-loaded worker not yet given one,
        and ``auto`` spreads them over GPUs and machines and packs them on a machine's CPU
        (docs/serving.md has the measurements).
        """
        # each group's least-loaded worker (a group's load changes only once the request uses it)
        least = [min(u, key=lambda w: w.streams) for u in self.units()]
        chosen: dict[int, WorkerHandle] = {}  # group -> the worker this request uses there
        out: dict[str, WorkerHandle] = {}
        for v in views:
            fresh = [i for i in range(len(least)) if i not in chosen]
            if fresh:
                i = min(fresh, key=lambda i: least[i].streams)
                chosen[i] = least[i]
            elif chosen:
                i = min(chosen, key=lambda i: chosen[i].streams)
            else:
                break  # no healthy worker
            w = chosen[i]
            w.streams += 1
            out[v] = w
        return out

    async def wait_ready(
        self, n: int, timeout: float, stop: asyncio.Event, first_say_s: float = 5.0, say_s: float = 15.0
    ) -> bool:
        """Until ``n`` workers are healthy (True), or ``stop`` is set first (False: a SIGTERM or
        Ctrl-C while waiting ends the server now, not after ``timeout``). While it waits it logs
        which workers are not ready and why, after ``first_say_s`` and then every ``say_s``.
        TimeoutError after ``timeout``."""
        start = time.monotonic()
        say_at = start + first_say_s
        while len(self.healthy) < n:
            if stop.is_set():
                return False
            now = time.monotonic()
            if now > start + timeout:
                ready = len(self.healthy)
                raise TimeoutError(f"{ready} of {n} workers ready after {timeout:.0f}s: {self._not_ready()}")
            if now >= say_at:
                log.warning(
                    "%d of %d workers ready after %.0f s (waiting up to %.0f s, worker_ready_s): %s",
                    len(self.healthy),
                    n,
                    now - start,
                    timeout,
                    self._not_ready(),
                )
                say_at = now + say_s
            await self.check_all(only_unhealthy=True)
            with contextlib.suppress(TimeoutError):  # (a stop ends the wait at once)
                await asyncio.wait_for(stop.wait(), 0.1)
        return True

    def _not_ready(self) -> str:
        return "; ".join(f"{w.address}: {w.reason}" for w in self.workers if not w.healthy)

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
        for w in self.workers:
            await w.channel.close()


class _Stream:
    def __init__(self, worker: WorkerHandle, call):
        self.worker = worker
        self.call = call


class RemoteDenoiser:
    """One Denoise stream per view, to the pool's workers. A view whose worker fails or is late
    moves once to another healthy worker (``move``: its observation again) while the request has
    time; otherwise it is dropped. Never a hang."""

    def __init__(self, pool: WorkerPool, spec: PolicySpec):
        self.pool = pool
        self.spec = spec
        self._streams: dict[str, _Stream] = {}
        self._dropped: dict[str, str] = {}
        self._moved: dict[str, str] = {}
        self._lost: list[str] = []  # dropped since the last move() and not moved before
        self._inputs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._unconditional = False

    @property
    def alive(self) -> list[str]:
        return list(self._streams)

    @property
    def dropped(self) -> dict[str, str]:
        return self._dropped

    @property
    def moved(self) -> dict[str, str]:
        return self._moved

    def _drop(self, view: str, reason: str, trip: bool = True, movable: bool = True) -> None:
        s = self._streams.pop(view, None)
        self._dropped[view] = reason
        if s is not None:
            s.worker.streams -= 1
            if trip:
                self.pool.trip(s.worker, reason)
            s.call.cancel()
        if movable and view not in self._moved and view not in self._lost:
            self._lost.append(view)

    async def _call(self, view: str, req: policy_pb2.DenoiseRequest, deadline: float) -> policy_pb2.DenoiseReply | None:
        s = self._streams[view]
        try:
            # One deadline over the write and the read, on the loop's clock (time.monotonic):
            # no task per await, as wait_for would create (measurable at a few ms per step).
            async with asyncio.timeout_at(deadline):
                await s.call.write(req)
                reply = await s.call.read()
        except TimeoutError:
            self._drop(view, f"worker {s.worker.address} late (step deadline)")
            return None
        except asyncio.InvalidStateError:  # the stream ended before this write (its worker went)
            self._drop(view, f"worker {s.worker.address}: the stream had ended")
            return None
        except grpc.aio.AioRpcError as exc:
            # refused input is refused by every worker: not worth moving, and not the worker's fault
            refused = exc.code() == grpc.StatusCode.INVALID_ARGUMENT
            why = f"worker {s.worker.address}: {exc.code().name} {exc.details()}"
            self._drop(view, why, trip=not refused, movable=not refused)
            return None
        if reply is grpc.aio.EOF:
            self._drop(view, f"worker {s.worker.address} closed the stream")
            return None
        return reply

    async def _replica(self, view: str, deadline: float, tries: int = 1) -> str | None:
        """The worker process that took this view's stream (its initial metadata); None if none
        said so by ``deadline`` (a replica frozen, or cut off behind a network that drops).

        ``tries`` > 1 (moving a view to a balanced address): that many streams at once, which
        the balancer gives to different replicas; the first to answer is kept, the rest cancelled."""
        s = self._streams[view]
        calls = [s.call] + [
            s.worker.stub.Denoise(metadata=self.pool._metadata, wait_for_ready=True) for _ in range(tries - 1)
        ]
        waits = {asyncio.ensure_future(c.initial_metadata()): c for c in calls}
        kept, replica = None, None
        try:
            while waits and kept is None:
                timeout = deadline - time.monotonic()
                done, _ = await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
                if not done:
                    break  # late
                for f in done:
                    call = waits.pop(f)
                    md = None if f.exception() else f.result()
                    if kept is None and (md is not None or not waits):
                        # not told (the last stream failed: its observation will say how): a group of its own
                        kept, replica = call, (md.get(REPLICA_KEY) if md else None) or uuid.uuid4().hex
        finally:
            for f in waits:
                f.cancel()
            for call in calls:
                if call is not kept and call is not s.call:
                    call.cancel()
        if kept is not None:
            s.call = kept
        return replica

    async def open(self, inputs, unconditional, deadline) -> None:
        self._inputs, self._unconditional = inputs, unconditional
        await self._open(list(inputs), deadline)

    async def move(self, deadline: float) -> list[str]:
        lost, self._lost = self._lost, []
        if not lost or time.monotonic() >= deadline:
            return []
        why = {v: self._dropped[v] for v in lost}
        for v in lost:
            self._moved[v] = ""  # once per request: a failure of the move is final
        await self._open(lost, deadline, tries=2)
        done = [v for v in lost if v in self._streams]
        for v in lost:
            if v in done:
                del self._dropped[v]
                self._moved[v] = f"moved to worker {self._streams[v].worker.address} ({why[v]})"
            else:
                del self._moved[v]
        if done:
            log.info("views %s moved to other workers: %s", ",".join(done), "; ".join(why[v] for v in done))
        return done

    async def _open(self, views: list[str], deadline: float, tries: int = 1) -> None:
        """Streams for ``views`` on the workers the pool places them on, their observations sent
        (``tries``: streams tried at once per view behind a balanced address, see ``_replica``)."""
        placed = self.pool.place(views)
        for v in views:
            if v not in placed:
                self._dropped.setdefault(v, "no healthy worker")
        for v, w in placed.items():
            # behind a balanced address a stream waits (within its deadline) for a replica to be
            # ready, rather than failing while the name is resolved again after one went away
            self._streams[v] = _Stream(w, w.stub.Denoise(metadata=self.pool._metadata, wait_for_ready=w.balanced))
        # The views that share a worker form a group there: one forward pass for all of them per
        # step. Behind a balanced address the streams may have reached different replicas (a
        # replica would wait for members that went elsewhere): each stream says which replica took
        # it, and the views are grouped by that.
        balanced = [v for v in placed if placed[v].balanced]
        replicas: dict[str, str | None] = {}
        if balanced:
            # half the time to hear which replica took each stream, half for the observations
            told_by = time.monotonic() + (deadline - time.monotonic()) / 2
            replicas = dict(zip(balanced, await asyncio.gather(*(self._replica(v, told_by, tries) for v in balanced))))
            for v in balanced:
                if replicas[v] is None:  # its replica is frozen or cut off: the others go on without it
                    self._drop(v, f"worker {placed.pop(v).address} late (no replica took the stream)")
        per_worker: dict[tuple[str, str], list[str]] = {}
        for v, w in placed.items():
            per_worker.setdefault((w.address, replicas.get(v, "")), []).append(v)
        group: dict[str, tuple[str, int]] = {}
        for vs in per_worker.values():
            gid = uuid.uuid4().hex
            for v in vs:
                group[v] = (gid, len(vs)) if len(vs) > 1 else ("", 0)
        reqs = {}
        for v in placed:
            frames, state = self._inputs[v]
            obs = policy_pb2.DenoiseObservation(
                checkpoint_sha256=self.pool.sha256,
                view=v,
                frames=to_tensor(frames),
                unconditional=self._unconditional,
                group=group[v][0],
                group_size=group[v][1],
                precision=self.pool.precision,
            )
            if state.shape[-1]:
                obs.state.CopyFrom(to_tensor(state))
            reqs[v] = policy_pb2.DenoiseRequest(observation=obs)
        await asyncio.gather(*(self._call(v, r, deadline) for v, r in reqs.items()))

    async def step(self, k, xs, deadline):
        views = [v for v in xs if v in self._streams]
        reqs = {
            v: policy_pb2.DenoiseRequest(step=policy_pb2.DenoiseStep(k=k, x=to_tensor(xs[v].astype(np.float32))))
            for v in views
        }
        if len(views) == 1:  # no gather (and its task) for a single view
            replies = [await self._call(views[0], reqs[views[0]], deadline)]
        else:
            replies = await asyncio.gather(*(self._call(v, reqs[v], deadline) for v in views))
        eps, eps_u = {}, {}
        for v, r in zip(views, replies):
            if r is None:
                continue
            eps[v] = from_tensor(r.eps)
            if r.eps_uncond.shape:
                eps_u[v] = from_tensor(r.eps_uncond)
        return eps, eps_u

    async def close(self) -> None:
        # Cancelled rather than half-closed and awaited: the worker has nothing more to say, and
        # waiting for the half-close to complete would put a round trip on the reply's path.
        for v in list(self._streams):
            s = self._streams.pop(v)
            s.worker.streams -= 1
            s.call.cancel()


# -- the Policy service -------------------------------------------------------------------------


@dataclass
class Session:
    generator: torch.Generator
    scheduler: Any
    last_seq: int = -1
    running: int = 0  # requests of this session being computed
    used: float = field(default_factory=time.monotonic)


def chunk_to_base(chunk_n: np.ndarray, spec: PolicySpec, reference: str, eef_quat_wxyz: np.ndarray) -> np.ndarray:
    """(Tp, 7) normalised chunk in the reference view's frame -> base-frame actions, unnormalised."""
    a = spec.normalizer.unnormalize_action(chunk_n.astype(np.float64))
    if spec.action_space == "camera":
        a = from_space(a, "camera", R_ext=spec.cameras[reference].R_ext)
    elif spec.action_space == "eef":
        a = eef_chunk_to_base(a, quat_wxyz_to_matrix(eef_quat_wxyz))
    return a


class PolicyService(policy_pb2_grpc.PolicyServicer):
    def __init__(
        self,
        spec: PolicySpec,
        noise: NoiseConfig,
        default_views: list[str],
        max_sessions: int = 256,
        request_timeout_s: float = DEFAULT_TIMEOUT_S,
        precision: str = "fp32",
        max_reach_m: float = MAX_REACH_M,
    ):
        self.spec = spec
        self.precision = precision  # what the model's passes compute in (PolicyInfo), wherever they run
        self.default_views = default_views
        self.max_sessions = max_sessions
        self.request_timeout_s = request_timeout_s
        self.max_reach_m = max_reach_m
        self.scheduler = make_inference_scheduler(noise)
        self.backend: Any = None  # () -> Denoiser, set once the model or the workers are ready
        self.sessions: dict[str, Session] = {}
        self.instance = uuid.uuid4().hex  # this process (PolicyInfo, ActionReply: server_instance)
        self.requests = 0
        self.degraded = 0
        # Frames are decoded off the event loop; their decode is numpy/OpenCV, released from the GIL.
        from concurrent.futures import ThreadPoolExecutor

        self._cpu = ThreadPoolExecutor(max_workers=2, thread_name_prefix="decode")

    def info(self) -> policy_pb2.PolicyInfo:
        s = self.spec
        out = policy_pb2.PolicyInfo(
            proto_version=POLICY_PROTO_VERSION,
            model_id=s.model_id,
            checkpoint_sha256=s.sha256,
            action_space=s.action_space,
            state_frame=s.state_frame,
            obs_horizon=s.To,
            pred_horizon=s.Tp,
            n_action_steps=s.n_action_steps,
            control_hz=s.control_hz,
            image_width=s.image_size[1],
            image_height=s.image_size[0],
            ddim_steps=len(self.scheduler.timesteps),
            unconditional=s.unconditional,
            default_views=self.default_views,
            server_instance=self.instance,
            precision=self.precision,
        )
        for name in s.camera_order:
            c = s.cameras[name]
            out.cameras.add(
                name=name,
                width=c.width,
                height=c.height,
                K=c.K.flatten().tolist(),
                R_ext=c.R_ext.flatten().tolist(),
                position=c.position.tolist(),
                default_gamma=1.0 / len(self.default_views) if name in self.default_views else 0.0,
            )
        return out

    async def GetPolicyInfo(self, request, context) -> policy_pb2.PolicyInfo:
        return self.info()

    async def Reset(self, request, context) -> policy_pb2.ResetReply:
        try:
            check_session_id(request.session_id)  # (any id, of any length, was kept as a session)
        except InvalidRequest as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        existed = self.sessions.pop(request.session_id, None)  # a running request sees it is gone and stops
        if request.HasField("seed"):
            self._session(request.session_id).generator.manual_seed(int(request.seed))
        return policy_pb2.ResetReply(existed=existed is not None)

    def _session(self, sid: str) -> Session:
        s = self.sessions.get(sid)
        if s is None:
            if len(self.sessions) >= self.max_sessions:  # forget the least recently used idle session
                idle = [k for k, v in self.sessions.items() if not v.running]
                if idle:
                    del self.sessions[min(idle, key=lambda k: self.sessions[k].used)]
            g = torch.Generator()
            g.seed()
            s = self.sessions[sid] = Session(g, copy.deepcopy(self.scheduler))
        s.used = time.monotonic()
        return s

    async def GetAction(self, request: policy_pb2.ActionRequest, context) -> policy_pb2.ActionReply:
        recv_ns = time.time_ns()
        t0 = time.perf_counter()
        if self.backend is None:
            await context.abort(grpc.StatusCode.UNAVAILABLE, "the model is still loading (health: NOT_SERVING)")
        try:
            parsed = parse(request, self.spec, self.default_views, self.max_reach_m)
        except InvalidRequest as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        session = self._session(parsed.session_id)
        if parsed.seq <= session.last_seq:
            await context.abort(
                grpc.StatusCode.ABORTED, f"seq {parsed.seq} is not newer than this session's last ({session.last_seq})"
            )
        session.last_seq = parsed.seq  # an older request still running stops at its next step

        def superseded() -> str | None:
            if self.sessions.get(parsed.session_id) is not session:
                return "the session was reset"
            if session.last_seq != parsed.seq:
                return f"superseded by seq {session.last_seq}"  # a late chunk is worthless: the newer one wins
            return None

        remaining = context.time_remaining()
        deadline = time.monotonic() + (remaining if remaining is not None else self.request_timeout_s)
        session.running += 1
        try:
            return await self._act(parsed, session, deadline, recv_ns, t0, context, superseded)
        finally:
            session.running -= 1

    async def _act(
        self, parsed: Parsed, session: Session, deadline: float, recv_ns: int, t0: float, context, superseded
    ) -> policy_pb2.ActionReply:
        loop = asyncio.get_running_loop()
        try:
            inputs = await loop.run_in_executor(self._cpu, model_inputs, parsed, self.spec)
        except InvalidRequest as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        decode_ms = (time.perf_counter() - t0) * 1e3
        gen = torch.Generator().manual_seed(parsed.seed) if parsed.seed is not None else session.generator
        x_T = torch.randn((self.spec.Tp, 7), generator=gen).numpy()
        denoiser = self.backend()
        try:
            result = await sample_composed(
                denoiser,
                inputs,
                self.spec,
                parsed.views,
                parsed.gamma,
                session.scheduler,
                x_T,
                deadline,
                parsed.unconditional,
                superseded,
            )
        except Superseded as exc:
            await context.abort(grpc.StatusCode.ABORTED, f"seq {parsed.seq}: {exc}")
        except Unavailable as exc:
            await context.abort(grpc.StatusCode.UNAVAILABLE, str(exc))
        except CompositionError as exc:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        except NotFinite as exc:
            log.warning("GetAction seq %d of %s: %s", parsed.seq, parsed.session_id, exc)
            await context.abort(grpc.StatusCode.INTERNAL, f"{exc}: no action sent")
        finally:
            await denoiser.close()
        actions = chunk_to_base(result.chunk, self.spec, result.reference, parsed.eef_quat_wxyz[-1])
        self.requests += 1
        self.degraded += bool(result.dropped or result.moved)
        reply = policy_pb2.ActionReply(
            seq=parsed.seq,
            start_index=self.spec.To - 1,
            obs_stamp_ns=parsed.obs_stamp_ns,
            views_used=result.views_used,
            degraded=bool(result.dropped or result.moved),
            degraded_reasons=[f"{v}: {why}" for v, why in {**result.dropped, **result.moved}.items()],
            checkpoint_sha256=self.spec.sha256,
            server_instance=self.instance,
        )
        for row in actions:
            reply.actions.append(action_msg(EefDelta(row[0:3], row[3:6], float(row[6]))))
        steps = result.step_ms or [0.0]
        reply.timing.CopyFrom(
            policy_pb2.Timing(
                decode_ms=decode_ms,
                encode_ms=result.encode_ms,
                step_p50_ms=statistics.median(steps),
                step_max_ms=max(steps),
                total_ms=(time.perf_counter() - t0) * 1e3,
                server_receive_ns=recv_ns,
                server_send_ns=time.time_ns(),
            )
        )
        return reply


# -- security: bearer token ---------------------------------------------------------------------


class BearerTokenInterceptor(grpc.aio.ServerInterceptor):
    """Every call but health and reflection needs ``authorization: Bearer <token>`` (constant-time compare)."""

    def __init__(self, token: str):
        if not token:
            raise ValueError("empty bearer token")
        self._expected = f"Bearer {token}".encode()

    async def intercept_service(self, continuation, details):
        if details.method.startswith(OPEN_METHODS) or bearer_matches(details.invocation_metadata, self._expected):
            return await continuation(details)
        handler = await continuation(details)

        async def deny_unary(request, context):
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")

        async def deny_stream(request_iterator, context):
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")
            yield  # pragma: no cover  (makes this an async generator)

        if handler is None:
            return None
        if handler.unary_unary:
            return grpc.unary_unary_rpc_method_handler(
                deny_unary, handler.request_deserializer, handler.response_serializer
            )
        return grpc.stream_stream_rpc_method_handler(
            deny_stream, handler.request_deserializer, handler.response_serializer
        )


# -- the server process -------------------------------------------------------------------------


class LocalWorkers:
    """Worker processes on loopback, started before any gRPC object exists in this process (never
    fork after gRPC is initialised); each one's address comes from its ready line. ``supervise``
    restarts one that exits (a crash, the OOM killer, kill -9) on the same address."""

    def __init__(self, cfg, n: int, log_dir: Path | None = None):
        import tempfile

        self.cfg = cfg
        self.n = n
        # the workers' stderr (worker-N.log): in log_dir, or in a folder of our own removed at the
        # end; either way a worker that exits is reported with its last line
        self._own_logs = tempfile.TemporaryDirectory(prefix="viewscale-workers-") if log_dir is None and n else None
        self.log_dir = Path(self._own_logs.name) if self._own_logs else log_dir
        self.procs: list[Any] = []
        self.addresses: list[str] = []
        # why serving ended when every local worker, at its first start, exited before it had
        # loaded the model (and no other worker was given): ``supervise`` stops then
        self.failed: str | None = None

    def last_words(self, i: int) -> str:
        """The last line worker ``i`` wrote to its stderr ('' if none)."""
        if self.log_dir is None:
            return ""
        try:
            with open(self.log_dir / f"worker-{i}.log", "rb") as f:
                f.seek(0, 2)
                f.seek(max(0, f.tell() - 4096))
                lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
        except OSError:
            return ""
        return lines[-1] if lines else ""

    def _spawn(self, i: int, listen: str, stdout: int):
        import subprocess
        import sys

        cmd = [sys.executable, "-m", "services.policy", "worker", "--checkpoint", str(self.cfg.checkpoint)]
        cmd += ["--listen", listen, "--device", self.cfg.device, "--threads", str(self.cfg.threads)]
        cmd += ["--precision", self.cfg.precision]
        env = child_env()  # the workers die with the server, however it dies
        if self.cfg.token:
            env["VIEWSCALE_TOKEN"] = self.cfg.token  # not on the command line (ps shows it)
        err = open(self.log_dir / f"worker-{i}.log", "a") if self.log_dir else None
        try:
            return subprocess.Popen(cmd, stdout=stdout, stderr=err or subprocess.DEVNULL, text=True, env=env)
        finally:
            if err:
                err.close()

    def __enter__(self) -> LocalWorkers:
        import subprocess

        for i in range(self.n):
            self.procs.append(self._spawn(i, "127.0.0.1:0", subprocess.PIPE))
        try:
            for i, p in enumerate(self.procs):
                for line in p.stdout:  # "listening worker ..." then "ready worker <addr>"
                    if line.startswith("listening worker "):
                        self.addresses.append(line.split()[2])
                        break
                else:
                    said = self.last_words(i)
                    raise RuntimeError(
                        f"worker {i} exited with code {p.wait()} before listening" + (f": {said}" if said else "")
                    )
        except BaseException:
            self.__exit__()
            raise
        return self

    async def supervise(self, stop: asyncio.Event, period_s: float = 0.5, quick_exit_s: float = 30.0) -> None:
        """Until ``stop``, restart a worker that exited, on its address: the pool's health check
        re-admits it once its model is loaded. One that keeps exiting soon after its start waits
        longer each time (1 s doubling to 60 s), so a worker that cannot start does not spin. (A
        Ctrl-C reaches the workers too: stopping, the server restarts none.)

        When every local worker's first process exits before it has loaded the model (weights that
        do not fit it, a device that fails), and no other worker was given, a restart would fail
        the same way: it sets ``failed`` with the first one's error and ``stop``, at once rather
        than when ``worker_ready_s`` runs out."""
        import subprocess

        loop = asyncio.get_running_loop()
        started = [time.monotonic()] * len(self.procs)
        delay = [0.5] * len(self.procs)  # doubled at a quick exit: 1 s the first time
        due: list[float | None] = [None] * len(self.procs)
        first = list(self.procs)  # the processes started with the server (their stdout is a pipe)
        never_ready: dict[int, str] = {}  # of those, the ones that exited before their ready line
        while not stop.is_set():
            await asyncio.sleep(period_s)
            for i, p in enumerate(self.procs):
                if stop.is_set():
                    return
                now = time.monotonic()
                if due[i] is None and p.poll() is not None:
                    if p is first[i] and "ready worker " not in (p.stdout.read() if p.stdout else ""):
                        said = self.last_words(i).removeprefix("error: ")
                        never_ready[i] = f"local worker {i} exited with code {p.returncode}" + (
                            f": {said}" if said else ""
                        )
                        if len(never_ready) == len(self.procs) and not self.cfg.worker:
                            self.failed = f"no local worker could load the model; {never_ready[min(never_ready)]}"
                            stop.set()
                            return
                    delay[i] = min(2 * delay[i], 60.0) if now - started[i] < quick_exit_s else 1.0
                    due[i] = now + delay[i]
                    log.warning(
                        "local worker %d (%s) exited with code %s%s: restarting it in %.0f s",
                        i,
                        self.addresses[i],
                        p.returncode,
                        f" ({said})" if (said := self.last_words(i)) else "",
                        delay[i],
                    )
                    if p.stdout:
                        p.stdout.close()
                if due[i] is not None and now >= due[i]:
                    # forked off the loop: a moment, but not the loop's
                    self.procs[i] = await loop.run_in_executor(
                        None, self._spawn, i, self.addresses[i], subprocess.DEVNULL
                    )
                    started[i], due[i] = time.monotonic(), None

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except Exception:
                p.kill()
                p.wait()
            if p.stdout:
                p.stdout.close()
        if self._own_logs is not None:
            self._own_logs.cleanup()


def rig_cameras(rig: str, task: str | None, width: int, height: int) -> dict[str, CameraSpec]:
    """Cameras of a rig file, calibrated at the checkpoint's frame size."""
    r = load_rig(rig, task)  # sim rigs move with the task's framing (services.core.rig)
    return {n: CameraSpec(n, width, height, c.K(width, height), c.R_ext, c.position) for n, c in r.cameras.items()}


def load_spec(cfg) -> tuple[PolicySpec, NoiseConfig, dict[str, Any]]:
    """The checkpoint's PolicySpec and its noise config; no weights. ``cfg.rig``'s cameras are added,
    and take the place of the checkpoint's of the same name (a camera recalibrated since training
    is served where it is now; each that differs is logged)."""
    info = read_info(cfg.checkpoint)
    noise = model_config(info, cfg.checkpoint).noise  # (a config this version cannot build: one line)
    sha = checkpoint_sha256(cfg.checkpoint)
    extra = {}
    if cfg.rig:
        cal = next((c for c in (info.get("calibration") or {}).values() if c), None)
        w, h = (
            (int(cal["source_width"]), int(cal["source_height"])) if cal else tuple(info["model"]["image_size"][::-1])
        )
        # a sim rig is framed per task: by default the checkpoint's (before: the default framing,
        # which for a checkpoint of another task placed every camera elsewhere)
        task = cfg.task or next(iter(info.get("tasks") or []), None)
        extra = rig_cameras(cfg.rig, task, w, h)
    spec = PolicySpec.from_info(info, sha, model_id(cfg.checkpoint))
    for name in sorted(set(extra) & set(spec.cameras)):
        a, b = spec.cameras[name], extra[name]
        if moved := camera_gap(
            a.R_ext, a.position, a.K, (a.width, a.height), b.R_ext, b.position, b.K, (b.width, b.height)
        ):
            log.warning(
                "camera %s: --rig %s differs from the checkpoint's training calibration (%s): served with the rig's",
                name,
                cfg.rig,
                moved,
            )
    # the rig's cameras take the place of the checkpoint's of the same name: a camera recalibrated
    # (moved) since training is served where it is now (before: the training calibration won)
    spec = dataclasses.replace(spec, cameras={**spec.cameras, **extra})
    views = list(cfg.views or spec.train_views)
    unknown = [v for v in views if v not in spec.cameras]
    if unknown:
        raise ValueError(
            f"views: no calibration for {', '.join(unknown)} (the checkpoint knows "
            f"{', '.join(spec.camera_order)}; add a rig with --rig)"
        )
    transforms = {v: view_transform(spec.action_space, spec.cameras[v].R_ext) for v in spec.cameras}
    check_orthogonal(spec.normalizer, transforms)  # refuse a checkpoint whose views cannot be composed
    return spec, noise, info


async def serve_policy(cfg, stop: asyncio.Event, worker_addresses: list[str], announce=print) -> int:
    """Run the Policy server until ``stop``: listen (NOT_SERVING), get the model or the workers ready, SERVING."""
    from services.policy.worker import add_health_and_reflection, server_credentials, set_serving

    spec, noise, _ = load_spec(cfg)
    views = list(cfg.views or spec.train_views)
    service = PolicyService(spec, noise, views, cfg.max_sessions, cfg.request_timeout_s, cfg.precision, cfg.max_reach_m)
    interceptors = [BearerTokenInterceptor(cfg.token)] if cfg.token else []
    server = grpc.aio.server(
        interceptors=interceptors,
        options=[
            *message_size_options(cfg.max_message_mb),
            *keepalive_server_options(),  # the robots' pings (PolicyClient keepalive_s)
            *EXCLUSIVE_PORT,  # a port another process holds: an error, not shared
        ],
    )
    policy_pb2_grpc.add_PolicyServicer_to_server(service, server)
    health = add_health_and_reflection(server, [POLICY_SERVICE])
    await set_serving(health, [POLICY_SERVICE], False)
    creds = server_credentials(cfg.tls)
    port = listen_on(server, cfg.listen, creds)
    address = f"{cfg.listen.rsplit(':', 1)[0]}:{port}"
    await server.start()
    announce(f"listening policy {address}")
    if open_to_others(cfg.listen) and not cfg.token:
        log.warning(
            "%s is open beyond loopback with no token: whoever reaches it can call GetAction "
            "(set VIEWSCALE_TOKEN, here and in the clients)",
            address,
        )
    loop = asyncio.get_running_loop()
    engine = pool = None
    try:  # whatever fails while starting, the server is stopped before the loop closes
        if cfg.in_process or not worker_addresses:
            engine = await loop.run_in_executor(
                None, lambda: ModelEngine.open(cfg.checkpoint, cfg.device, cfg.threads, precision=cfg.precision)
            )
            service.backend = lambda: LocalDenoiser(engine)
            mode = "in-process"
        else:
            creds_out = None
            if cfg.tls.ca:
                creds_out = grpc.ssl_channel_credentials(root_certificates=Path(cfg.tls.ca).read_bytes())
            pool = WorkerPool(
                worker_addresses,
                spec.sha256,
                creds_out,
                cfg.token,
                placement=cfg.placement,
                keepalive_s=cfg.worker_keepalive_s,
                precision=cfg.precision,
            )
            await pool.start()
            if not await pool.wait_ready(1, cfg.worker_ready_s, stop):
                log.info("stopped before any worker was ready")
                return 0
            service.backend = lambda: RemoteDenoiser(pool, spec)
            ready, n = len(pool.healthy), len(worker_addresses)
            mode = f"{n} worker{'s' * (n != 1)}"
            if ready < n:
                mode = f"{ready} of {n} workers ready (the rest are admitted as they answer)"
        await set_serving(health, [POLICY_SERVICE], True)
        log.info(
            "policy %s on %s: %s, views %s, precision %s, %s",
            spec.model_id,
            address,
            spec.action_space,
            ",".join(views),
            cfg.precision,
            mode,
        )
        announce(f"ready policy {address}")
        await stop.wait()
        await set_serving(health, [POLICY_SERVICE], False)
    finally:
        await server.stop(grace=2.0)
        if pool is not None:
            await pool.close()
        if engine is not None:
            engine.close()
    return 0
