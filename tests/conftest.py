"""Shared fixtures: a real Zenoh router on a free loopback port, bus configs to join it, and one
small sim dataset recorded through the real services for the training tests."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import subprocess
from pathlib import Path

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


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_PYTEST_HANDLERS: dict[int, object] = {}


def pytest_configure(config):
    # Headless MuJoCo for every test process and the services it starts (set here, never at import).
    os.environ.setdefault("MUJOCO_GL", "egl")
    _PYTEST_HANDLERS.update({sig: signal.getsignal(sig) for sig in _STOP_SIGNALS})


@pytest.fixture(autouse=True)
def _stop_signals_restored():
    """A test that runs a command in-process (``viewscale(...)``, in the test or in a session fixture
    it sets up) gets that command's stop-signal handlers; the next test, and the processes it forks,
    get pytest's again."""
    yield
    for sig, handler in _PYTEST_HANDLERS.items():
        if signal.getsignal(sig) is not handler:
            signal.signal(sig, handler)


def pytest_sessionfinish(session, exitstatus):
    """Child processes a test left running fail the run and are killed here. Left to pytest's exit,
    multiprocessing would join them after a SIGTERM that a training's loader workers ignore: the
    run would hang (the project's CI once waited out its 90 minutes so)."""
    left = multiprocessing.active_children()
    for child in left:
        child.kill()
        child.join(10)
    if left:
        names = ", ".join(f"{c.name} (pid {c.pid})" for c in left)
        print(f"\nerror: the tests left {len(left)} child process(es) running, killed now: {names}")
        if session.exitstatus == 0:
            session.exitstatus = 1


def pytest_collection_modifyitems(config, items):
    gpu_items = [item for item in items if "gpu" in item.keywords]
    if not gpu_items:
        return  # torch is imported only where a test needs it
    import torch

    if not torch.cuda.is_available():
        skip_gpu = pytest.mark.skip(reason="no CUDA device on this machine")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip_gpu)


SIM_VIEWS = ["F", "FL", "FR"]


@pytest.fixture(scope="session")
def sim_dataset(tmp_path_factory) -> Path:
    """Two scripted lift episodes on the three15 rig (32 px, lockstep), recorded by `viewscale collect`
    and built into a camera-space dataset by `viewscale dataset build`."""
    from services.cli import main as viewscale

    root = tmp_path_factory.mktemp("sim")
    raw, ds = root / "raw", root / "ds"
    assert (
        viewscale(
            [
                "collect",
                "--task",
                "lift",
                "--episodes",
                "2",
                "--rig",
                "three15",
                "--out",
                str(raw),
                "--size",
                "32",
                "--fast",
            ]
        )
        == 0
    )
    assert (
        viewscale(
            [
                "dataset",
                "build",
                "--raw",
                str(raw),
                "--views",
                ",".join(SIM_VIEWS),
                "--space",
                "camera",
                "--out",
                str(ds),
                "--image-size",
                "32x32",
                "--contact-episodes",
                "0",
            ]
        )
        == 0
    )
    return ds


@pytest.fixture(scope="session")
def tiny_checkpoint(sim_dataset, tmp_path_factory) -> Path:
    """A tiny policy (few channels, 4 DDIM steps) trained 3 steps on ``sim_dataset``: real weights, real files."""
    from services.trainer.config import train_config_from_dict
    from services.trainer.train import train

    out = tmp_path_factory.mktemp("tiny-policy") / "run"
    model = {
        "down_dims": [16, 32],
        "diffusion_step_embed_dim": 16,
        "noise": {"num_inference_steps": 4},
        # width 8, not 4: at width 4 torch 2.15's CPU backward of this encoder corrupts the heap
        # here (glibc aborts; seen in a plain training script too)
        "encoder": {"width": 8, "num_keypoints": 4, "feature_dim": 8},
    }
    cfg = {
        "preset": "tiny",
        "data": str(sim_dataset),
        "out": str(out),
        "steps": 3,
        "batch_size": 4,
        "num_workers": 0,
        "progress": False,
        "val_every": 0,
        "checkpoint_every": 0,
        "validation": False,
        "model": model,
    }
    train(train_config_from_dict(cfg))
    return out
