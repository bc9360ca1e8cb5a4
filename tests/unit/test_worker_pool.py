"""The server's worker pool: which addresses gRPC may balance over several replicas, that the CLI
keeps an address with commas whole, and where a request's views are placed."""

from __future__ import annotations

import argparse

import pytest
import torch

from services.policy.cli import _load, add_policy_commands
from services.policy.config import ServerConfig
from services.policy.server import may_balance
from services.policy.worker import accelerator_id


@pytest.mark.parametrize(
    "address, balanced",
    [
        ("127.0.0.1:7001", False),
        ("[::1]:7001", False),
        ("10.0.0.5:7001", False),
        ("unix:/tmp/worker.sock", False),
        ("ipv4:127.0.0.1:7001", False),
        ("ipv4:127.0.0.1:7001,127.0.0.1:7002", True),
        ("ipv6:[::1]:7001,[::1]:7002", True),
        ("dns:///policy-worker:7001", True),
        ("policy-worker:7001", True),  # a host name may resolve to every replica
        ("localhost:7001", True),
    ],
)
def test_which_addresses_may_reach_several_replicas(address, balanced):
    assert may_balance(address) is balanced


def test_a_worker_address_with_commas_stays_one_address():
    parser = argparse.ArgumentParser()
    add_policy_commands(parser.add_subparsers())
    many = "ipv4:127.0.0.1:7001,127.0.0.1:7002"
    args = parser.parse_args(["serve", "--checkpoint", "ck", "--worker", many, "--worker", "10.0.0.5:7001"])
    cfg = _load(ServerConfig, args, ["checkpoint", "worker"], "policy")
    assert cfg.worker == [many, "10.0.0.5:7001"]


def _pool(placement: str, devices: list[str], streams: list[int], machines=None, cores=None, gpus=None):
    """A pool of admitted workers (channels to nowhere: placing opens no call); by default all on
    one machine with the same two cores, and GPU workers that did not say which GPU they hold."""
    import asyncio

    from services.policy.server import WorkerPool

    machines = machines or ["m"] * len(devices)
    cores = cores or [{0, 1}] * len(devices)
    gpus = gpus or [""] * len(devices)

    async def make():
        pool = WorkerPool([f"127.0.0.1:{7001 + i}" for i in range(len(devices))], "sha", placement=placement)
        for w, dev, n, m, c, g in zip(pool.workers, devices, streams, machines, cores, gpus):
            w.healthy, w.device, w.streams, w.machine, w.cores, w.accelerator = True, dev, n, m, frozenset(c), g
        return pool

    return asyncio.run(make())


def _where(placed) -> dict[str, int]:
    return {v: int(w.address.rsplit(":", 1)[1]) - 7001 for v, w in placed.items()}


def test_pack_puts_a_requests_views_on_the_least_loaded_worker():
    pool = _pool("pack", ["cpu"] * 3, [2, 1, 3])
    assert _where(pool.place(["F", "FL", "FR"])) == {"F": 1, "FL": 1, "FR": 1}
    assert [w.streams for w in pool.workers] == [2, 4, 3]
    assert _where(pool.place(["F"])) == {"F": 0}  # the next request: now the least loaded


def test_spread_gives_each_view_its_own_worker_while_there_are_any():
    pool = _pool("spread", ["cpu"] * 3, [0, 0, 0])
    assert _where(pool.place(["F", "FL", "FR", "FU"])) == {"F": 0, "FL": 1, "FR": 2, "FU": 0}
    pool.workers[1].healthy = False
    assert set(_where(pool.place(["F", "FL"])).values()) == {0, 2}


def test_auto_packs_on_cpu_workers_and_spreads_on_gpus():
    assert len(set(_where(_pool("auto", ["cpu"] * 3, [0] * 3).place(["F", "FL", "FR"])).values())) == 1
    gpus = _pool("auto", ["cuda:0", "cuda:1", "cuda:0"], [0] * 3)
    assert len(set(_where(gpus.place(["F", "FL", "FR"])).values())) == 3
    mixed = _pool("auto", ["cpu", "cuda:0"], [0, 0])
    assert len(set(_where(mixed.place(["F", "FL"])).values())) == 2


