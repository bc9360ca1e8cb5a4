"""Serving on real gRPC over loopback: the policy server and real worker processes, a tiny real
checkpoint trained on the session's sim dataset, the robot-side client."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import NamedTuple

import grpc
import numpy as np
import pytest
import torch
from cli_process import viewscale
from grpc_health.v1 import health_pb2, health_pb2_grpc
from policy_processes import (
    launch,
    launch_server,
    launch_worker,
    side_by_side,
    start,
    start_server,
    start_worker,
    stop,
    stop_all,
    worker_flags,
    worker_info,
)
from polling import wait_for

from services.core.action_spaces import from_space
from services.core.bus import free_tcp_port
from services.pb import policy_pb2, policy_pb2_grpc
from services.policy.checkpoint import LATEST, POLICY_FILE, latest_checkpoint, load_policy
from services.policy.client import ActionChunk, PolicyClient, PolicyError, State
from services.policy.config import ServerConfig
from services.policy.model import sample
from services.policy.observation import model_inputs, parse
from services.policy.server import load_spec
from services.recorder.reader import read_episode

ROOT = Path(__file__).resolve().parents[2]
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def checkpoint(tiny_checkpoint) -> Path:
    return tiny_checkpoint


@pytest.fixture(scope="module")
def served_f(checkpoint) -> str:
    """The address of one in-process server of view F, shared by the tests that only call it (a
    server of their own costs each 4-5 s to start and stop)."""
    proc, addr = start_server(checkpoint, "--views", "F", "--in-process")
    yield addr
    stop(proc)


@pytest.fixture(scope="module")
def observations(sim_dataset) -> list[tuple[dict, list[State]]]:
    """(frames per camera, states) of consecutive ticks of a recorded sim episode, To = 2."""
    ep = read_episode(sorted((sim_dataset.parent / "raw").glob("*.mcap"))[0])
    states = [r.msg for r in ep.messages("/robot/state")]
    frames = {c: [(r.msg.data, r.publish_time) for r in ep.messages(f"/camera/{c}/image")] for c in ("F", "FL", "FR")}
    out = []
    for t in range(1, 12):
        st = [
            State(np.array(s.eef_pos), np.array(s.eef_quat_wxyz), s.gripper, s.header.stamp_ns)
            for s in states[t - 1 : t + 1]
        ]
        out.append(({c: f[t - 1 : t + 1] for c, f in frames.items()}, st))
    return out


def reference_actions(ckpt: Path, frames, states, view: str, seed: int) -> np.ndarray:
    """The single-view policy sampled in this process with sample(), from the same preprocessing."""
    loaded = load_policy(ckpt)
    spec, _, _ = load_spec(ServerConfig(checkpoint=str(ckpt)))
    msg = policy_pb2.ActionRequest(session_id="ref", seq=1, views=[view])
    for name, items in frames.items():
        cam = msg.cameras.add(name=name)
        for data, stamp in items:
            cam.frames.add(jpeg=data, stamp_ns=stamp)
    for s in states:
        msg.states.add(
            stamp_ns=s.stamp_ns, eef_pos=list(s.eef_pos), eef_quat_wxyz=list(s.eef_quat_wxyz), gripper=s.gripper
        )
    img, st = model_inputs(parse(msg, spec, [view]), spec)[view]
    obs = torch.from_numpy(np.ascontiguousarray(spec.normalizer.normalize_image(img[None]).transpose(0, 1, 4, 2, 3)))
    # with as many intra-op threads as the server's model: another count splits the float sums
    # otherwise and changes the last bits (seen: a test that left 2 here made this differ by 2e-6)
    threads = torch.get_num_threads()
    torch.set_num_threads(ServerConfig(checkpoint=str(ckpt)).threads)
    try:
        with torch.no_grad():
            chunk = sample(
                loaded.policy, obs, torch.from_numpy(st[None]), generator=torch.Generator().manual_seed(seed)
            )
    finally:
        torch.set_num_threads(threads)
    a = spec.normalizer.unnormalize_action(chunk[0].numpy().astype(np.float64))
    return from_space(a, "camera", R_ext=spec.cameras[view].R_ext)


def test_one_view_through_the_server_is_the_in_process_sampler(checkpoint, served_f, observations):
    addr = served_f
    frames, states = observations[3]
    with PolicyClient(addr, session_id="robot-1") as client:
        info = client.info
        assert info.obs_horizon == 2 and info.pred_horizon == 16 and info.ddim_steps == 4
        assert info.action_space == "camera" and list(info.default_views) == ["F"]
        assert {c.name for c in info.cameras} == {"F", "FL", "FR"}
        chunk = client.get_action({"F": frames["F"]}, states, seed=7)
    assert chunk.actions.shape == (16, 7) and chunk.start_index == 1 and chunk.views_used == ("F",)
    assert chunk.obs_stamp_ns == states[-1].stamp_ns and not chunk.degraded
    assert np.array_equal(chunk.actions, reference_actions(checkpoint, {"F": frames["F"]}, states, "F", 7))


def test_viewscale_serve_logs_at_its_log_level(checkpoint):
    """``viewscale serve`` (whose CLI configures logging at WARNING first) logs what it serves at
    its ``log_level`` setting, INFO by default, as ``python -m services.policy serve`` does."""
    args = ["serve", "--checkpoint", str(checkpoint), "--listen", "127.0.0.1:0", "--views", "F", "--in-process"]
    (proc, _), (quiet, _) = side_by_side(
        [launch(a, "policy", module="services.cli") for a in (args, [*args, "--set", "log_level=WARNING"])]
    )
    try:
        assert "INFO services.policy.server: policy " in proc.log_path.read_text()  # its model, address, views
        assert "INFO" not in quiet.log_path.read_text()
    finally:
        stop_all([proc, quiet])


def test_fan_out_to_workers_gives_the_in_process_actions(checkpoint, observations):
    # the grouping worker waits as long as it takes for a group's views (a loaded machine can hold a
    # view's message back longer than the default 50 ms): the pass count below is then exact
    # the grouping worker logs every module it imports: a worker computes eps and never steps a
    # scheduler, so it must not pay for diffusers' import (which imports torch._dynamo: 1.5 s here)
    imports = dict(os.environ, PYTHONPROFILEIMPORTTIME="1")
    grouping = ("--set", "group_wait_ms=60000")
    *workers, local = side_by_side(
        [launch_worker(checkpoint) for _ in range(3)]
        + [launch_worker(checkpoint, *grouping, env=imports if i == 0 else None) for i in range(3)]
        + [launch_server(checkpoint, "--views", "F,FL,FR", "--in-process")]
    )
    # two replicas behind one balanced address (as a DNS name of several replicas): gRPC spreads
    # the streams over them, and the server groups the views by the replica each stream reached
    balanced = "ipv4:" + ",".join(a for _, a in workers[4:6])
    views = ("--views", "F,FL,FR")
    servers = [local] + side_by_side(
        [
            # a view per worker, and the three views grouped on one worker (one pass per step)
            launch_server(checkpoint, *views, "--placement", "spread", *worker_flags(workers[:3])),
            launch_server(checkpoint, *views, "--worker", workers[3][1]),
            launch_server(checkpoint, *views, "--worker", balanced),
        ]
    )
    try:
        got = []
        for _, addr in servers:
            with PolicyClient(addr) as client:
                got.append([client.get_action(f, s, seed=11 + i) for i, (f, s) in enumerate(observations[:3])])
        for local, *fans in zip(*got):
            for fan in fans:
                assert fan.views_used == local.views_used == ("F", "FL", "FR") and not fan.degraded
                np.testing.assert_allclose(fan.actions, local.actions, rtol=0, atol=1e-6)
        assert not np.allclose(got[0][0].actions, got[0][1].actions)  # different observations, other chunks
        # spread: each worker one view of each request
        assert [worker_info(a).streams for _, a in workers[:3]] == [3, 3, 3]
        # three requests of three views: an encode and four steps each, every one a pass of three
        info = worker_info(workers[3][1])
        assert (info.streams, info.passes, info.batched_items) == (9, 3 * 5, 3 * 5 * 3)
        # every view's encode and steps computed once, on whichever replica its stream reached
        infos = [worker_info(a) for _, a in workers[4:6]]
        assert sum(i.streams for i in infos) == 9 and sum(i.batched_items for i in infos) == 3 * 5 * 3
        imported = workers[3][0].log_path.read_text()
        assert re.search(r"^import time: .*\| +torch$", imported, re.M)  # the import log is there
        assert "diffusers" not in imported and "torch._dynamo" not in imported
    finally:
        stop_all(servers + workers)


def test_precision_bf16_through_a_worker_is_the_in_process_bf16_and_a_worker_computing_otherwise_is_left_out(
    checkpoint, observations
):
    bf16, fp32, here_bf16, here_fp32 = side_by_side(
        [
            launch_worker(checkpoint, "--precision", "bf16"),
            launch_worker(checkpoint),
            launch_server(checkpoint, "--views", "F", "--in-process", "--precision", "bf16"),
            launch_server(checkpoint, "--views", "F", "--in-process"),
        ]
    )
    servers = {
        "in-process bf16": here_bf16,
        "fan-out bf16": start_server(checkpoint, "--views", "F", "--precision", "bf16", *worker_flags([bf16, fp32])),
        "in-process fp32": here_fp32,
    }
    try:
        got = {}
        for name, (_, addr) in servers.items():
            with PolicyClient(addr) as client:
                assert client.info.precision == name.split()[-1]  # what it computes in, told
                got[name] = [client.get_action(f, s, seed=5 + i).actions for i, (f, s) in enumerate(observations[:3])]
        np.testing.assert_array_equal(got["fan-out bf16"], got["in-process bf16"])
        diff = np.abs(np.subtract(got["in-process bf16"], got["in-process fp32"])).max()
        assert 0 < diff < 0.05 * np.abs(got["in-process fp32"]).max()  # bfloat16's rounding: near, not equal
        # every view went to the bf16 worker; the float32 one was not admitted, and the log says why
        assert (worker_info(bf16[1]).streams, worker_info(fp32[1]).streams) == (3, 0)
        log = servers["fan-out bf16"][0].log_path.read_text()
        assert f"worker {fp32[1]} not admitted: computes in fp32, the server's setting is bf16" in log
        # and a stream that asks a worker for another precision is refused, as for another checkpoint
        sha = worker_info(fp32[1]).checkpoint_sha256
        ask = policy_pb2.DenoiseRequest(
            observation=policy_pb2.DenoiseObservation(checkpoint_sha256=sha, precision="bf16")
        )
        with grpc.insecure_channel(fp32[1]) as ch:
            with pytest.raises(grpc.RpcError) as err:
                list(policy_pb2_grpc.DenoiseWorkerStub(ch).Denoise(iter([ask]), timeout=10))
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "worker computes in fp32, the server asks for bf16" in err.value.details()
    finally:
        stop_all([*servers.values(), bf16, fp32])


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPU cores to pin workers to")
def test_auto_placement_spreads_views_over_workers_on_cores_of_their_own(checkpoint, observations):
    """Three CPU workers on one machine, pinned (taskset): the first and third to one core, the
    second to another. Each reports its machine and cores; placement auto gives a request's views
    to the two that do not compete -- two views on the first worker (one pass), one on the second
    -- and none to the third, which would take turns with the first on its core."""
    a, b = sorted(os.sched_getaffinity(0))[:2]
    workers = side_by_side([launch_worker(checkpoint, prefix=("taskset", "-c", str(c))) for c in (a, b, a)])
    server, addr = start_server(checkpoint, "--views", "F,FL,FR", *worker_flags(workers))
    try:
        infos = [worker_info(w) for _, w in workers]
        assert [list(i.cores) for i in infos] == [[a], [b], [a]]
        boot_id = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        assert {i.machine for i in infos} == {boot_id} and {i.accelerator for i in infos} == {""}  # no GPU
        with PolicyClient(addr) as client:
            for i, (f, s) in enumerate(observations[:2]):
                chunk = client.get_action(f, s, seed=i)
                assert chunk.views_used == ("F", "FL", "FR") and not chunk.degraded
        assert [worker_info(w).streams for _, w in workers] == [4, 2, 0]
    finally:
        stop_all([server, *workers])


@pytest.mark.gpu
def test_auto_placement_packs_views_on_workers_that_share_a_gpu(checkpoint, observations):
    """Two workers on one GPU report its UUID, the same one: placement auto puts each request's
    views on one of them (one batched pass per step) rather than on both taking turns on the GPU."""
    workers = [start_worker(checkpoint, "--device", "cuda") for _ in range(2)]
    server, addr = start_server(checkpoint, "--views", "F,FL,FR", *worker_flags(workers))
    try:
        infos = [worker_info(w) for _, w in workers]
        assert infos[0].accelerator and infos[0].accelerator == infos[1].accelerator
        with PolicyClient(addr) as client:
            for i, (f, s) in enumerate(observations[:2]):
                assert client.get_action(f, s, seed=i).views_used == ("F", "FL", "FR")
        assert sorted(worker_info(w).streams for _, w in workers) == [0, 6]
    finally:
        stop_all([server, *workers])


class Answer(NamedTuple):
    sent: float  # when the request went (time.monotonic)
    came: float  # when its answer came
    obs: int  # index into the observations
    seed: int
    chunk: ActionChunk


class Robots:
    """Robots calling GetAction in a loop, each on its own thread, while the block runs: every
    answer (``results``) and every failure (``errors``)."""

    def __init__(self, address: str, observations, n: int = 4):
        self.results: list[Answer] = []
        self.errors: list[PolicyError] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._loop, args=(address, observations, i)) for i in range(n)]

    def _loop(self, address: str, observations, i: int) -> None:
        with PolicyClient(address, session_id=f"robot-{i}", timeout_s=10.0) as client:
            n = 0
            while not self._stop.is_set():
                j, seed = n % len(observations), 1000 * i + n
                try:
                    sent = time.monotonic()
                    chunk = client.get_action(*observations[j], seed=seed)
                    self.results.append(Answer(sent, time.monotonic(), j, seed, chunk))
                except PolicyError as exc:
                    self.errors.append(exc)
                n += 1

    def __enter__(self) -> Robots:
        for t in self._threads:
            t.start()
        wait_for(lambda: len(self.results) >= len(self._threads), 60, "the robots' first answers")
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=30)

    def moved_after(self, t0: float) -> Answer | None:
        """An answer since ``t0`` with views that moved to another worker."""
        return next(
            (a for a in list(self.results) if a.came > t0 and any("moved to" in w for w in a.chunk.degraded_reasons)),
            None,
        )

    def sent_after(self, t0: float) -> list[Answer]:
        return [a for a in list(self.results) if a.sent > t0]


def test_a_frozen_or_killed_worker_moves_its_views_and_is_readmitted(checkpoint, observations):
    """Three CPU workers (placement auto: a request's three views packed on one); four robots call
    in a loop. A worker frozen (SIGSTOP), then killed (kill -9): the views of the requests it held
    move to another worker, so not one GetAction fails; the answers say so and are what a healthy
    server answers; resumed, and restarted, it is re-admitted."""
    ports = [free_tcp_port() for _ in range(3)]
    workers = side_by_side([launch_worker(checkpoint, port=p) for p in ports])
    server, addr = start_server(checkpoint, "--views", "F,FL,FR", *worker_flags(workers))
    robots = Robots(addr, observations)
    try:
        with robots:
            t0 = time.monotonic()
            workers[1][0].send_signal(signal.SIGSTOP)  # frozen: its requests miss a step deadline
            frozen = wait_for(lambda: robots.moved_after(t0), 60, "views moved off the frozen worker")
            workers[1][0].send_signal(signal.SIGCONT)
            served = worker_info(workers[1][1]).streams
            wait_for(lambda: worker_info(workers[1][1]).streams > served, 60, "the resumed worker re-admitted")
            t1 = time.monotonic()
            workers[1][0].kill()  # kill -9: its streams break mid-request
            killed = wait_for(lambda: robots.moved_after(t1), 60, "views moved off the killed worker")
            stop(workers[1][0])  # (reaped, its log file removed: not left in /tmp by every run)
            workers[1] = start_worker(checkpoint, port=ports[1])
            # a new process: nothing served yet
            wait_for(lambda: worker_info(workers[1][1]).streams > 0, 60, "the restarted worker re-admitted")
        # a moved view computes what it would have: the same observation and seed, the same actions
        with PolicyClient(addr, session_id="check") as client:
            for _, _, j, seed, chunk in (frozen, killed):
                again = client.get_action(*observations[j], seed=seed)
                assert not again.degraded and again.views_used == chunk.views_used == ("F", "FL", "FR")
                np.testing.assert_allclose(again.actions, chunk.actions, rtol=0, atol=1e-6)
    finally:
        stop_all([server, *workers])
    assert robots.errors == []  # not one GetAction failed
    assert len(robots.results) > 20


def test_a_killed_replica_behind_a_balanced_address_costs_no_answer(checkpoint, observations):
    """Two workers behind one balanced address (a DNS name of two replicas), four robots calling in
    a loop, one replica killed: gRPC's balancer routes around it and the views it held move to the
    other replica; the address stays in the pool (taking it out would leave no worker at all)."""
    workers = side_by_side([launch_worker(checkpoint) for _ in range(2)])
    balanced = "ipv4:" + ",".join(a for _, a in workers)
    server, addr = start_server(checkpoint, "--views", "F,FL,FR", "--worker", balanced)
    robots = Robots(addr, observations)
    try:
        with robots:
            killed_at = time.monotonic()
            workers[0][0].kill()
            # answers keep coming, whole, from the replica left
            wait_for(
                lambda: sum(len(a.chunk.views_used) == 3 for a in robots.sent_after(killed_at + 1.0)) >= 8,
                60,
                "whole answers after the kill",
            )
    finally:
        stop_all([server, *workers])
    assert robots.errors == []  # not one GetAction failed


def test_a_frozen_replica_behind_a_balanced_address_is_left_after_a_keepalive(checkpoint, observations):
    """Two workers behind one balanced address, four robots calling in a loop, one replica frozen
    (SIGSTOP: its connection stays open and nothing answers, as from a hung host or behind a cut
    network). The balancer would keep giving it streams, each costing its request a late step and
    a move; the server's keepalive pings go unanswered, gRPC closes the connection and the balancer
    leaves the replica: the answers are whole and not degraded again. Resumed, it gets streams again."""
    workers = side_by_side([launch_worker(checkpoint) for _ in range(2)])
    balanced = "ipv4:" + ",".join(a for _, a in workers)
    server, addr = start_server(checkpoint, "--views", "F,FL,FR", "--worker", balanced, "--set", "worker_keepalive_s=1")
    robots = Robots(addr, observations)
    try:
        time.sleep(4.0)  # idle: pings with no data in between, which the workers must accept
        with robots:
            frozen_at = time.monotonic()
            workers[0][0].send_signal(signal.SIGSTOP)
            wait_for(
                lambda: [a for a in list(robots.results) if a.came > frozen_at and a.chunk.degraded],
                60,
                "a request that met the frozen replica",
            )
            # a ping after 1 s without a read, its answer awaited 1 s: left within ~2 s of the freeze
            left_by = frozen_at + 4.0
            wait_for(lambda: len(robots.sent_after(left_by)) >= 16, 90, "answers after the keepalive")
            after = robots.sent_after(left_by)
            workers[0][0].send_signal(signal.SIGCONT)  # back: the balancer reconnects and uses it again
            before = worker_info(workers[0][1]).streams  # (and more, from streams it held frozen)
            wait_for(lambda: worker_info(workers[0][1]).streams > before + 30, 60, "the resumed replica given streams")
    finally:
        server_log = server.log_path.read_text()
        stop_all([server, *workers])
    assert robots.errors == []
    assert [a.chunk.degraded_reasons for a in after if a.chunk.degraded] == []
    # a worker refusing the pings (GOAWAY too_many_pings) would drop the server's connections to it
    assert "too_many_pings" not in server_log


def local_workers(server_pid: int) -> dict[int, list[str]]:
    """The worker processes a server started: pid -> command line (one that just exited left out)."""
    out = {}
    # each thread's children (the server starts a worker again from a thread of its executor)
    for task in Path(f"/proc/{server_pid}/task").iterdir():
        try:
            pids = (task / "children").read_text().split()
        except FileNotFoundError:  # the thread ended
            continue
        for p in pids:
            try:
                cmd = Path(f"/proc/{p}/cmdline").read_text().split("\0")
            except (FileNotFoundError, ProcessLookupError):
                continue
            if "worker" in cmd:
                out[int(p)] = cmd
    return out


def test_serve_restarts_a_local_worker_that_dies_on_its_address(checkpoint, observations, tmp_path):
    """`viewscale serve --workers 2` on a run, four robots calling in a loop, one worker process
    killed (kill -9, as the OOM killer would): its views move meanwhile, not one GetAction fails,
    and the server starts it again on its address, where it serves again -- the checkpoint the
    server serves, though the run (still training) has a newer one by then (before: the restarted
    worker loaded the run's newer latest, and the server did not admit it)."""
    run = tmp_path / "run"
    shutil.copytree(checkpoint, run)
    served_step = latest_checkpoint(run)
    newer = served_step.with_name("step_9999999")
    shutil.copytree(served_step, newer)
    with open(newer / POLICY_FILE, "a") as f:
        f.write("\n")  # another checkpoint: another hash
    server, addr = start_server(run, "--views", "F,FL,FR", "--workers", "2")
    robots = Robots(addr, observations)
    try:
        # the server answers once one worker is ready: kill one only when both are admitted (else
        # the other may still be loading its model, with nowhere for the views to move)
        wait_for(lambda: server.log_path.read_text().count(" admitted (") >= 2, 60, "both workers admitted")
        marker = run / "checkpoints" / LATEST
        marker.with_name("latest.tmp").write_text(newer.name)
        os.replace(marker.with_name("latest.tmp"), marker)  # the training wrote a newer checkpoint
        with robots:
            first = local_workers(server.pid)
            assert len(first) == 2
            victim = min(first)
            os.kill(victim, signal.SIGKILL)
            again = wait_for(
                lambda: {p: c for p, c in local_workers(server.pid).items() if p not in first}, 60, "a new worker"
            )
            [cmd] = again.values()
            address = cmd[cmd.index("--listen") + 1]
            assert f"({address}) exited with code -9" in server.log_path.read_text()  # the dead one's

            def served() -> int:
                try:
                    return worker_info(address).streams
                except grpc.RpcError:  # not listening yet
                    return 0

            wait_for(lambda: served() > 0, 60, "the restarted worker given views")
    finally:
        stop(server)
    assert robots.errors == []
    # stopped, the server takes its workers with it, the restarted one too
    wait_for(lambda: not any(Path(f"/proc/{p}").exists() for p in [*first, *again]), 30, "the workers gone")


def test_malformed_requests_are_refused_with_the_field_and_the_server_stays_up(checkpoint, observations):
    proc, addr = start_server(checkpoint, "--views", "F,FL", "--in-process", "--set", "max_message_mb=4")
    try:
        good_client = PolicyClient(addr, session_id="good")
        frames, states = observations[0]
        good = good_client.request(frames, states)
        stub = policy_pb2_grpc.PolicyStub(
            grpc.insecure_channel(addr, options=[("grpc.max_send_message_length", 64 << 20)])
        )
        rng = np.random.default_rng(0)

        def variant(i: int) -> tuple[policy_pb2.ActionRequest, str]:
            req = policy_pb2.ActionRequest()
            req.CopyFrom(good)
            req.session_id, req.seq = f"bad-{i}", 1
            kind = i % 12
            if kind == 0:
                del req.cameras[1].frames[1]
                return req, "expected 2 frames, got 1"
            if kind == 1:
                req.cameras[0].frames[0].jpeg = bytes(rng.integers(0, 255, 200, dtype=np.uint8))
                return req, "not a complete JPEG"
            if kind == 2:
                req.cameras[0].frames[0].jpeg = (
                    b"\xff\xd8" + bytes(rng.integers(0, 255, 300, dtype=np.uint8)) + b"\xff\xd9"
                )
                return req, "undecodable JPEG"
            if i % 24 == 3:
                req.states[1].eef_pos[0] = float("nan")
                return req, "states[1].eef_pos: not finite"
            if kind == 3:  # millimetres for metres
                req.states[1].eef_pos[:] = [450.0, 0.0, 300.0]
                return req, "states[1].eef_pos: 540.8 m from the robot's base, farther than 10 m"
            if kind == 4:
                del req.states[0].eef_quat_wxyz[:]
                return req, "states[0].eef_quat_wxyz: expected 4 values"
            if kind == 5:
                req.views.append("XX")
                return req, "unknown camera 'XX'"
            if kind == 6:
                req.cameras[0].frames[0].rgb.dtype, req.cameras[0].frames[0].rgb.shape[:] = "float32", [32, 32, 3]
                return req, "uint8"
            if kind == 7:
                req.cameras[0].frames[0].rgb.dtype, req.cameras[0].frames[0].rgb.shape[:] = "|u1", [8, 8, 3]
                return req, "expected shape"
            if kind == 8:
                req.gamma["F"] = -1.0
                return req, "gamma: the weight of F must be finite and non-negative, got -1.0"
            if i % 24 == 9:
                req.session_id = ""
                return req, "session_id"
            if kind == 9:  # a hand-written client that never sets it
                req.ClearField("seq")
                return req, "seq: 0 or not set: number each session's requests 1, 2, 3, ..."
            if kind == 10:
                del req.states[:]
                return req, "states: expected 2 states, got 0"
            if i % 24 == 11:  # a name the server does not know, in place of F: said back
                req.cameras[0].name = "front"
                return req, "images['F']: missing (the request composes F, FL; it sent front, FL, FR)"
            del req.cameras[:]
            return req, "images['F']: missing (the request composes F, FL; it sent none)"

        codes = {}
        for i in range(1000):
            req, text = variant(i)
            with pytest.raises(grpc.RpcError) as err:
                stub.GetAction(req, timeout=10)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (i, err.value.details())
            assert text in err.value.details(), (i, err.value.details())
            codes[i % 12] = err.value.details()
        assert len(codes) == 12
        big = policy_pb2.ActionRequest()
        big.CopyFrom(good)
        big.cameras[0].frames[0].jpeg = b"\xff\xd8" + b"\x00" * (5 << 20) + b"\xff\xd9"  # over the 4 MB cap
        with pytest.raises(grpc.RpcError) as err:
            stub.GetAction(big, timeout=10)
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        # Reset checks its session id too (an id of megabytes, with a seed, was kept as a session)
        for sid in ("", "x" * (1 << 20), "bad\nid"):
            with pytest.raises(grpc.RpcError) as err:
                stub.Reset(policy_pb2.ResetRequest(session_id=sid, seed=1), timeout=10)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "session_id" in err.value.details()
        good_client.reset(seed=3)  # a good id: the session is made, with its seed
        assert good_client.reset(seed=3) is True
        assert good_client.get_action(frames, states).actions.shape == (16, 7)  # still answering
    finally:
        stop(proc)


def test_a_chunk_that_is_not_finite_is_never_sent(checkpoint, observations):
    """A position the reach bound lets through (raised here) but the model's float32 passes overflow
    on: the request fails with INTERNAL, in-process and through a worker, and no NaN action reaches
    the robot; the server answers the next good request."""
    frames, states = observations[0]
    far = [State(np.array([1e30, 0.0, 0.0]), s.eef_quat_wxyz, s.gripper, s.stamp_ns) for s in states]
    worker, here = side_by_side(
        [launch_worker(checkpoint), launch_server(checkpoint, "--in-process", "--set", "max_reach_m=1e38")]
    )
    servers = [here]
    try:  # (a server that fails to start must not leave the worker running)
        servers.append(start_server(checkpoint, *worker_flags([worker]), "--set", "max_reach_m=1e38"))
        for _, addr in servers:
            with PolicyClient(addr, session_id="far") as client:
                with pytest.raises(PolicyError) as err:
                    client.get_action(frames, far, views=["F", "FL"])
                assert err.value.code == grpc.StatusCode.INTERNAL, err.value
                assert "noise prediction for F, FL at step" in str(err.value), err.value
                assert "is not finite: no action sent" in str(err.value), err.value
                chunk = client.get_action(frames, states, views=["F", "FL"])
                assert np.isfinite(chunk.actions).all() and not chunk.degraded, chunk
    finally:
        stop_all([*servers, worker])


def test_a_newer_request_of_a_session_cancels_the_older_and_sessions_are_separate(checkpoint, observations):
    proc, addr = start_server(checkpoint, "--in-process")
    try:
        frames, states = observations[0]
        a, b = PolicyClient(addr, session_id="a"), PolicyClient(addr, session_id="b")
        stub = policy_pb2_grpc.PolicyStub(grpc.insecure_channel(addr))
        # Two requests of one session sent back to back. The older one either finished before the
        # newer came, or is cut at its next step (superseded), or -- when the newer overtook it on
        # the way -- refused as not newer. Repeat until the cut has been seen; every outcome must be
        # one of the three.
        outcomes = []
        while "superseded" not in outcomes and len(outcomes) < 30:
            old = a.request(frames, states)
            new = a.request(frames, states)
            first = stub.GetAction.future(old, timeout=20)
            second = stub.GetAction(new, timeout=20)
            assert second.seq == new.seq
            try:
                first.result()
                outcomes.append("done")
            except grpc.RpcError as exc:
                assert exc.code() == grpc.StatusCode.ABORTED, exc
                if "superseded by seq" in exc.details():
                    outcomes.append("superseded")
                else:
                    assert "is not newer than this session's last" in exc.details(), exc.details()
                    outcomes.append("overtaken")
        assert "superseded" in outcomes, outcomes
        with pytest.raises(PolicyError) as err:
            a.call(old)  # an older seq than the last one is refused
        assert err.value.code == grpc.StatusCode.ABORTED
        assert b.get_action(frames, states, seed=3).actions.shape == (16, 7)  # b never saw a's requests
        assert np.array_equal(
            b.get_action(frames, states, seed=3).actions, a.get_action(frames, states, seed=3).actions
        )
    finally:
        stop(proc)


def test_after_a_restart_the_client_checks_the_server_again_and_refuses_a_changed_one(
    checkpoint, observations, tmp_path
):
    """The server on the client's address restarted: with the same settings its answers are used
    (the client asked for its PolicyInfo once: server_changes); with other default views, or
    another checkpoint, the client refuses its chunks (PolicyChanged) rather than act on them."""
    import json
    import shutil

    from services.policy.checkpoint import resolve_checkpoint
    from services.policy.client import PolicyChanged

    other = tmp_path / "other-run" / "checkpoints" / "step_0000001"
    shutil.copytree(resolve_checkpoint(checkpoint), other)
    info = json.loads((other / "policy.json").read_text())
    (other / "policy.json").write_text(json.dumps({**info, "note": "another checkpoint"}))  # another sha256
    port = free_tcp_port()
    frames, states = observations[3]

    def serve(ckpt: Path, views: str = "F") -> subprocess.Popen:
        args = ["serve", "--checkpoint", str(ckpt), "--listen", f"127.0.0.1:{port}", "--views", views, "--in-process"]
        return start(args, "policy")[0]

    proc = serve(checkpoint)
    try:
        with PolicyClient(f"127.0.0.1:{port}", session_id="robot-1", connect_timeout_s=60) as client:
            first = client.get_action({"F": frames["F"]}, states, seed=1)
            assert first.actions.shape == (16, 7) and client.server_changes == 0
            stop(proc)
            proc = serve(checkpoint)  # the same settings: its answers are used, once its info is checked
            again = client.get_action({"F": frames["F"]}, states, seed=1, timeout_s=60)
            np.testing.assert_array_equal(again.actions, first.actions)
            client.get_action({"F": frames["F"]}, states, seed=1)
            assert client.server_changes == 1  # checked once, not per call
            stop(proc)
            # the same checkpoint, other default views: it answers a request naming its view, and
            # the client refuses the chunk
            proc = serve(checkpoint, views="F,FL")
            with pytest.raises(PolicyChanged, match=r"another server process .*default_views"):
                client.get_action({"F": frames["F"]}, states, views=["F"], seed=1, timeout_s=60)
            stop(proc)
            proc = serve(other)  # the same address now serves another checkpoint
            with pytest.raises(PolicyChanged, match="now serves other-run@step_0000001"):
                client.get_action({"F": frames["F"]}, states, seed=1, timeout_s=60)
    finally:
        stop(proc)


def _has_session(address: str, session_id: str) -> bool:
    """Whether the policy server at ``address`` holds the session (asking ends it)."""
    with grpc.insecure_channel(address) as ch:
        reset = policy_pb2_grpc.PolicyStub(ch).Reset(policy_pb2.ResetRequest(session_id=session_id), timeout=10)
        return reset.existed


def test_a_robot_leaves_a_frozen_policy_server_after_a_keepalive(checkpoint, observations):
    """Two policy servers behind one address (as a DNS name of two replicas). The robot's client
    pings every 0.5 s: idle for 5 s, its connection stays up (the server accepts the pings; grpc's
    default would answer them with GOAWAY too_many_pings). Then the server it is connected to
    freezes (SIGSTOP: the connection stays open and nothing answers, as from a host gone or behind
    a NAT that forgot the connection): after an unanswered ping the client leaves it, and the other
    server answers. Without keepalive every GetAction ran into the frozen connection to its deadline
    (still so 40 s on, in a trial run)."""
    servers = side_by_side([launch_server(checkpoint, "--views", "F", "--in-process") for _ in range(2)])
    frames, states = observations[3]
    frames = {"F": frames["F"]}
    seen: list[grpc.ChannelConnectivity] = []
    try:
        with PolicyClient("ipv4:" + ",".join(a for _, a in servers), keepalive_s=0.5, timeout_s=2.0) as client:
            client.get_action(frames, states, seed=1)
            client.channel.subscribe(seen.append)
            time.sleep(5.0)  # idle: ten pings (grpc's default answered the sixth with GOAWAY)
            assert seen and set(seen) == {grpc.ChannelConnectivity.READY}, seen
            # the server it reached holds its session (asking ends it: the next answer starts one again)
            on = [i for i, (_, a) in enumerate(servers) if _has_session(a, "robot")]
            assert len(on) == 1
            frozen, other = servers[on[0]], servers[1 - on[0]]
            frozen[0].send_signal(signal.SIGSTOP)
            failed: list[PolicyError] = []

            def answered() -> ActionChunk | None:
                try:
                    return client.get_action(frames, states, seed=1)
                except PolicyError as exc:
                    failed.append(exc)
                    return None

            chunk = wait_for(answered, 30, "an answer from the server that is not frozen")
            assert chunk.views_used == ("F",) and not chunk.degraded
            assert _has_session(other[1], "robot")  # answered there
            assert client.server_changes == 1  # after checking that server's PolicyInfo
            # the calls that ran into the frozen connection: late, or cut when the ping went unanswered
            assert all(e.code in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE) for e in failed)
            client.channel.unsubscribe(seen.append)
    finally:
        stop_all(servers)


def test_health_is_not_serving_until_a_worker_is_ready(checkpoint, observations):
    port, never = free_tcp_port(), free_tcp_port()  # a worker that starts late, and one that never does
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.policy",
            "serve",
            "--checkpoint",
            str(checkpoint),
            "--listen",
            "127.0.0.1:0",
            "--worker",
            f"127.0.0.1:{port}",
            "--worker",
            f"127.0.0.1:{never}",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    worker = None
    try:
        line = proc.stdout.readline()
        assert line.startswith("listening policy "), line + proc.stderr.read()[-2000:]
        addr = line.split()[2]
        health = health_pb2_grpc.HealthStub(grpc.insecure_channel(addr))
        check = lambda: health.Check(health_pb2.HealthCheckRequest(service="viewscale.v1.Policy"), timeout=5).status
        assert check() == health_pb2.HealthCheckResponse.NOT_SERVING
        with pytest.raises(grpc.RpcError) as err:
            policy_pb2_grpc.PolicyStub(grpc.insecure_channel(addr)).GetAction(policy_pb2.ActionRequest(), timeout=5)
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
        # the robot's client answers GetPolicyInfo meanwhile, but connects only once the server serves
        with pytest.raises(PolicyError, match=r"answers but is not serving after 2s \(health NOT_SERVING"):
            PolicyClient(addr, connect_timeout_s=2)
        connected: list[PolicyClient] = []
        waiting = threading.Thread(target=lambda: connected.append(PolicyClient(addr, connect_timeout_s=120)))
        waiting.start()
        time.sleep(1.0)
        assert not connected  # still waiting for SERVING
        worker = start_worker(checkpoint, port=port)
        assert proc.stdout.readline().startswith("ready policy ")
        assert check() == health_pb2.HealthCheckResponse.SERVING
        waiting.join(120)
        frames, states = observations[0]
        assert connected and connected[0].get_action(frames, states).actions.shape == (16, 7)  # no UNAVAILABLE
    finally:
        stop(proc)
        if worker:
            stop(worker[0])
    # serving from the first worker on, and saying that the other is not there yet
    assert "1 of 2 workers ready" in proc.stderr.read()


def test_reflection_lists_the_services(served_f):
    from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

    addr = served_f
    db = ProtoReflectionDescriptorDatabase(grpc.insecure_channel(addr))
    services = set(db.get_services())
    assert {"viewscale.v1.Policy", "grpc.health.v1.Health"} <= services
    assert db.FindFileContainingSymbol("viewscale.v1.Policy").name.endswith("policy.proto")


def test_a_bearer_token_is_required_when_configured(checkpoint, observations):
    env = dict(os.environ, VIEWSCALE_TOKEN="s3cret-token")
    proc, addr = start_server(checkpoint, "--in-process", env=env)
    try:
        with pytest.raises(PolicyError) as err:
            PolicyClient(addr, connect_timeout_s=5)
        assert err.value.code == grpc.StatusCode.UNAUTHENTICATED
        with pytest.raises(PolicyError) as err:
            PolicyClient(addr, token="s3cret-tokeN", connect_timeout_s=5)
        assert err.value.code == grpc.StatusCode.UNAUTHENTICATED
        frames, states = observations[0]
        with PolicyClient(addr, token="s3cret-token") as client:
            assert client.get_action(frames, states).actions.shape == (16, 7)
        health = health_pb2_grpc.HealthStub(grpc.insecure_channel(addr))  # health stays open for probes
        assert health.Check(health_pb2.HealthCheckRequest(), timeout=5).status == health_pb2.HealthCheckResponse.SERVING
    finally:
        stop(proc)


def test_tls_serves_verified_clients_only(checkpoint, observations, tmp_path):
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    made = subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            str(key),
            "-out",
            str(cert),
            "-days",
            "1",
            "-subj",
            "/CN=localhost",
            "-addext",
            "subjectAltName=DNS:localhost,IP:127.0.0.1",
        ],
        capture_output=True,
        text=True,
    )
    assert made.returncode == 0, made.stderr
    proc, addr = start_server(checkpoint, "--in-process", "--set", f"tls.cert={cert}", "--set", f"tls.key={key}")
    try:
        frames, states = observations[0]
        with PolicyClient(addr, tls_ca=cert.read_bytes()) as client:
            assert client.get_action(frames, states).actions.shape == (16, 7)
        with pytest.raises(PolicyError) as err:
            PolicyClient(addr, connect_timeout_s=3)  # plaintext against a TLS server never connects
        assert "if the server serves TLS" in str(err.value) and "(tls_ca)" in str(err.value)  # (before: no hint)
        with pytest.raises(ValueError, match="tls_ca holds no PEM certificate"):  # (before: a handshaker error per try)
            PolicyClient(addr, tls_ca=key.read_bytes())

        # the robot side as the README runs it: the policy teleop, and `viewscale eval --server`,
        # given the CA (before: neither had a setting for it, and neither could reach a TLS server)
        from services.core.config import ConfigError
        from services.teleop.config import PolicyTeleopConfig
        from services.teleop.policy import PolicyTeleop

        driver = PolicyTeleop(PolicyTeleopConfig(server=addr, tls_ca=str(cert)))
        assert driver.client.info.model_id and driver.cameras
        driver.client.close()
        with pytest.raises(ConfigError, match=f"tls_ca {tmp_path / 'none.pem'}: No such file"):
            PolicyTeleop(PolicyTeleopConfig(server=addr, tls_ca=str(tmp_path / "none.pem")))
        out = tmp_path / "eval"
        run = viewscale(
            "eval", "--server", addr, "--tls-ca", str(cert), "--episodes", "1", "--max-ticks", "6", "--views", "F",
            "--out", str(out),
        )  # fmt: skip
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        summary = json.loads((out / "report.json").read_text())["summary"]
        assert summary["requests"] >= 1 and summary["failed_requests"] == 0
        run = viewscale("eval", "--server", addr, "--tls-ca", str(key), "--out", str(tmp_path / "bad"))
        assert run.returncode == 2 and f"--tls-ca {key}: tls_ca holds no PEM certificate" in run.stderr, run.stderr
    finally:
        stop(proc)


