"""The robot-side client of the policy server: numpy, grpcio and protobuf only (never torch).

    client = PolicyClient("127.0.0.1:50051")          # connects, retries, checks GetPolicyInfo
    chunk = client.get_action(frames, states)           # frames: camera -> To (image, stamp_ns)
    chunk.actions                                       # (Tp, 7) base frame: dp, drot (axis-angle), gripper
    runner = ChunkRunner(client, control_hz=20)         # at the control rate, from a queue:
    action, fresh = runner.act(tick, frames_now, state_now)

``ChunkRunner`` executes a chunk's actions one per control tick, asks for the next chunk ahead of
time from the measured latency, drops the actions that went stale while a request was in flight,
and never blocks the control loop: when no action is queued for a tick it answers a hold (zero
motion, the last gripper target) and counts an underrun. In lockstep (``blocking=True``) there is
no wall clock to race, so it waits for the chunk instead, and for a server that is down or not
serving yet (restarting, its model loading), within the client's deadline.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from services.core.robot_types import kept_gripper
from services.core.tensors import encode_jpeg, to_tensor
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy import POLICY_PROTO_VERSION
from services.policy.transport import bad_target, keepalive_channel_options, message_size_options

Image = bytes | np.ndarray  # JPEG bytes, or (H, W, 3) uint8 RGB

POLICY_SERVICE = policy_pb2.DESCRIPTOR.services_by_name["Policy"].full_name  # its name in grpc.health.v1
RETRY_S = 0.2  # lockstep: how often a server that is not serving is asked again


class PolicyError(RuntimeError):
    """The server refused or could not answer; ``code`` is the gRPC status (None: not a gRPC error)."""

    def __init__(self, message: str, code: grpc.StatusCode | None = None):
        super().__init__(message)
        self.code = code


class PolicyChanged(PolicyError):
    """After a reconnect the server holds another checkpoint (or protocol): stop and look."""


@dataclass(frozen=True)
class State:
    """The robot at one observation step (base frame)."""

    eef_pos: np.ndarray  # (3,)
    eef_quat_wxyz: np.ndarray  # (4,)
    gripper: float
    stamp_ns: int


@dataclass(frozen=True)
class ActionChunk:
    actions: np.ndarray  # (Tp, 7) base frame
    start_index: int  # the action for the observation's own step
    obs_stamp_ns: int
    views_used: tuple[str, ...]
    degraded: bool
    degraded_reasons: tuple[str, ...]
    timing: dict[str, float]
    latency_s: float  # request to reply, measured here


def _frame(image: Image, stamp_ns: int, quality: int) -> policy_pb2.Frame:
    if isinstance(image, (bytes, bytearray)):
        return policy_pb2.Frame(jpeg=bytes(image), stamp_ns=stamp_ns)
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"an image must be JPEG bytes or (H, W, 3) uint8 RGB, got {arr.dtype} {arr.shape}")
    return (
        policy_pb2.Frame(jpeg=encode_jpeg(arr, quality), stamp_ns=stamp_ns)
        if quality
        else policy_pb2.Frame(rgb=to_tensor(arr), stamp_ns=stamp_ns)
    )


def tls_hint(error: str, tls: bool) -> str:
    """What a connection error means when client and server disagree on TLS (gRPC names only the
    symptom: a plaintext client's connection is closed by a TLS server, a TLS client's handshake
    with a plaintext server fails)."""
    if not tls and "Socket closed" in error:
        return "; if the server serves TLS (`--set tls.cert=...`), give the client its CA certificate (tls_ca)"
    if tls and "WRONG_VERSION_NUMBER" in error:
        return "; the server does not serve TLS: connect without tls_ca"
    if tls and "CERTIFICATE_VERIFY_FAILED" in error:
        return "; the server's certificate is not signed by the CA given (tls_ca)"
    return ""


class PolicyClient:
    """One connection to a policy server, one session (``session_id``: one robot), reset on connect.
    Thread-safe for one call at a time per session. ``keepalive_s``: ping the server this often and
    leave a connection whose ping goes unanswered as long (0: never; docs/serving.md)."""

    def __init__(
        self,
        address: str,
        *,
        session_id: str = "robot",
        token: str | None = None,
        tls_ca: bytes | None = None,
        timeout_s: float = 5.0,
        connect_timeout_s: float = 30.0,
        jpeg_quality: int = 90,
        max_message_mb: int = 16,
        keepalive_s: float = 5.0,
    ):
        if why := bad_target(address):
            raise PolicyError(f"{address}: {why}", grpc.StatusCode.INVALID_ARGUMENT)
        for name, value in (("timeout_s", timeout_s), ("connect_timeout_s", connect_timeout_s)):
            if not value > 0:
                raise ValueError(f"{name} must be positive, got {value}")
        if not 0 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 0 (raw RGB) to 100, got {jpeg_quality}")
        if max_message_mb < 1:
            raise ValueError(f"max_message_mb must be at least 1, got {max_message_mb}")
        if tls_ca is not None and b"-----BEGIN CERTIFICATE-----" not in tls_ca:
            # (before: every connection failed with 'Failed to create security handshaker')
            raise ValueError("tls_ca holds no PEM certificate (-----BEGIN CERTIFICATE-----): give the CA's certificate")
        self.address = address
        self.session_id = session_id
        self.tls = tls_ca is not None
        self.timeout_s = timeout_s
        # a lockstep runner waited a whole deadline for this server to serve, in vain: its next
        # requests do not wait, until one is answered (ChunkRunner)
        self.waited_out = False
        self.jpeg_quality = jpeg_quality  # raw numpy frames are sent as JPEG at this quality (0: raw RGB)
        self._metadata = (("authorization", f"Bearer {token}"),) if token else None
        options = [
            *message_size_options(max_message_mb),
            ("grpc.enable_retries", 0),  # a late chunk is worthless: never retried blindly
            # a server that stopped answering with the connection open (frozen, its host gone, a
            # NAT that forgot an idle robot) is left after an unanswered ping, and the channel
            # connects again -- to another of the address's servers, or to this one once back --
            # rather than every GetAction running into the dead connection to its deadline
            *keepalive_channel_options(keepalive_s),
        ]
        self.channel = (
            grpc.secure_channel(address, grpc.ssl_channel_credentials(tls_ca), options=options)
            if tls_ca is not None
            else grpc.insecure_channel(address, options=options)
        )
        self.stub = policy_pb2_grpc.PolicyStub(self.channel)
        self._seq = 0
        self._lock = threading.Lock()
        self.info = self._connect(connect_timeout_s)
        self._verified = {self.info.server_instance}  # server processes whose PolicyInfo is this one
        self.server_changes = 0  # answers from a server process not seen before (restart, replica)
        self.reset()  # a fresh session: a client restarted under the same id starts its seq again at 1

    # -- connection ----------------------------------------------------------------------------
    def _connect(self, timeout_s: float) -> policy_pb2.PolicyInfo:
        """Retry until the server answers GetPolicyInfo (it may still be starting), then until its
        health says SERVING: it describes its policy while the model loads or its first worker
        comes up, but answers GetAction only after (UNAVAILABLE before)."""
        deadline = time.monotonic() + timeout_s
        delay, last = 0.1, ""
        while True:
            try:
                info = self.stub.GetPolicyInfo(
                    policy_pb2.PolicyInfoRequest(),
                    timeout=min(5.0, timeout_s),
                    metadata=self._metadata,
                    wait_for_ready=True,
                )
                break
            except grpc.RpcError as exc:
                if exc.code() in (grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.PERMISSION_DENIED):
                    raise PolicyError(f"{self.address}: {exc.details()}", exc.code()) from None
                last = f"{exc.code().name}: {exc.details()}"
            if time.monotonic() + delay > deadline:
                raise PolicyError(
                    f"no policy server at {self.address} after {timeout_s:.0f}s ({self._why_not(last)})",
                    grpc.StatusCode.UNAVAILABLE,
                )
            time.sleep(delay)
            delay = min(2 * delay, 1.0)
        if info.proto_version != POLICY_PROTO_VERSION:
            raise PolicyChanged(
                f"{self.address} speaks policy protocol v{info.proto_version}, this client "
                f"v{POLICY_PROTO_VERSION}: update one of them"
            )
        self._wait_serving(deadline, timeout_s)
        return info

    def _why_not(self, last: str) -> str:
        """Why the channel cannot connect. A call that waits for the connection ends in
        DEADLINE_EXCEEDED, which hides the reason; one that does not wait gets the channel's last
        connection error (connection refused, a name that does not resolve, a bad address), with
        what it means when the two ends disagree on TLS."""
        if last.startswith("DEADLINE_EXCEEDED"):
            try:
                self.stub.GetPolicyInfo(policy_pb2.PolicyInfoRequest(), timeout=1.0, metadata=self._metadata)
            except grpc.RpcError as exc:
                if exc.code() != grpc.StatusCode.DEADLINE_EXCEEDED:
                    last = f"{exc.code().name}: {exc.details()}"
        return last + tls_hint(last, self.tls)

    def _health(self, timeout_s: float) -> tuple[bool, str]:
        """(serving, what the health check said): one ``grpc.health.v1`` check of the policy
        service. A server (or proxy) without the health entry counts as serving: GetAction will tell."""
        req = health_pb2.HealthCheckRequest(service=POLICY_SERVICE)
        try:
            status = health_pb2_grpc.HealthStub(self.channel).Check(req, timeout=timeout_s).status
        except grpc.RpcError as exc:
            said = f"{exc.code().name}: {exc.details()}"
            return exc.code() in (grpc.StatusCode.UNIMPLEMENTED, grpc.StatusCode.NOT_FOUND), said
        said = health_pb2.HealthCheckResponse.ServingStatus.Name(status)
        return status == health_pb2.HealthCheckResponse.SERVING, said

    def _wait_serving(self, deadline: float, timeout_s: float) -> None:
        delay = 0.1
        while True:
            serving, last = self._health(min(5.0, timeout_s))
            if serving:
                return
            if time.monotonic() + delay > deadline:
                raise PolicyError(
                    f"the policy server at {self.address} answers but is not serving after {timeout_s:.0f}s "
                    f"(health {last}: its model is loading, or none of its workers is ready)",
                    grpc.StatusCode.UNAVAILABLE,
                )
            time.sleep(delay)
            delay = min(2 * delay, 1.0)

    def serving(self) -> bool:
        """Whether the server's health says SERVING now (False: down, starting, or its model still
        loading)."""
        return self._health(2.0)[0]

    def _check_server(self, reply: policy_pb2.ActionReply) -> None:
        """Refuse a chunk the held PolicyInfo does not describe.

        Another checkpoint (the server restarted with a new one, or a load balancer reached another):
        its actions were computed with other normalisation and views. Another server process
        (``server_instance``: a restart, a reconnect to another replica, a proxy's other backend):
        its PolicyInfo is asked for and compared field by field -- the same, and it is used from
        now on (``server_changes`` counts it); other views, calibration, horizons or settings, and
        the chunk is refused."""
        if reply.checkpoint_sha256 and reply.checkpoint_sha256 != self.info.checkpoint_sha256:
            try:
                now = self._connect(self.timeout_s).model_id
            except PolicyError:
                now = "another checkpoint"
            raise PolicyChanged(
                f"{self.address} now serves {now} ({reply.checkpoint_sha256[:12]}), not {self.info.model_id} "
                f"({self.info.checkpoint_sha256[:12]}): reconnect to use it"
            )
        if not reply.server_instance or reply.server_instance in self._verified:
            return
        now = self._connect(self.timeout_s)
        differ = [
            f.name
            for f in now.DESCRIPTOR.fields
            if f.name != "server_instance" and getattr(now, f.name) != getattr(self.info, f.name)
        ]
        if differ:
            raise PolicyChanged(
                f"{self.address} is now answered by another server process (restarted, or another "
                f"replica) whose {', '.join(differ)} differ from the one connected to: reconnect to use it"
            )
        with self._lock:
            self._verified.add(now.server_instance)
            self.server_changes += 1

    # -- calls ---------------------------------------------------------------------------------
    def request(
        self,
        frames: Mapping[str, Sequence[tuple[Image, int]]],
        states: Sequence[State],
        views: Sequence[str] | None = None,
        gamma: Mapping[str, float] | None = None,
        seed: int | None = None,
        unconditional: bool = False,
    ) -> policy_pb2.ActionRequest:
        """The ActionRequest for ``frames`` (camera -> To (image, stamp_ns), oldest first) and ``states``."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        req = policy_pb2.ActionRequest(
            session_id=self.session_id,
            seq=seq,
            views=list(views or []),
            gamma=dict(gamma or {}),
            unconditional=unconditional,
        )
        if seed is not None:
            req.seed = seed
        for name, items in frames.items():
            cam = req.cameras.add(name=name)
            for image, stamp in items:
                cam.frames.append(_frame(image, int(stamp), self.jpeg_quality))
        for s in states:
            req.states.add(
                stamp_ns=int(s.stamp_ns),
                eef_pos=[float(v) for v in s.eef_pos],
                eef_quat_wxyz=[float(v) for v in s.eef_quat_wxyz],
                gripper=float(s.gripper),
            )
        return req

    def renumbered(self, req: policy_pb2.ActionRequest) -> policy_pb2.ActionRequest:
        """``req`` again as the session's next request (a new ``seq``): to ask anew after a refusal."""
        again = policy_pb2.ActionRequest()
        again.CopyFrom(req)
        with self._lock:
            self._seq += 1
            again.seq = self._seq
        return again

    def call(
        self, req: policy_pb2.ActionRequest, timeout_s: float | None = None, wait_for_ready: bool = False
    ) -> ActionChunk:
        """GetAction. ``wait_for_ready``: a server that cannot be reached is waited for, up to the
        deadline, instead of failing at once (gRPC's own queueing of the call)."""
        t0 = time.perf_counter()
        try:
            reply = self.stub.GetAction(
                req, timeout=timeout_s or self.timeout_s, metadata=self._metadata, wait_for_ready=wait_for_ready
            )
        except grpc.RpcError as exc:
            raise PolicyError(f"GetAction seq {req.seq}: {exc.code().name}: {exc.details()}", exc.code()) from None
        self._check_server(reply)
        acts = np.array([[*a.dp, *a.drot, a.gripper] for a in reply.actions], dtype=np.float64).reshape(-1, 7)
        t = reply.timing
        return ActionChunk(
            acts,
            int(reply.start_index),
            int(reply.obs_stamp_ns),
            tuple(reply.views_used),
            bool(reply.degraded),
            tuple(reply.degraded_reasons),
            {
                "decode_ms": t.decode_ms,
                "encode_ms": t.encode_ms,
                "step_p50_ms": t.step_p50_ms,
                "step_max_ms": t.step_max_ms,
                "total_ms": t.total_ms,
            },
            time.perf_counter() - t0,
        )

    def get_action(self, frames, states, **kw) -> ActionChunk:
        timeout = kw.pop("timeout_s", None)
        return self.call(self.request(frames, states, **kw), timeout)

    def reset(self, seed: int | None = None) -> bool:
        req = policy_pb2.ResetRequest(session_id=self.session_id)
        if seed is not None:
            req.seed = seed
        try:
            return self.stub.Reset(req, timeout=self.timeout_s, metadata=self._metadata).existed
        except grpc.RpcError as exc:
            raise PolicyError(f"Reset: {exc.code().name}: {exc.details()}", exc.code()) from None

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- executing chunks at the control rate ---------------------------------------------------------


