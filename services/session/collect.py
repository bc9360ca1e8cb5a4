"""``viewscale collect``: a whole sim collection session on this machine, one process per service.

Starts a Zenoh router on a free loopback port, then the sim, teleop and recorder services as
subprocesses connected to it (exactly what `docker compose up` runs, minus the containers),
waits for each one's ``ready`` line, runs the session in this process with progress per episode,
and stops everything with SIGTERM when the episodes are recorded. Service logs go to
``<out>/logs/<service>.log``. With ``auth`` (``viewscale collect --auth``) the router enforces
deploy/zenoh/router-acl.json5 and each service authenticates as its own user, with credentials made
for this session in a temporary folder and deleted after it.
"""

from __future__ import annotations

import os
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from services.core.bus import Bus, BusConfig, free_tcp_port, router
from services.core.config import ConfigError, load_config
from services.core.runtime import RECORDINGS, child_env, refuse_other_output, writable_dir
from services.recorder.config import RecorderConfig
from services.recorder.reader import EpisodeReadError, read_episode
from services.router.credentials import USERS_FILE, password_path, write_credentials
from services.session.config import EVAL_SEED_FLOOR, SessionConfig
from services.session.session import Session, SessionError, SessionResult, summary
from services.teleop.config import TeleopConfig
from sim.config import SimConfig

MODULES = {"recorder": "services.recorder", "sim": "sim", "teleop": "services.teleop"}  # service -> module
SERVICE_CONFIGS = {"recorder": RecorderConfig, "sim": SimConfig, "teleop": TeleopConfig}
ACL_FILE = Path(__file__).resolve().parents[2] / "deploy" / "zenoh" / "router-acl.json5"  # in a source tree


class CollectError(RuntimeError):
    pass


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log_path: Path

    def tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


@dataclass
class LocalStack:
    """Service subprocesses on loopback around one router; a context manager."""

    out_dir: Path
    config: str | None
    overrides: dict[str, list[str]] = field(default_factory=dict)  # service -> --set items
    ready_timeout_s: float = 120.0
    auth: bool = False  # the router enforces ACL_FILE; every service, and the session, its own user
    children: list[Child] = field(default_factory=list)

    def __post_init__(self):
        self.port = free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.log_dir = self.out_dir / "logs"
        self._secrets: tempfile.TemporaryDirectory | None = None

    def _credentials(self, user: str) -> dict[str, object]:
        if self._secrets is None:
            return {}
        return {"user": user, "password_file": password_path(Path(self._secrets.name), user)}

    def bus_config(self) -> BusConfig:
        """How the session in this process joins (as user ``session`` when ``auth``)."""
        return BusConfig(mode="client", connect=[self.endpoint], **self._credentials("session"))

    def check(self) -> None:
        """Every service's config as it will start, loaded here first: a wrong --set is one error, not a
        service that dies at start-up (raises ConfigError)."""
        for name, model in SERVICE_CONFIGS.items():
            load_config(model, self.config, ["bus.mode=client", *self.overrides.get(name, [])], section=name)
        unknown = sorted(set(self.overrides) - set(MODULES))
        if unknown:
            raise ConfigError(
                f"--set {unknown[0]}.*: no service {unknown[0]!r} in this session (services: {', '.join(MODULES)})"
            )

    def __enter__(self) -> LocalStack:
        self.check()
        self.log_dir.mkdir(parents=True, exist_ok=True)
        if self.auth:
            self._secrets = tempfile.TemporaryDirectory(prefix="viewscale-credentials-")
            secrets = Path(self._secrets.name)
            write_credentials(secrets)
            self._router = router([self.endpoint], acl_file=ACL_FILE, users_file=secrets / USERS_FILE)
        else:
            self._router = router([self.endpoint])
        try:
            self._wait_ready([self._start(name) for name in MODULES])
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start(self, name: str) -> Child:
        cmd = [sys.executable, "-m", MODULES[name]]
        if self.config:
            cmd += ["--config", self.config]
        creds = [f"bus.{k}={v}" for k, v in self._credentials(name).items()]
        for item in ["bus.mode=client", f"bus.connect=[{self.endpoint}]", *creds, *self.overrides.get(name, [])]:
            cmd += ["--set", item]
        log_path = self.log_dir / f"{name}.log"
        env = child_env(dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), PYTHONUNBUFFERED="1"))
        with open(log_path, "a") as log_file:  # append: a restarted service keeps its history
            log_file.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(cmd)}\n")
            log_file.flush()
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log_file, env=env, text=True)
        child = Child(name, proc, log_path)
        self.children.append(child)
        return child

    def restart(self, name: str) -> None:
        """Kill (SIGKILL) a service and start it again; returns once it is ready."""
        old = next(c for c in self.children if c.name == name)
        old.proc.kill()
        old.proc.wait()
        old.proc.stdout.close()
        self.children.remove(old)
        self._wait_ready([self._start(name)])

    def _wait_ready(self, children: list[Child]) -> None:
        pending = {c.proc.stdout.fileno(): c for c in children}
        sel = selectors.DefaultSelector()
        for child in children:
            sel.register(child.proc.stdout, selectors.EVENT_READ, child)
        deadline = time.monotonic() + self.ready_timeout_s
        while pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                names = ", ".join(c.name for c in pending.values())
                raise CollectError(f"not ready after {self.ready_timeout_s:.0f}s: {names}")
            for key, _ in sel.select(timeout=min(remaining, 1.0)):
                child: Child = key.data
                line = child.proc.stdout.readline()
                if not line:  # EOF: the process died before it was ready
                    child.proc.wait(timeout=5)
                    raise CollectError(
                        f"{child.name} exited with code {child.proc.returncode} before it was "
                        f"ready; last log lines:\n{child.tail()}"
                    )
                if line.startswith(f"ready {child.name}"):
                    sel.unregister(child.proc.stdout)
                    pending.pop(child.proc.stdout.fileno(), None)
        sel.close()

    def check_alive(self, grace_s: float = 0.0) -> None:
        """CollectError naming a child that exited, with its last log lines. ``grace_s``: how long to
        wait for one to exit, after an error that a dying child causes before it is gone (its
        queryable is, while the process still closes its bus: the session's query fails first)."""
        deadline = time.monotonic() + grace_s
        while True:
            for child in self.children:
                if child.proc.poll() is not None:
                    raise CollectError(
                        f"{child.name} exited with code {child.proc.returncode}; last log lines:\n{child.tail()}"
                    )
            if time.monotonic() >= deadline:
                return
            time.sleep(0.05)

    def __exit__(self, *exc) -> None:
        for child in self.children:
            if child.proc.poll() is None:
                child.proc.send_signal(signal.SIGTERM)
        for child in self.children:
            try:
                child.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait()
            if child.proc.stdout:
                child.proc.stdout.close()
        self.children.clear()
        if getattr(self, "_router", None) is not None:
            self._router.close()
            self._router = None
        if self._secrets is not None:
            self._secrets.cleanup()
            self._secrets = None