def test_the_client_imports_without_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"  # any `import torch` now fails
        "import services.policy.client as c\n"
        "print('ok', 'torch' in sys.modules and sys.modules['torch'] is not None)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok", "False"]


def test_the_chunk_runner_executes_chunks_drops_stale_actions_and_never_blocks(served_f, observations):
    from services.policy.client import ChunkRunner

    addr = served_f
    frames, states = observations[0]
    now = {c: f[-1] for c, f in frames.items()}
    with PolicyClient(addr, session_id="runner") as client:
        for bad, says in [
            (dict(control_hz=0), "control_hz must be positive, got 0"),
            (dict(n_action_steps=0), "n_action_steps must be 1..15 for this policy (Tp - To + 1), got 0"),
            (dict(n_action_steps=16), "got 16"),
            (dict(margin_ticks=-1), "margin_ticks must be 0 or more"),
        ]:
            with pytest.raises(ValueError, match=re.escape(says)):
                ChunkRunner(client, **bad)
        lockstep = ChunkRunner(client, blocking=True, seed=0)
        got = [lockstep.act(t, now, states[-1]) for t in range(20)]
        assert all(fresh for _, fresh in got) and lockstep.stats.underruns == 0
        assert lockstep.stats.requests == 3  # 8 actions a chunk: ticks 0, 8 and 16 asked
        chunk = lockstep.last_chunk
        assert np.array_equal(got[16][0], chunk.actions[chunk.start_index])

        live = ChunkRunner(client, seed=100)
        holding = State(states[-1].eef_pos, states[-1].eef_quat_wxyz, 0.8, states[-1].stamp_ns)
        action, fresh = live.act(0, now, holding)  # the first chunk is on its way: hold still
        assert not fresh and np.array_equal(action[:6], np.zeros(6)) and live.stats.underruns == 1
        # ... with the gripper as it is: closed on an object (reads 0.8), closed (before: open,
        # so an episode begun holding an object dropped it while the first chunk was on its way)
        assert action[6] == 1.0
        deadline = time.monotonic() + 20
        while live._pending is not None and live._pending[1].is_alive():
            assert time.monotonic() < deadline
            time.sleep(0.01)
        action, fresh = live.act(3, now, holding)  # arrived at tick 3: ticks 0-2 went stale
        assert fresh and live.stats.stale_dropped == 3
        c = live.last_chunk
        assert np.array_equal(action, c.actions[c.start_index + 3])
        assert live.stats.requests >= 1 and live.stats.failed == 0


