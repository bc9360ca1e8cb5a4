"""The only module that imports zenoh: sessions, typed publish/subscribe, queries, liveliness.

Every service opens one ``Bus`` from a ``BusConfig`` and talks through it. Data we record is
published with congestion control BLOCK (zenoh's default DROP loses samples under bursts); the
recorder, not the transport, decides what to drop, and counts it.

Authentication is opt-in: with ``user`` and ``password_file`` a client authenticates to the router
with zenoh's user/password scheme; a router with ``users_file`` refuses every session whose user and
password are not in it, and with ``acl_file`` lets each user send and receive only what its rules
allow (deploy/zenoh/router-acl.json5; deploy/README.md). Without them nothing changes: loopback
sessions and tests run unauthenticated.
"""

from __future__ import annotations

import json
import logging
import re
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import zenoh
from google.protobuf.message import DecodeError, Message
from pydantic import Field, model_validator

from services.core.config import ConfigError, Frozen
from services.core.topics import Topic

log = logging.getLogger(__name__)


class BusConfig(Frozen):
    mode: Literal["peer", "client", "router"] = "peer"  # zenoh session mode
    listen: list[str] = Field(default_factory=list)  # endpoints to listen on, e.g. tcp/0.0.0.0:7447
    connect: list[str] = Field(default_factory=list)  # endpoints to connect to (a router or peer)
    multicast_scouting: bool = False  # off by default: sessions find each other only via `connect`
    namespace: str = "vs"  # prefix of every key expression, so sessions can share a network
    # keep retrying `connect` endpoints this long at start-up (router still booting); zenoh reads a
    # negative timeout as "forever", so it must be a positive number
    connect_timeout_s: float = Field(30.0, gt=0, allow_inf_nan=False)
    user: str | None = None  # authenticate to the router as this user (zenoh user/password); None: no authentication
    password_file: Path | None = None  # file whose first line is `user`'s password (a compose secret); never logged
    acl_file: Path | None = None  # router only: zenoh JSON5 with the `access_control` it enforces, per user
    users_file: Path | None = None  # router only: `user:password` lines it accepts; everyone else is refused

    @model_validator(mode="after")
    def _check_auth(self) -> BusConfig:
        if (self.user is None) != (self.password_file is None):
            raise ValueError("bus.user and bus.password_file go together (a user authenticates with its password)")
        if self.user is not None:
            if not self.user or ":" in self.user or self.user != self.user.strip():
                raise ValueError(f"bus.user {self.user!r} must be a non-empty name without ':' or spaces around it")
            if self.mode != "client":
                # A peer also accepts links from other peers, which would bypass the router's access control.
                raise ValueError(
                    f"bus.user needs bus.mode=client, not {self.mode!r}: "
                    "authenticated services talk only through the router"
                )
        if (self.acl_file is not None or self.users_file is not None) and self.mode != "router":
            raise ValueError("bus.acl_file and bus.users_file configure a router (bus.mode=router)")
        if self.acl_file is not None and self.users_file is None:
            raise ValueError("bus.acl_file needs bus.users_file: its rules name users that must authenticate")
        return self


def free_tcp_port() -> int:
    """A port the OS just handed out on loopback (for tests and local sessions)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def read_password(path: Path, user: str) -> str:
    """The first line of ``path``: ``user``'s password. A ConfigError names the file, never the password."""
    what = f"the password file of Zenoh user {user!r}"
    try:
        lines = Path(path).read_text().splitlines()
    except FileNotFoundError:
        raise ConfigError(f"{what}, {path}, does not exist (`viewscale credentials` writes one per service)") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what}, {path}: {exc.strerror}") from None
    password = lines[0].strip() if lines else ""
    if not password:
        raise ConfigError(f"{what}, {path}, is empty: its first line must be the password")
    return password


def read_users(path: Path) -> list[str]:
    """The user names of a router's ``user:password`` file, checked line by line as zenoh reads it."""
    try:
        lines = Path(path).read_text().splitlines()
    except FileNotFoundError:
        raise ConfigError(
            f"the router's users file {path} does not exist (`viewscale credentials` writes it)"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read the router's users file {path}: {exc.strerror}") from None
    users = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ConfigError(f"{path}:{number}: expected user:password")
        users.append(user)
    if not users:
        raise ConfigError(f"the router's users file {path} names no user: every session would be refused")
    return users


def _router_base(cfg: BusConfig) -> zenoh.Config:
    """A router's config: its access control file (when given) with our settings over it."""
    if cfg.acl_file is None:
        return zenoh.Config()
    path = Path(cfg.acl_file)
    if not path.is_file():
        raise ConfigError(f"the router's access control file {path} does not exist")
    try:
        conf = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(f"the router's access control file {path} is not a valid zenoh config: {exc}") from None
    if json.loads(conf.get_json("access_control/enabled")) is not True:
        raise ConfigError(f"{path} does not enable access control (access_control.enabled: true)")
    return conf


def _zenoh_config(cfg: BusConfig) -> zenoh.Config:
    conf = _router_base(cfg) if cfg.mode == "router" else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    # A peer with no explicit listen endpoint would listen on every interface; stay local.
    listen = cfg.listen or (["tcp/127.0.0.1:0"] if cfg.mode == "peer" else [])
    for key, endpoints in (("listen", listen), ("connect", list(cfg.connect))):
        try:
            conf.insert_json5(f"{key}/endpoints", json.dumps(endpoints))
        except zenoh.ZError as exc:  # e.g. no protocol: "Endpoints must be of the form <protocol>/<address>..."
            raise ConfigError(
                f"bus.{key} {', '.join(endpoints)}: {zenoh_reason(exc)} (e.g. tcp/127.0.0.1:7447)"
            ) from None
    if cfg.connect:
        conf.insert_json5("connect/timeout_ms", json.dumps(int(cfg.connect_timeout_s * 1000)))
        conf.insert_json5("connect/retry", "{period_init_ms: 100, period_max_ms: 1000, period_increase_factor: 2}")
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    if cfg.user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(cfg.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(read_password(cfg.password_file, cfg.user)))
    if cfg.users_file is not None:
        read_users(cfg.users_file)  # zenoh's own error names neither the file nor the line
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(Path(cfg.users_file).resolve())))
    return conf