def recorded_seeds(out: Path, task: str) -> list[int]:
    """The seeds of the ``task`` episodes a collection recorded in ``out`` (its metadata, not its
    name; re-renderings of them are left out, the same scenes through other cameras, and an
    evaluation's rollouts, whose seeds are the evaluation's)."""
    seeds = []
    for path in sorted(out.glob("*.mcap")) if out.is_dir() else []:
        try:
            md = read_episode(path, topics=()).metadata
        except EpisodeReadError:  # (a file the dataset build will name; not a seed of ours)
            continue
        if md.get("task") == task and md.get("seed") is not None and not md.get("rerendered_from"):
            if int(md["seed"]) < EVAL_SEED_FLOOR:  # (an evaluation's rollouts: not collection seeds)
                seeds.append(int(md["seed"]))
    return sorted(seeds)


def first_seed(out: Path, task: str, asked: int | None, progress=print) -> int:
    """Where a collection into ``out`` starts. A seed is a scene and the scripted expert is
    deterministic, so the seeds ``out`` holds already would record the same episodes again: with
    no seed asked for, it starts after them (0 in a new folder); a seed asked for is taken, and
    what it may repeat is said."""
    seeds = recorded_seeds(out, task)
    if asked is None:
        if not seeds:
            return 0
        progress(
            f"{out} holds {len(seeds)} {task} episodes (seeds {seeds[0]}..{seeds[-1]}): "
            f"continuing from seed {seeds[-1] + 1}"
        )
        return seeds[-1] + 1
    if seeds and asked <= seeds[-1]:
        progress(
            f"note: {out} holds {task} episodes of seeds {seeds[0]}..{seeds[-1]}: from --seed {asked}, the seeds "
            "recorded there record the same scenes again (leave --seed out to continue after them)"
        )
    return asked


def collect(
    task: str,
    episodes: int,
    rig: str,
    out: Path,
    config: str | None = None,
    seed: int = 0,
    size: int | None = None,
    realtime: bool = True,
    control_hz: float = 20.0,
    max_ticks: int | None = None,
    extra: dict[str, list[str]] | None = None,
    progress=print,
    auth: bool = False,
) -> SessionResult:
    out = Path(out)
    sim = [f"rig={rig}", f"task={task}", f"realtime={str(realtime).lower()}", f"control_hz={control_hz}"]
    if size:
        sim += [f"width={size}", f"height={size}"]
    overrides = {"sim": sim, "recorder": [f"out_dir={out}"], "teleop": []}
    for name, items in (extra or {}).items():
        overrides.setdefault(name, []).extend(items)
    stack = LocalStack(out, config, overrides, auth=auth)
    stack.check()  # a wrong --set is one error before anything starts (and before --out is made)
    refuse_other_output(out, "--out", RECORDINGS)  # (episodes in among a dataset's or a run's files)
    writable_dir(out, "--out")
    progress(f"starting sim ({task}, rig {rig}), teleop (scripted) and recorder -> {out}")
    with stack:
        how = " (authenticated, access control on)" if auth else ""
        progress(f"services ready on {stack.endpoint}{how}; logs in {stack.log_dir}")
        cfg = SessionConfig(
            bus=stack.bus_config(),
            task=task,
            rig=rig,
            episodes=episodes,
            seed=seed,
            control_hz=control_hz,
            max_ticks=max_ticks,
        )
        with Bus(cfg.bus) as bus:
            try:
                result = Session(cfg, bus, progress=progress).run()
            except (SessionError, TimeoutError) as exc:
                stack.check_alive(grace_s=3.0)  # a crashed child explains more than the symptom
                raise CollectError(str(exc)) from exc
    progress(summary(result))
    return result