def test_a_rig_given_to_serve_takes_the_place_of_the_checkpoints_calibration(checkpoint, tmp_path, caplog):
    """A camera moved and recalibrated since training is served where it is now (before: the
    checkpoint's calibration of a camera won over the rig's, and there was no way to serve it)."""
    from services.core.rig import load_rig

    rig = tmp_path / "recalibrated.yaml"
    rig.write_text("name: recalibrated\ncameras:\n  F: {yaw_deg: 5}\n")
    trained, _, _ = load_spec(ServerConfig(checkpoint=str(checkpoint)))
    with caplog.at_level("WARNING", logger="services.policy.server"):
        spec, _, _ = load_spec(ServerConfig(checkpoint=str(checkpoint), rig=str(rig), task="lift"))
    moved = load_rig(str(rig), "lift").cameras["F"]
    assert np.allclose(spec.cameras["F"].R_ext, moved.R_ext) and np.allclose(spec.cameras["F"].position, moved.position)
    assert not np.allclose(spec.cameras["F"].R_ext, trained.cameras["F"].R_ext)
    assert np.array_equal(spec.cameras["FL"].R_ext, trained.cameras["FL"].R_ext)  # the others as trained
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith(f"camera F: --rig {rig} differs from the checkpoint's training"), said
    assert "5.00 degrees away" in said[0]

    # a sim rig is framed for a task: with no --task, the checkpoint's (here made a can checkpoint;
    # before: lift's framing, half a metre from can's, for every camera)
    can = tmp_path / "can-checkpoint"
    shutil.copytree(latest_checkpoint(checkpoint), can)
    info = json.loads((can / POLICY_FILE).read_text())
    (can / POLICY_FILE).write_text(json.dumps({**info, "tasks": ["can"]}))
    served = load_spec(ServerConfig(checkpoint=str(can), rig="three15"))[0].cameras
    framed = load_spec(ServerConfig(checkpoint=str(can), rig="three15", task="can"))[0].cameras
    assert np.array_equal(served["F"].position, framed["F"].position)
    assert not np.allclose(served["F"].position, load_rig("three15", "lift").cameras["F"].position)


