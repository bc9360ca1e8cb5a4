"""A denoising worker process on loopback: the views of one request computed in one pass per step,
its refusals (each with the right code, the worker still serving), and its token."""

from __future__ import annotations

import asyncio
import os
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from policy_processes import start_worker, stop

from services.core.tensors import from_tensor, to_tensor
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy.checkpoint import checkpoint_sha256, read_info
from services.policy.server import RemoteDenoiser, WorkerPool

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def worker(tiny_checkpoint):
    # a group waits as long as it takes for its views (on a loaded machine a view's thread can be held
    # back past the default 50 ms): the pass counts the tests check are then exact
    proc, addr = start_worker(tiny_checkpoint, "--set", "group_wait_ms=60000")
    yield addr
    stop(proc)


def observation(ckpt: Path, seed: int, view: str, group: str = "", size: int = 0) -> policy_pb2.DenoiseRequest:
    m = read_info(ckpt)["model"]
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 255, (m["obs_horizon"], *m["image_size"], 3), dtype=np.uint8)
    state = rng.uniform(-1, 1, (m["obs_horizon"], m["state_dim"])).astype(np.float32)
    obs = policy_pb2.DenoiseObservation(
        checkpoint_sha256=checkpoint_sha256(ckpt),
        view=view,
        frames=to_tensor(frames),
        state=to_tensor(state),
        group=group,
        group_size=size,
    )
    return policy_pb2.DenoiseRequest(observation=obs)


def step(k: int, x: np.ndarray) -> policy_pb2.DenoiseRequest:
    return policy_pb2.DenoiseRequest(step=policy_pb2.DenoiseStep(k=k, x=to_tensor(x)))


class Stream:
    """One Denoise stream driven message by message (a request's view, as the server drives it)."""

    def __init__(self, stub):
        self._out: list = []
        self._cv = threading.Condition()
        self._done = False
        self.replies = stub.Denoise(self._requests(), timeout=60)

    def _requests(self):
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._out or self._done)
                if not self._out:
                    return
                msg = self._out.pop(0)
            yield msg

    def ask(self, msg) -> policy_pb2.DenoiseReply:
        with self._cv:
            self._out.append(msg)
            self._cv.notify()
        return next(self.replies)

    def close(self) -> None:
        with self._cv:
            self._done = True
            self._cv.notify()


def info(stub) -> policy_pb2.WorkerInfo:
    return stub.GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=10)


def run_views(stub, ckpt, views: list[str], group: str, ks: list[int]) -> dict[str, list[np.ndarray]]:
    """Each view on its own stream and thread, in lockstep like the server: observation, then steps."""
    out: dict[str, list[np.ndarray]] = {v: [] for v in views}
    barrier = threading.Barrier(len(views))
    errors: list[BaseException] = []

    def one(v: str) -> None:
        s = Stream(stub)
        seed = sum(map(ord, v))  # a view's inputs are the same whichever streams run beside it
        try:
            s.ask(observation(ckpt, seed, v, group, len(views) if group else 0))
            x = np.random.default_rng(seed).standard_normal((16, 7)).astype(np.float32)
            for k in ks:
                barrier.wait(timeout=30)  # every view sends step k together, as the server does
                reply = s.ask(step(k, x))
                out[v].append(np.frombuffer(reply.eps.data, np.float32).reshape(16, 7))
        except BaseException as exc:  # noqa: BLE001  (re-raised in the test's thread)
            errors.append(exc)
            barrier.abort()
        finally:
            s.close()

    threads = [threading.Thread(target=one, args=(v,)) for v in views]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    if errors:
        raise errors[0]
    return out


def test_a_request_s_views_are_one_pass_per_step_with_the_numbers_of_separate_streams(worker, tiny_checkpoint):
    stub = policy_pb2_grpc.DenoiseWorkerStub(grpc.insecure_channel(worker))
    views, ks = ["F", "FL", "FR"], [90, 50, 10]
    alone = {v: run_views(stub, tiny_checkpoint, [v], "", ks)[v] for v in views}  # one view at a time
    before = info(stub)
    grouped = run_views(stub, tiny_checkpoint, views, "request-1", ks)
    after = info(stub)
    # one encode of three and one pass of three per step: 4 passes, 12 items
    assert (after.passes - before.passes, after.batched_items - before.batched_items) == (4, 12)
    assert after.streams - before.streams == 3
    for v in views:
        for a, b in zip(alone[v], grouped[v]):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


