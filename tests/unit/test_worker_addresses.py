"""Worker addresses: which ones gRPC may balance over several replicas, and that the CLI keeps
an address with commas whole."""

from __future__ import annotations

import argparse

import pytest

from services.policy.cli import _load, add_policy_commands
from services.policy.config import ServerConfig
from services.policy.server import may_balance


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