def test_the_policy_teleop_drives_only_within_an_episode(served_f, observations, caplog):
    """(on hardware it drove the arm from the teleop's start on, an operator resetting the scene
    between two episodes included); `outside_episodes: true` drives there too."""
    from services.pb.sensors_pb2 import RobotState
    from services.teleop.base import CameraFrame
    from services.teleop.config import PolicyTeleopConfig
    from services.teleop.policy import PolicyTeleop

    addr = served_f
    frames, states = observations[3]
    s = states[-1]
    seen = {"F": CameraFrame(*frames["F"][-1])}

    def state(episode: str, gripper: float = 0.4) -> RobotState:
        msg = RobotState(tick=1, eef_pos=list(s.eef_pos), eef_quat_wxyz=list(s.eef_quat_wxyz), gripper=gripper)
        msg.header.stamp_ns, msg.episode_id = s.stamp_ns, episode
        return msg

    for outside in (False, True):
        # (no calibration will come: no wait for it here; its wait is tested with a bus below)
        cfg = PolicyTeleopConfig(server=addr, blocking=True, outside_episodes=outside, calibration_wait_s=0)
        driver = PolicyTeleop(cfg)
        try:
            between = driver.act(state(""), None, seen)
            asked = driver.runner.stats.requests if driver.runner is not None else 0
            assert (asked > 0) == outside, (outside, asked)
            if not outside:  # held still, the gripper as it is: no GetAction
                assert not between.dp.any() and not between.drot.any() and between.gripper == 0.0
                # closed on an object (reads 0.8): kept closed (before: commanded to 0.8, the
                # reading, where a gripper holds no grip; and again at every tick's reading)
                assert driver.act(state("", 0.8), None, seen).gripper == 1.0
            driver.reset("lift", "ep-1")
            with caplog.at_level("WARNING", logger="services.teleop.policy"):
                driver.act(state("ep-1"), None, seen)
                driver.act(state("ep-1"), None, seen)
            assert driver.runner.stats.requests > 0
            # attached to no bus, it heard no calibration: said once, as it began to drive
            said = [r.getMessage() for r in caplog.records if "no calibration and pose heard" in r.getMessage()]
            assert len(said) == 1 and said[0].startswith("no calibration and pose heard from camera F in 0 s:")
            caplog.clear()
        finally:
            driver.close()


