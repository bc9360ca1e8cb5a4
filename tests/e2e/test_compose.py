"""`docker compose up` for a sim collection session, as a user runs it, on a machine that may have
no Docker at all and no image registry.

Steps (each a script a user runs too, see deploy/docker/README.md): start an engine, make
`docker compose` v2 available, build the local Debian base image, build the collection image on
it, run one short lift episode, and read the episode back with the ``mcap`` library.

Skipped only when no engine can be started on this machine (not root and no sudo, no dockerd to
be had); under CI (``CI`` set) that is a failure, never a skip.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from services.core.bus import free_tcp_port
from services.core.rig import load_rig

# (no per-test timeout: each step below has its own, the image builds up to 30 minutes on a fresh machine)
pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(0)]

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "deploy" / "docker"
LOCAL_BASE = "viewscale-base:bookworm"
TASK, RIG, SIZE = "lift", "five15", 84


def run(cmd: list[str], timeout: float, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    start = time.monotonic()
    print(f"$ {shlex.join(cmd)}", flush=True)
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    print(f"  -> exit {proc.returncode} in {time.monotonic() - start:.1f} s", flush=True)
    return proc


def output(proc: subprocess.CompletedProcess, lines: int = 60) -> str:
    text = (proc.stdout or "") + (proc.stderr or "")
    return "\n".join(text.splitlines()[-lines:])


def ca_bundle() -> str | None:
    """The CA bundle pip on this machine is told to trust, so pip in the image build trusts it too
    (a TLS-intercepting proxy's CA lives there); None: pip's own certificates."""
    for name in ("VIEWSCALE_CA_BUNDLE", "PIP_CERT", "SSL_CERT_FILE", "REQUESTS_CA_BUNDLE"):
        path = os.environ.get(name)
        if path and Path(path).is_file():
            return path
    return None


@pytest.fixture(scope="module")
def engine() -> None:
    proc = run(["bash", str(SCRIPTS / "ensure-engine.sh")], timeout=900)
    if proc.returncode != 0:
        reason = f"no Docker engine could be started here:\n{output(proc, 20)}"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)


@pytest.fixture(scope="module")
def compose_env(engine, tmp_path_factory) -> dict[str, str]:
    """Environment for `docker compose` with the collection image built."""
    proc = run(["bash", str(SCRIPTS / "ensure-compose.sh")], timeout=900)
    assert proc.returncode == 0, output(proc)

    base = os.environ.get("VIEWSCALE_BASE_IMAGE", LOCAL_BASE)
    if base == LOCAL_BASE:
        proc = run(["bash", str(SCRIPTS / "build-base-image.sh")], timeout=900)
        assert proc.returncode == 0, output(proc)

    data = tmp_path_factory.mktemp("compose") / "raw"
    data.mkdir()
    env = dict(
        os.environ,
        BASE_IMAGE=base,
        VIEWSCALE_DATA=str(data),
        VIEWSCALE_UID=str(os.getuid()),
        VIEWSCALE_GID=str(os.getgid()),
        EPISODES="1",
        TASK=TASK,
        RIG=RIG,
        COMPOSE_PROJECT_NAME=f"viewscale-e2e-{os.getpid()}",
        COMPOSE_PROGRESS="plain",
    )
    if bundle := ca_bundle():
        env["VIEWSCALE_CA_BUNDLE"] = bundle
    proc = run(["docker", "compose", "build"], timeout=1800, env=env)
    assert proc.returncode == 0, output(proc)
    return env


@pytest.fixture(scope="module")
def session(compose_env) -> tuple[Path, subprocess.CompletedProcess]:
    """One `docker compose up` that records one episode and stops when the session exits."""
    try:
        proc = run(["docker", "compose", "up", "--exit-code-from", "session"], timeout=900, env=compose_env)
    finally:
        run(["docker", "compose", "down", "--remove-orphans"], timeout=120, env=compose_env)
    return Path(compose_env["VIEWSCALE_DATA"]), proc


def test_session_records_one_episode_and_stops_the_stack(session):
    data, proc = session
    assert proc.returncode == 0, output(proc, 120)
    assert "recorded 1 episodes" in proc.stdout, output(proc, 120)
    files = sorted(data.glob("*.mcap"))
    assert len(files) == 1, sorted(p.name for p in data.iterdir())
    assert not list(data.glob("*.part")), "the recorder left an unfinished file"
    assert files[0].stat().st_uid == os.getuid(), "episode files belong to the user who ran compose"


def test_episode_reads_back_with_an_image_channel_per_rig_camera(session):
    data, _ = session
    (path,) = sorted(data.glob("*.mcap"))
    cameras = sorted(load_rig(RIG).names)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{path} has no summary"
        channels = {ch.topic: ch for ch in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        for name in cameras:
            topic = f"/camera/{name}/image"
            assert topic in channels, f"{topic} missing; channels: {sorted(channels)}"
            channel = channels[topic]
            assert summary.schemas[channel.schema_id].name == "foxglove.CompressedImage"
            assert counts.get(channel.id, 0) > 0, f"{topic} has no messages"
        # Every camera's first frame decodes to an image of the configured size.
        seen: set[str] = set()
        topics = [f"/camera/{name}/image" for name in cameras]
        for _, channel, _, msg in reader.iter_decoded_messages(topics=topics):
            if channel.topic in seen:
                continue
            seen.add(channel.topic)
            img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
            assert img is not None and img.shape == (SIZE, SIZE, 3), channel.topic
            if len(seen) == len(topics):
                break
        assert len(seen) == len(topics)


def test_the_real_profile_adds_the_hardware_services_and_leaves_the_sim_session_alone(engine):
    """`docker compose --profile real ...` (README "Real robot"): the robot, camera, teleop and
    recorder services read deploy/real.yaml from an image with the hardware extra, the camera gets
    the video and USB devices, and none of them takes the sim session's TASK/RIG overrides (which
    would replace the calibrated rig real.yaml names). Plain `docker compose up` is unchanged."""
    import json

    proc = run(["bash", str(SCRIPTS / "ensure-compose.sh")], timeout=900)
    assert proc.returncode == 0, output(proc)
    sim = run(["docker", "compose", "config", "--services"], timeout=60)
    assert sim.returncode == 0, output(sim)
    assert set(sim.stdout.split()) == {"router", "sim", "teleop", "recorder", "session"}
    real = run(["docker", "compose", "--profile", "real", "config", "--format", "json"], timeout=60)
    assert real.returncode == 0, output(real)
    services = json.loads(real.stdout)["services"]
    hardware = {"robot", "camera", "teleop-device", "teleop-keyboard", "recorder-real"}
    assert hardware <= set(services)
    for name in hardware:
        svc = services[name]
        assert "deploy/real.yaml" in svc["command"], (name, svc["command"])
        assert svc["build"]["args"]["EXTRAS"] == "hardware", name
        assert not {"VIEWSCALE_RIG", "VIEWSCALE_TASK"} & set(svc.get("environment", {})), name
    assert {"c 81:* rmw", "c 189:* rmw"} <= set(services["camera"]["device_cgroup_rules"])
    assert services["teleop-keyboard"]["tty"] and services["teleop-keyboard"]["stdin_open"]
    assert "lab" in services["robot"]["networks"] and "lab" in services["camera"]["networks"]


def test_the_serve_profile_runs_a_server_over_every_worker_replica(engine):
    """`docker compose --profile serve up --scale policy-worker=N policy policy-worker`: the server
    reaches every worker replica through one DNS name (gRPC round-robin), both read the checkpoint
    volume, the image has the `train` extra, only the server's port is published, on loopback, and
    docker starts a server or worker that dies again."""
    import json

    proc = run(["bash", str(SCRIPTS / "ensure-compose.sh")], timeout=900)
    assert proc.returncode == 0, output(proc)
    env = dict(os.environ, VIEWSCALE_CHECKPOINT="/srv/ckpt")
    serve = run(["docker", "compose", "--profile", "serve", "config", "--format", "json"], timeout=60, env=env)
    assert serve.returncode == 0, output(serve)
    services = json.loads(serve.stdout)["services"]
    server, worker = services["policy"], services["policy-worker"]
    assert "dns:///policy-worker:7001" in server["command"] and "--checkpoint" in worker["command"]
    for svc in (server, worker):
        assert svc["build"]["args"]["EXTRAS"] == "train"
        assert svc["restart"] == "unless-stopped"
        assert any(v["source"] == "/srv/ckpt" and v["target"] == "/checkpoint" for v in svc["volumes"])
    [port] = server["ports"]
    assert port["host_ip"] == "127.0.0.1" and port["target"] == 50051
    assert "ports" not in worker


@pytest.mark.long  # builds the serving image: torch and its CUDA libraries, about 7 GB
def test_the_serve_profile_answers_from_the_host_and_goes_on_when_a_replica_it_knew_alone_dies(
    compose_env, tiny_checkpoint
):
    """`docker compose --profile serve up --scale policy-worker=N policy policy-worker`, as
    docker-compose.yml says to run it, on a real checkpoint volume: the robot's client on the host
    connects through the published loopback port (once the server serves) and gets chunks composed
    over every view. Then a second replica is added and the first, the only one the server has
    resolved so far, is killed: the server finds the new one within seconds (grpc's default was
    to resolve the name again only 30 s after the last time: 25 s of refusals, measured)."""
    from services.policy.client import PolicyClient, PolicyError, State

    port = free_tcp_port()
    env = dict(
        compose_env,
        VIEWSCALE_CHECKPOINT=str(tiny_checkpoint),
        VIEWSCALE_POLICY_PORT=str(port),
        COMPOSE_PROJECT_NAME=f"viewscale-serve-{os.getpid()}",
    )
    serve = ["docker", "compose", "--profile", "serve"]
    proc = run([*serve, "build", "policy"], timeout=2400, env=env)
    assert proc.returncode == 0, output(proc)

    def replicas() -> list[str]:
        return run([*serve, "ps", "-q", "policy-worker"], timeout=60, env=env).stdout.split()

    def serving(container: str) -> bool:
        probe = (
            "import grpc; from grpc_health.v1 import health_pb2 as h, health_pb2_grpc as g; "
            "r = g.HealthStub(grpc.insecure_channel('127.0.0.1:7001')).Check(h.HealthCheckRequest(), timeout=5); "
            "raise SystemExit(r.status != h.HealthCheckResponse.SERVING)"
        )
        return run(["docker", "exec", container, "python", "-c", probe], timeout=60).returncode == 0

    try:
        proc = run([*serve, "up", "-d", "--scale", "policy-worker=1", "policy", "policy-worker"], timeout=600, env=env)
        assert proc.returncode == 0, output(proc)
        client = PolicyClient(f"127.0.0.1:{port}", connect_timeout_s=300)
        views = tuple(client.info.default_views)
        h, w = client.info.cameras[0].height, client.info.cameras[0].width
        image = np.zeros((h, w, 3), np.uint8)
        frames = {v: [(image, 1), (image, 2)] for v in views}
        states = [State(np.array([0.5, 0.0, 0.2]), np.array([1.0, 0, 0, 0]), 0.0, t) for t in (1, 2)]
        chunk = client.get_action(frames, states)
        assert chunk.actions.shape == (client.info.pred_horizon, 7) and chunk.views_used == views
        [first] = replicas()
        more = [*serve, "up", "-d", "--no-recreate", "--scale", "policy-worker=2", "policy-worker"]
        proc = run(more, timeout=600, env=env)
        assert proc.returncode == 0, output(proc)
        [second] = [c for c in replicas() if c != first]
        deadline = time.monotonic() + 120
        while not serving(second):
            assert time.monotonic() < deadline, "the second replica did not load its model in 2 minutes"
            time.sleep(1)
        assert run(["docker", "kill", first], timeout=60).returncode == 0
        killed, refused, answered = time.monotonic(), [], []
        while len(answered) < 10:
            try:
                answered.append(client.get_action(frames, states))
            except PolicyError as exc:
                assert not answered, f"refused after answering again: {exc}"
                refused.append(str(exc))
                assert time.monotonic() - killed < 5, f"still refused 5 s after the kill: {refused[-1]}"
        assert all(a.views_used == views for a in answered)
        print(f"{len(refused)} refused before the server answered again", flush=True)
    finally:
        print(output(run([*serve, "logs", "policy"], timeout=60, env=env), 30))
        run([*serve, "down", "--remove-orphans"], timeout=120, env=env)