def _accepts_tcp(endpoints: list[str], timeout: float = 1.0) -> bool:
    """Whether any ``tcp/host:port`` endpoint accepts a TCP connection (a router that is there)."""
    for endpoint in endpoints:
        proto, _, address = endpoint.partition("/")
        if proto != "tcp":
            continue
        host, _, port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
            return True
        except (OSError, ValueError):
            continue
    return False


def zenoh_reason(exc: Exception) -> str:
    """A zenoh error's message without the Rust source location zenoh appends (`` at /root/.cargo/...rs:62.``)."""
    text = str(exc)
    text = re.sub(r"Json5Err\(Message \{ msg: \"(.*?)\", location: .*", r"\1", text, flags=re.S)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return text.strip().rstrip(".")


def _open_error(cfg: BusConfig, exc: Exception) -> ConnectionError:
    if not cfg.connect:  # it only listens (a router, a peer): what failed is its listening
        listen = ", ".join(cfg.listen) or "(default endpoints)"
        return ConnectionError(f"cannot open a Zenoh {cfg.mode} session listening on {listen}: {zenoh_reason(exc)}")
    where = ", ".join(cfg.connect)
    if cfg.mode == "client" and _accepts_tcp(cfg.connect):
        # The router is there and still no session: zenoh refuses a failed authentication silently.
        if cfg.user is not None:
            return ConnectionError(
                f"the Zenoh router at {where} refused user {cfg.user!r}: wrong password in "
                f"{cfg.password_file}, or the user is not in the router's users file"
            )
        return ConnectionError(
            f"the Zenoh router at {where} accepts connections but refused the session within "
            f"{cfg.connect_timeout_s:.0f}s: it may require a user and password (bus.user, bus.password_file)"
        )
    return ConnectionError(
        f"cannot open a Zenoh {cfg.mode} session to {where} "
        f"within {cfg.connect_timeout_s:.0f}s (is the router running?): {zenoh_reason(exc)}"
    )


@dataclass(frozen=True)
class Received:
    """One sample as it arrived: raw bytes plus where and when."""

    key: str
    payload: bytes
    receive_ns: int


class Publisher:
    def __init__(self, pub: zenoh.Publisher, topic: Topic):
        self._pub = pub
        self.topic = topic

    def put(self, msg: Message | bytes) -> None:
        self._pub.put(msg if isinstance(msg, bytes) else msg.SerializeToString())


def decode(topic: Topic, payload: bytes) -> Message:
    """Parse ``payload`` as ``topic``'s message type; raises ``DecodeError`` on garbage."""
    msg = topic.msg_type()
    msg.ParseFromString(payload)  # raises DecodeError on truncated / invalid wire data
    return msg