def test_the_policy_teleop_holds_still_while_a_camera_is_calibrated_elsewhere_than_the_server_has_it(
    served_f, observations, make_bus, tmp_path
):
    """A camera-space policy's actions are turned into the base frame with the server's calibration
    of each view. A camera that publishes another one (moved and recalibrated since training, or a
    server started with another rig) would send the arm the wrong way: the policy teleop holds it
    still and says why, and drives again once they agree. Before, it drove."""
    from services.core import topics
    from services.core.clock import now_ns
    from services.core.rig import load_rig
    from services.pb.sensors_pb2 import RobotState
    from services.teleop.base import CameraFrame
    from services.teleop.config import PolicyTeleopConfig
    from services.teleop.policy import PolicyTeleop

    moved = tmp_path / "moved.yaml"
    moved.write_text("name: moved\ncameras:\n  F: {yaw_deg: 5}\n")
    addr = served_f
    frames, states = observations[3]
    s = states[-1]
    seen = {"F": CameraFrame(*frames["F"][-1])}
    msg = RobotState(tick=1, eef_pos=list(s.eef_pos), eef_quat_wxyz=list(s.eef_quat_wxyz), gripper=0.0)
    msg.header.stamp_ns, msg.episode_id = s.stamp_ns, "ep-1"
    driver = PolicyTeleop(PolicyTeleopConfig(server=addr, blocking=True, calibration_wait_s=1.0))
    driver.attach(make_bus())
    camera_bus = make_bus()
    calibration = camera_bus.publisher(topics.camera_calibration("F"))
    pose = camera_bus.publisher(topics.camera_pose("F"))

    def publish(rig: str) -> None:
        cam = load_rig(rig, "lift").cameras["F"]
        calibration.put(cam.calibration_msg(32, 32, now_ns()))
        pose.put(cam.pose_msg(now_ns()))

    def asks() -> int:  # GetAction requests after one more tick
        driver.act(msg, None, seen)
        return driver.runner.stats.requests

    try:
        driver.reset("lift", "ep-1")
        time.sleep(1.2)  # the episode begins later than calibration_wait_s after the teleop's start
        # no calibration heard yet: it holds still for it (up to calibration_wait_s from this first
        # tick), asking nothing (before: it drove, unchecked)
        held = driver.act(msg, None, seen)
        assert not held.dp.any() and not held.drot.any() and driver.runner.stats.requests == 0
        publish("three15")  # where the checkpoint was trained: it drives
        time.sleep(0.3)
        assert asks() > 0 and driver.refused is None
        publish(str(moved))
        wait_for(lambda: driver._moved_cameras(), what="the moved camera's calibration")
        driver.reset("lift", "ep-2")
        held = driver.act(msg, None, seen)  # holds still, asks nothing
        assert not held.dp.any() and not held.drot.any() and driver.runner.stats.requests == 0
        says = driver.refused
        assert says.startswith("camera F: placed ") and "5.00 degrees away" in says and "serve --rig" in says
        publish("three15")  # back where the server has it
        wait_for(lambda: not driver._moved_cameras(), what="the camera's calibration to agree again")
        assert asks() > 0
    finally:
        driver.close()

    # through the whole path: `viewscale eval` against this server (trained and served for
    # lift's framing) on can, whose sim places the cameras elsewhere: held still, exit 1, why
    out = tmp_path / "eval"
    run = viewscale(
        "eval", "--server", addr, "--task", "can", "--rig", "three15", "--episodes", "1", "--max-ticks", "6",
        "--views", "F", "--out", str(out),
    )  # fmt: skip
    assert run.returncode == 1, run.stdout[-2000:] + run.stderr[-2000:]
    assert "error: the policy held the arm still in 1 of 1 episodes: camera F: placed " in run.stderr
    summary = json.loads((out / "report.json").read_text())["summary"]
    assert summary["refused_episodes"] == 1 and summary["requests"] == 0


