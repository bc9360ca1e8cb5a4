"""Which worker and policy-server addresses are refused before gRPC is given them.

gRPC takes any string as a target and fails on every call when it cannot use it; a server given
such a worker waited its whole worker_ready_s. Every form gRPC documents for a client must pass.
"""

from __future__ import annotations

import pytest

from services.policy.transport import bad_target

ACCEPTED = [
    "127.0.0.1:50051",
    "localhost:7001",
    "policy-worker:7001",
    "[::1]:7001",
    "dns:///policy-worker:7001",  # (the compose profile's)
    "dns://10.0.0.2/policy-worker:7001",
    "dns:policy-worker:7001",
    "ipv4:10.0.0.5:7001,10.0.0.6:7001",
    "ipv6:[::1]:7001,[fe80::1]:7002",
    "unix:/run/viewscale/worker.sock",
    "unix-abstract:viewscale-worker",
    "xds:///policy-worker",
]

REFUSED = [
    ("http://10.0.0.5:7001", "http:// is not a gRPC address: give host:port (e.g. 10.0.0.5:7001)"),
    ("grpc://10.0.0.5:7001/", "grpc:// is not a gRPC address: give host:port (e.g. 10.0.0.5:7001)"),
    ("10.0.0.5", "10.0.0.5 has no port (gRPC would use 443): give host:port"),
    ("dns:///policy-worker", "policy-worker has no port (gRPC would use 443): give host:port"),
    ("10.0.0.5:", "nothing after the last ':': give host:port"),
    ("10.0.0.5:http", "port 'http' is not a number"),
    ("10.0.0.5:99999", "port 99999 is beyond 65535"),
    ("ipv4:10.0.0.5:7001,10.0.0.6:70001", "port 70001 is beyond 65535"),
    ("10.0.0.5:0", "port 0 is no port to connect to"),
    (":7001", "no host before :7001"),
    ("fe80::1:7001", "host 'fe80::1' has a ':' in it (an IPv6 address goes in brackets: [::1]:7001)"),
    ("10.0.0.5 :7001", "has a space in it"),
    ("unix:", "nothing after unix:"),
]


@pytest.mark.parametrize("target", ACCEPTED)
def test_every_form_grpc_documents_is_accepted(target):
    assert bad_target(target) is None


@pytest.mark.parametrize(("target", "says"), REFUSED)
def test_a_target_grpc_cannot_use_is_refused_saying_why(target, says):
    assert bad_target(target) == says