def test_auto_spreads_over_machines_and_disjoint_cores_and_packs_where_cores_are_shared():
    # three CPU workers on three machines: a view each
    apart = _pool("auto", ["cpu"] * 3, [0] * 3, machines=["a", "b", "c"])
    assert _where(apart.place(["F", "FL", "FR"])) == {"F": 0, "FL": 1, "FR": 2}
    # one machine, pinned to cores of their own (taskset, cpusets): a view each
    pinned = _pool("auto", ["cpu"] * 2, [0] * 2, cores=[{0, 1}, {2, 3}])
    assert _where(pinned.place(["F", "FL"])) == {"F": 0, "FL": 1}
    # overlapping cores compete: 0 and 1 share core 1, 1 and 2 share core 2 -- one group of three
    chain = _pool("auto", ["cpu"] * 3, [0] * 3, cores=[{0, 1}, {1, 2}, {2, 3}])
    assert len(chain.units()) == 1 and set(_where(chain.place(["F", "FL", "FR"])).values()) == {0}
    # a worker that did not say which cores (an empty set) competes with every CPU worker there
    unsaid = _pool("auto", ["cpu"] * 2, [0] * 2, cores=[set(), {3}])
    assert len(unsaid.units()) == 1
    # two groups, three views: 0 and 2 compete (core 0), 1 is alone; the third view joins the
    # least-loaded worker the request uses, and worker 2 gets none (it would take turns with 0)
    mixed = _pool("auto", ["cpu"] * 3, [0] * 3, cores=[{0}, {1}, {0}])
    assert [[int(w.address[-1]) - 1 for w in u] for u in mixed.units()] == [[0, 2], [1]]
    assert _where(mixed.place(["F", "FL", "FR"])) == {"F": 0, "FL": 1, "FR": 0}
    # a loaded worker in a group: the group's least-loaded one is used
    loaded = _pool("auto", ["cpu"] * 3, [5, 0, 0], cores=[{0}, {1}, {0}])
    assert _where(loaded.place(["F", "FL"])) == {"F": 2, "FL": 1}
    # a GPU beside a machine's CPU workers: the GPU is a group of its own
    gpu = _pool("auto", ["cpu", "cpu", "cuda:0"], [0] * 3)
    assert _where(gpu.place(["F", "FL", "FR"])) == {"F": 0, "FL": 2, "FR": 0}


def test_auto_packs_workers_that_share_a_gpu_and_spreads_over_gpus():
    # `serve --workers 3 --device cuda` on a one-GPU machine: three workers on one GPU (one UUID)
    # would only take turns on it; one worker computes a request's views in one batched pass
    one = _pool("auto", ["cuda:0"] * 3, [0] * 3, gpus=["GPU-a"] * 3)
    assert len(one.units()) == 1 and set(_where(one.place(["F", "FL", "FR"])).values()) == {0}
    assert _where(one.place(["F"])) == {"F": 1}  # the next request: the group's least-loaded worker
    # the index says nothing (CUDA_VISIBLE_DEVICES renumbers per process): two "cuda:0" on two GPUs
    two = _pool("auto", ["cuda:0", "cuda:0", "cuda:1"], [0] * 3, gpus=["GPU-a", "GPU-b", "GPU-a"])
    assert [[int(w.address[-1]) - 1 for w in u] for u in two.units()] == [[0, 2], [1]]
    assert _where(two.place(["F", "FL", "FR"])) == {"F": 0, "FL": 1, "FR": 0}
    # the same id on two machines is not one GPU; a GPU and a CPU worker never compete
    apart = _pool("auto", ["cuda:0", "cuda:0", "cpu"], [0] * 3, machines=["a", "b", "a"], gpus=["GPU-a", "GPU-a", ""])
    assert len(apart.units()) == 3


MIG_A = "MIG-5c1f2e3d-0a1b-5c2d-8e3f-4a5b6c7d8e9f"
MIG_B = "MIG-GPU-41255406-c9af-f94b-4ebf-9d57ad1853da/1/0"  # the older form, GPU UUID/GI/CI


@pytest.mark.parametrize(
    "visible, index, want",
    [(MIG_A, 0, MIG_A), (MIG_B, 0, MIG_B), (f" {MIG_A} ", 0, MIG_A), (f"GPU-x,{MIG_B}", 1, MIG_B)],
)
def test_a_mig_slice_is_named_by_its_cuda_visible_devices_entry(monkeypatch, visible, index, want):
    # (no CUDA here: a MIG entry is answered before any call into CUDA, so this runs on CPU)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    assert accelerator_id(torch.device("cuda", index)) == want
    assert accelerator_id(torch.device("cpu")) == ""


def test_workers_on_two_mig_slices_of_one_gpu_are_spread():
    # two slices are two GPUs for placement: a request's views go to both, in parallel
    pool = _pool("auto", ["cuda:0", "cuda:0"], [0, 0], gpus=[MIG_A, MIG_B])
    assert len(pool.units()) == 2 and _where(pool.place(["F", "FL"])) == {"F": 0, "FL": 1}


def test_no_healthy_worker_places_nothing_and_a_bad_placement_is_refused():
    pool = _pool("pack", ["cpu"], [0])
    pool.workers[0].healthy = False
    assert pool.place(["F", "FL"]) == {}
    with pytest.raises(ValueError, match="placement 'tight'"):
        _pool("tight", ["cpu"], [0])