def test_a_getaction_that_fails_every_tick_is_logged_once_a_while_not_every_tick(served_f, caplog):
    """Frames of another size than the policy's (a camera service set up otherwise): every
    GetAction is refused. The policy teleop holds still and says why, once, then how many more
    failed (before: a warning per tick, 20 lines a second, for as long as it lasted)."""
    import cv2

    from services.pb.sensors_pb2 import RobotState
    from services.teleop.base import CameraFrame
    from services.teleop.config import PolicyTeleopConfig
    from services.teleop.policy import PolicyTeleop

    addr = served_f
    jpeg = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))[1].tobytes()  # the policy's are 32x32
    # (attached to no bus, it hears no calibration: no wait for it here)
    driver = PolicyTeleop(PolicyTeleopConfig(server=addr, blocking=True, calibration_wait_s=0))
    try:
        driver.reset("lift", "ep-1")
        with caplog.at_level("WARNING", logger="services.teleop.policy"):
            for tick in range(30):
                msg = RobotState(tick=tick, eef_pos=[0.45, 0.0, 0.25], eef_quat_wxyz=[0.0, 1.0, 0.0, 0.0])
                msg.header.stamp_ns, msg.episode_id = time.time_ns(), "ep-1"
                held = driver.act(msg, None, {"F": CameraFrame(jpeg, msg.header.stamp_ns)})
                assert not held.dp.any()
        assert driver.runner.stats.failed == 30 and "INVALID_ARGUMENT" in driver.first_error
        said = [r.getMessage() for r in caplog.records if "GetAction failed" in r.getMessage()]
        assert 1 <= len(said) <= 3, said  # the first, then at most one line every 5 s
        assert "16x16" in said[0] or "size" in said[0], said[0]
    finally:
        driver.close()


