"""Shared fixtures: a real Zenoh router on a free loopback port, and bus configs to join it."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before anything imports mujoco

import shutil
import subprocess

import pytest

from services.core.bus import Bus, BusConfig, free_tcp_port, router


@pytest.fixture
def zenoh_endpoint():
    """A router on tcp/127.0.0.1:<free port>; yields the endpoint services connect to."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    hub = router([endpoint])
    yield endpoint
    hub.close()


@pytest.fixture
def bus_config(zenoh_endpoint) -> BusConfig:
    return BusConfig(mode="client", connect=[zenoh_endpoint])


@pytest.fixture
def make_bus(bus_config):
    opened: list[Bus] = []

    def _make() -> Bus:
        bus = Bus(bus_config)
        opened.append(bus)
        return bus

    yield _make
    for bus in opened:
        bus.close()


def _docker_usable() -> bool:
    if shutil.which("docker") is None:
        return False
    return subprocess.run(["docker", "info"], capture_output=True).returncode == 0


def pytest_collection_modifyitems(config, items):
    import torch  # noqa: F401  (gpu marker)

    if not torch.cuda.is_available():
        skip_gpu = pytest.mark.skip(reason="no CUDA device on this machine")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip_gpu)