def test_bad_streams_are_refused_with_the_reason_and_the_worker_keeps_serving(worker, tiny_checkpoint):
    stub = policy_pb2_grpc.DenoiseWorkerStub(grpc.insecure_channel(worker))
    good = observation(tiny_checkpoint, 0, "F")
    wrong_ckpt = policy_pb2.DenoiseRequest()
    wrong_ckpt.CopyFrom(good)
    wrong_ckpt.observation.checkpoint_sha256 = "0" * 64
    small = policy_pb2.DenoiseRequest()
    small.CopyFrom(good)
    small.observation.frames.CopyFrom(to_tensor(np.zeros((2, 7, 5, 3), np.uint8)))
    nan = np.full((16, 7), np.nan, np.float32)
    x = np.zeros((16, 7), np.float32)
    cases = [
        ([step(10, x)], grpc.StatusCode.FAILED_PRECONDITION, "before the observation"),
        ([wrong_ckpt], grpc.StatusCode.FAILED_PRECONDITION, "worker holds checkpoint"),
        ([small], grpc.StatusCode.INVALID_ARGUMENT, "frames must be uint8"),
        ([good, step(10, nan)], grpc.StatusCode.INVALID_ARGUMENT, "x is not finite"),
        ([good, step(10, x[:5])], grpc.StatusCode.INVALID_ARGUMENT, "x must be float32 (16, 7), got (5, 7)"),
        ([good, step(5000, x)], grpc.StatusCode.INVALID_ARGUMENT, "timestep 5000"),
        ([policy_pb2.DenoiseRequest()], grpc.StatusCode.INVALID_ARGUMENT, "empty DenoiseRequest"),
    ]
    for msgs, code, text in cases:
        with pytest.raises(grpc.RpcError) as err:
            list(stub.Denoise(iter(msgs), timeout=30))
        assert err.value.code() == code and text in err.value.details(), (text, err.value.details())
    # still serving: a good stream goes through
    replies = list(stub.Denoise(iter([good, step(10, x)]), timeout=30))
    assert len(replies) == 2 and replies[1].eps.shape == [16, 7]


def test_a_worker_with_a_token_refuses_calls_without_it_and_leaves_health_open(tiny_checkpoint):
    proc, addr = start_worker(tiny_checkpoint, env=dict(os.environ, VIEWSCALE_TOKEN="w0rker-token"))
    try:
        ch = grpc.insecure_channel(addr)
        stub = policy_pb2_grpc.DenoiseWorkerStub(ch)
        for metadata in (None, (("authorization", "Bearer w0rker-tokeN"),)):
            with pytest.raises(grpc.RpcError) as err:
                stub.GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=10, metadata=metadata)
            assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
            with pytest.raises(grpc.RpcError) as err:
                list(stub.Denoise(iter([observation(tiny_checkpoint, 0, "F")]), timeout=10, metadata=metadata))
            assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
        ok = stub.GetWorkerInfo(
            policy_pb2.WorkerInfoRequest(), timeout=10, metadata=(("authorization", "Bearer w0rker-token"),)
        )
        assert ok.checkpoint_sha256 == checkpoint_sha256(tiny_checkpoint) and ok.max_streams == 256
        health = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=10)
        assert health.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        stop(proc)


def test_a_refused_step_drops_its_view_but_leaves_the_worker_in_the_pool(worker, tiny_checkpoint):
    """The server's side of a refusal: a step the worker refuses (INVALID_ARGUMENT, the request's
    fault: any worker would refuse it) drops the view from that request without moving it, and the
    worker stays in the pool; the next request is served by it."""
    obs = observation(tiny_checkpoint, 0, "F").observation
    inputs = {"F": (np.asarray(from_tensor(obs.frames)), np.asarray(from_tensor(obs.state)))}
    x = np.zeros((read_info(tiny_checkpoint)["model"]["pred_horizon"], 7), np.float32)

    async def run() -> None:
        pool = WorkerPool([worker], checkpoint_sha256(tiny_checkpoint))
        await pool.start()
        try:
            deadline = time.monotonic() + 30
            refused = RemoteDenoiser(pool, None)
            await refused.open(inputs, False, deadline)
            eps, _ = await refused.step(10**6, {"F": x}, deadline)
            assert eps == {} and "INVALID_ARGUMENT" in refused.dropped["F"] and "timestep" in refused.dropped["F"]
            assert await refused.move(deadline) == []  # not moved: every worker would refuse it
            assert [w.address for w in pool.healthy] == [worker]
            await refused.close()
            served = RemoteDenoiser(pool, None)
            await served.open(inputs, False, deadline)
            eps, _ = await served.step(0, {"F": x}, deadline)
            assert eps["F"].shape == x.shape and served.dropped == {}
            await served.close()
        finally:
            await pool.close()

    asyncio.run(run())