def test_a_lockstep_runner_waits_for_a_server_that_restarts_instead_of_holding_the_arm(checkpoint, observations):
    """In lockstep (`viewscale eval`) the sim waits for each chunk: a policy server that is down or
    still loading when a chunk is due is waited for, within the client's deadline. Before, every
    tick's request failed at once and the arm was held tick after tick: an evaluation whose server
    restarted lost its episodes to it (by hand: 603 of 665 requests failed, 7 of 8 episodes)."""
    from services.policy.client import ChunkRunner

    port = free_tcp_port()
    args = ["serve", "--checkpoint", str(checkpoint), "--listen", f"127.0.0.1:{port}", "--views", "F", "--in-process"]
    proc = start(args, "policy")[0]
    try:
        with PolicyClient(f"127.0.0.1:{port}", session_id="lockstep", timeout_s=120) as client:
            runner = ChunkRunner(client, blocking=True, views=["F"])
            ticks = [({"F": frames["F"][-1]}, states[-1]) for frames, states in observations]
            _, fresh = runner.act(0, *ticks[0])
            assert fresh
            stop(proc)
            proc = launch(args, "policy")  # not waited for: it loads while the next chunk is due
            for tick in range(1, runner.n_action_steps + 1):  # the last one needs the next chunk
                _, fresh = runner.act(tick, *ticks[tick])
                assert fresh, (tick, runner.stats)
            assert runner.stats.failed == 0 and runner.stats.underruns == 0
            # and while it waits for a server that is down, its caller stopping (cancel) ends the wait
            stop(proc)
            for tick in range(runner.n_action_steps + 1, 2 * runner.n_action_steps):
                assert runner.act(tick, *ticks[tick % len(ticks)])[1]
            threading.Timer(1.0, runner.cancel.set).start()
            t0 = time.monotonic()
            _, fresh = runner.act(2 * runner.n_action_steps, *ticks[0])
            assert not fresh and time.monotonic() - t0 < 5.0  # a hold, at once (not at the 120 s deadline)
    finally:
        stop(proc)