class Bus:
    """An open zenoh session with our namespace and message types applied."""

    def __init__(self, cfg: BusConfig):
        self.cfg = cfg
        conf = _zenoh_config(cfg)  # ConfigError on a missing or bad credential file
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise _open_error(cfg, exc) from exc
        self._keep: list[object] = []  # declared entities live as long as the bus
        self.callback_errors: Counter[str] = Counter()  # key -> handler failures (caught, logged, counted)

    # -- context management -------------------------------------------------------------
    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for entity in reversed(self._keep):
            try:
                entity.undeclare()  # type: ignore[attr-defined]
            except Exception:  # already gone when the session closes underneath
                pass
        self._keep.clear()
        if not self.session.is_closed():
            self.session.close()

    def key(self, rel: str) -> str:
        return f"{self.cfg.namespace}/{rel}"

    # -- pub/sub ------------------------------------------------------------------------
    def publisher(self, topic: Topic, block: bool = True) -> Publisher:
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self.session.declare_publisher(self.key(topic.key), congestion_control=cc)
        self._keep.append(pub)
        return Publisher(pub, topic)

    def subscribe_raw(self, key: str, callback: Callable[[Received], None]) -> None:
        """Call ``callback`` for every sample on ``key`` (relative, wildcards allowed).

        The callback runs on a zenoh thread: keep it short (enqueue, don't process).
        """
        prefix = len(self.cfg.namespace) + 1

        def on_sample(sample: zenoh.Sample) -> None:
            rx = Received(str(sample.key_expr)[prefix:], sample.payload.to_bytes(), time.time_ns())
            try:
                callback(rx)
            except Exception:  # a bad handler must not kill zenoh's thread
                self.callback_errors[rx.key] += 1
                log.exception("subscriber callback failed on %s (%d so far)", rx.key, self.callback_errors[rx.key])

        self._keep.append(self.session.declare_subscriber(self.key(key), on_sample))

    def subscribe(
        self,
        topic: Topic,
        callback: Callable[[Message, Received], None],
        on_error: Callable[[Received, Exception], None] | None = None,
    ) -> None:
        """Decoded subscription; malformed payloads go to ``on_error`` (default: log)."""

        def handle(rx: Received) -> None:
            try:
                msg = decode(topic, rx.payload)
            except DecodeError as exc:
                if on_error is None:
                    log.warning("malformed payload on %s (%d bytes): %s", rx.key, len(rx.payload), exc)
                else:
                    on_error(rx, exc)
                return
            callback(msg, rx)

        self.subscribe_raw(topic.key, handle)

    # -- queries ------------------------------------------------------------------------
    def queryable(self, key: str, handler: Callable[[bytes], bytes]) -> None:
        """Answer queries on ``key`` with ``handler(request_bytes) -> reply_bytes``."""
        full = self.key(key)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                try:
                    reply = handler(payload)
                except Exception as exc:
                    log.exception("queryable %s failed", key)
                    query.reply_err(f"{type(exc).__name__}: {exc}".encode())
                    return
                query.reply(full, reply)
            finally:
                # The query completes when it is dropped: not when the last reference goes, which a
                # log record holding a traceback can delay until the caller's timeout.
                query.drop()

        self._keep.append(self.session.declare_queryable(full, on_query))

    def query(self, key: str, payload: bytes, timeout: float = 5.0) -> bytes:
        """One request/reply; raises ``TimeoutError`` if nobody answers in ``timeout``."""
        t0 = time.monotonic()
        for reply in self.session.get(self.key(key), payload=payload, timeout=timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            error = reply.err.payload.to_bytes().decode(errors="replace")
            if error == "Timeout":  # zenoh's own: the service is there but did not answer in time
                # (before: a RuntimeError, which the sessions did not expect: a traceback)
                raise TimeoutError(f"no reply on {self.key(key)} within {timeout:.1f}s (the service is busy or stuck)")
            raise RuntimeError(f"query {key} failed: {error}")
        if time.monotonic() - t0 < 0.9 * timeout:  # (before: 'within 20.0s' for an answer in 0.01 s)
            raise TimeoutError(f"no reply on {self.key(key)}: nothing answers it (is the service running?)")
        raise TimeoutError(f"no reply on {self.key(key)} within {timeout:.1f}s (is the service running?)")

    # -- liveliness ---------------------------------------------------------------------
    def announce(self, service: str) -> None:
        """Declare a liveliness token ``<ns>/alive/<service>`` held until close."""
        self._keep.append(self.session.liveliness().declare_token(self.key(f"alive/{service}")))

    def presence(self, name: str):
        """A liveliness token ``<ns>/alive/<name>`` the caller withdraws (``.undeclare()``) when
        the thing it stands for goes away (a camera that stops delivering), unlike ``announce``."""
        return self.session.liveliness().declare_token(self.key(f"alive/{name}"))

    def alive(self, timeout: float = 1.0) -> set[str]:
        prefix = self.key("alive/")
        names = set()
        for reply in self.session.liveliness().get(prefix + "**", timeout=timeout):
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr)[len(prefix) :])
        return names

    def wait_alive(self, services: set[str] | list[str], timeout: float = 30.0) -> None:
        """Block until every named service holds its liveliness token, or raise TimeoutError."""
        want = set(services)
        deadline = time.monotonic() + timeout
        while True:
            have = self.alive(timeout=0.5)
            if want <= have:
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"services not alive after {timeout:.0f}s: {sorted(want - have)}")
            time.sleep(0.05)

    def watch_alive(self, callback: Callable[[str, bool], None]) -> None:
        """``callback(service, alive)`` whenever a service appears or disappears."""
        prefix = self.key("alive/")

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr)[len(prefix) :], sample.kind == zenoh.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(prefix + "**", on_sample, history=True)
        self._keep.append(sub)


def router(listen: list[str], acl_file: Path | None = None, users_file: Path | None = None) -> Bus:
    """A zenoh router session (what `viewscale router` and local sessions run as the hub); with
    ``users_file`` it refuses unauthenticated sessions, with ``acl_file`` it enforces those rules."""
    return Bus(BusConfig(mode="router", listen=listen, acl_file=acl_file, users_file=users_file))


__all__ = [
    "Bus",
    "BusConfig",
    "Publisher",
    "Received",
    "decode",
    "free_tcp_port",
    "read_password",
    "read_users",
    "router",
    "DecodeError",
]