@dataclass
class RunnerStats:
    requests: int = 0
    failed: int = 0  # GetAction errors (the runner holds still and asks again)
    degraded: int = 0  # answers with a view dropped
    underruns: int = 0  # ticks with no action queued: held still
    stale_dropped: int = 0  # actions whose tick passed while their request was in flight
    latency_s: list[float] = field(default_factory=list)


class ChunkRunner:
    """Actions for each control tick from the policy's chunks, requested ahead of time.

    ``act(tick, frames, state)`` is called once per tick with that tick's newest frame per camera
    and state; it keeps the last To of each for the requests. A chunk answering the observation of
    tick t holds the actions of ticks t, t+1, ... (``n_action_steps`` of them from
    ``start_index``); when it arrives at tick t' the actions of ticks before t' are dropped.
    """

    def __init__(
        self,
        client: PolicyClient,
        control_hz: float | None = None,
        *,
        blocking: bool = False,
        n_action_steps: int | None = None,
        views: Sequence[str] | None = None,
        gamma: Mapping[str, float] | None = None,
        seed: int | None = None,
        margin_ticks: int = 1,
        on_error=None,
        cancel: threading.Event | None = None,
    ):
        """``cancel``: once set, a blocking ``act`` waits no longer for its chunk (a hold), nor for
        a server that is down: the caller is stopping."""
        info = client.info
        most = int(info.pred_horizon) - int(info.obs_horizon) + 1  # a chunk's actions from start_index on
        if control_hz is not None and not control_hz > 0:
            raise ValueError(f"control_hz must be positive, got {control_hz}")
        if n_action_steps is not None and not 1 <= n_action_steps <= most:
            # (0 fell back to the policy's own; a negative count executed nothing, ever)
            raise ValueError(f"n_action_steps must be 1..{most} for this policy (Tp - To + 1), got {n_action_steps}")
        if margin_ticks < 0:
            raise ValueError(f"margin_ticks must be 0 or more, got {margin_ticks}")
        self.client = client
        self.To = int(info.obs_horizon)
        self.n_action_steps = int(n_action_steps if n_action_steps is not None else info.n_action_steps)
        self.hz = float(control_hz if control_hz is not None else info.control_hz)
        self.blocking = blocking
        self.views = list(views) if views else None
        self.gamma = dict(gamma) if gamma else None
        self.seed = seed  # a base seed: request i of the episode uses seed + i (reproducible episodes)
        self.margin_ticks = margin_ticks
        self.on_error = on_error
        self.cancel = cancel or threading.Event()
        self.stats = RunnerStats()
        self.last_chunk: ActionChunk | None = None
        self.reset()

    def reset(self) -> None:
        """A new episode: forget the history, the queue, a request in flight."""
        self._frames: dict[str, deque] = {}
        self._states: deque = deque(maxlen=self.To)
        self._queue: dict[int, np.ndarray] = {}
        self._pending: tuple[int, threading.Thread, list] | None = None  # (obs tick, thread, [result])
        self._gripper: float | None = None  # what a hold commands: the last action's, else as the robot reads
        self._requests = 0
        self._latency = 0.0  # running estimate (s)

    def _observe(self, frames: Mapping[str, tuple[Image, int]], state: State) -> None:
        for name, item in frames.items():
            q = self._frames.setdefault(name, deque(maxlen=self.To))
            q.append(item)
            while len(q) < self.To:  # episode start: repeat the first frame, as the training data pad
                q.appendleft(q[0])
        self._states.append(state)
        while len(self._states) < self.To:
            self._states.appendleft(self._states[0])

    def _start(self, tick: int) -> None:
        seed = None if self.seed is None else self.seed + self._requests
        self._requests += 1
        req = self.client.request(
            {n: list(q) for n, q in self._frames.items()}, list(self._states), self.views, self.gamma, seed
        )
        box: list = []

        def call() -> None:
            # In lockstep the sim waits for this chunk, so a server that is down or restarting (not
            # serving yet: its health says so) is waited for, within the client's deadline, rather
            # than the arm held tick after tick and the episode lost to it. A serving server that
            # refuses (no worker left) is not: that is its answer. In real time a late chunk is
            # worthless: one try.
            # A wait that ran out is not waited again (a server gone for good would cost every
            # tick the deadline) until the server answers again.
            patient = self.blocking and not self.client.waited_out
            deadline = time.monotonic() + self.client.timeout_s
            attempt = req
            while True:
                try:
                    left = deadline - time.monotonic()  # (every try within the one deadline)
                    box.append(self.client.call(attempt, timeout_s=left, wait_for_ready=patient))
                    self.client.waited_out = False
                    return
                except PolicyError as exc:
                    down = exc.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
                    waiting = patient and down and not self.client.serving()
                    if not (waiting and deadline - time.monotonic() > RETRY_S):
                        self.client.waited_out = self.client.waited_out or waiting
                        box.append(exc)
                        return
                    failed = exc
                if self.cancel.wait(RETRY_S):  # (stopping: the last refusal is the answer)
                    box.append(failed)
                    return
                attempt = self.client.renumbered(req)

        thread = threading.Thread(target=call, name="policy-request", daemon=True)
        self._pending = (tick, thread, box)
        self.stats.requests += 1
        thread.start()

    def _collect(self, tick: int, wait: bool) -> None:
        if self._pending is None:
            return
        obs_tick, thread, box = self._pending
        while wait and thread.is_alive() and not self.cancel.is_set():
            thread.join(0.1)
        if thread.is_alive():
            return
        self._pending = None
        result = box[0]
        if isinstance(result, PolicyError):
            self.stats.failed += 1
            if self.on_error is not None:
                self.on_error(result)
            return
        chunk: ActionChunk = result
        self.last_chunk = chunk
        self.stats.latency_s.append(chunk.latency_s)
        self.stats.degraded += chunk.degraded
        self._latency = chunk.latency_s if self._latency == 0 else 0.7 * self._latency + 0.3 * chunk.latency_s
        fresh = {}
        for j in range(self.n_action_steps):
            i = chunk.start_index + j
            if i >= len(chunk.actions):
                break
            t = obs_tick + j
            if t < tick:
                self.stats.stale_dropped += 1  # its moment passed while the request was in flight
                continue
            fresh[t] = chunk.actions[i]
        self._queue = fresh  # a newer chunk replaces what is left of the older one

    def _lead_ticks(self) -> int:
        return int(np.ceil(self._latency * self.hz)) + self.margin_ticks

    def act(self, tick: int, frames: Mapping[str, tuple[Image, int]], state: State) -> tuple[np.ndarray, bool]:
        """(7-vector action for ``tick``, True) or a hold and False when none is queued."""
        self._observe(frames, state)
        if self._gripper is None:  # (before: open, dropping an object held when the episode began)
            self._gripper = kept_gripper(state.gripper)
        self._collect(tick, wait=False)
        left = sum(1 for t in self._queue if t >= tick)
        if self._pending is None and left <= (0 if self.blocking else self._lead_ticks()):
            self._start(tick)
            if self.blocking:
                self._collect(tick, wait=True)
        action = self._queue.pop(tick, None)
        for t in [t for t in self._queue if t < tick]:
            del self._queue[t]
        if action is None:
            self.stats.underruns += 1
            return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self._gripper]), False
        self._gripper = float(action[6])
        return action, True