def test_a_lockstep_runner_waits_once_for_a_server_gone_for_good_then_no_more(checkpoint, observations):
    """A server that does not come back within the deadline: that one request waited the deadline
    out, the next ones fail at once (a hold each), until the server answers again. Otherwise an
    evaluation whose server died would cost every tick the whole deadline."""
    from services.policy.client import ChunkRunner

    port = free_tcp_port()
    args = ["serve", "--checkpoint", str(checkpoint), "--listen", f"127.0.0.1:{port}", "--views", "F", "--in-process"]
    proc = start(args, "policy")[0]
    ticks = [({"F": frames["F"][-1]}, states[-1]) for frames, states in observations]
    try:
        with PolicyClient(f"127.0.0.1:{port}", session_id="lockstep", timeout_s=2) as client:
            runner = ChunkRunner(client, blocking=True, views=["F"])
            n = runner.n_action_steps
            for tick in range(n):
                assert runner.act(tick, *ticks[tick % len(ticks)])[1]
            stop(proc)

            def timed(tick: int) -> tuple[bool, float]:
                t0 = time.monotonic()
                fresh = runner.act(tick, *ticks[tick % len(ticks)])[1]
                return fresh, time.monotonic() - t0

            fresh, waited = timed(n)
            assert not fresh and 1.5 < waited < 10 and client.waited_out  # the deadline, waited out
            fresh, waited = timed(n + 1)
            assert not fresh and waited < 1.0  # at once
            proc = start(args, "policy")[0]
            tick, deadline = n + 2, time.monotonic() + 60  # (holds until gRPC's channel reconnects)
            while not timed(tick)[0]:
                assert time.monotonic() < deadline, runner.stats
                tick += 1
                time.sleep(0.2)
            assert not client.waited_out  # answered again: the next outage is waited for again
    finally:
        stop(proc)
