"""The only module that imports zenoh: sessions, typed publish/subscribe, queries, liveliness.

Every service opens one ``Bus`` from a ``BusConfig`` and talks through it. Data we record is
published with congestion control BLOCK (zenoh's default DROP loses samples under bursts); the
recorder, not the transport, decides what to drop, and counts it.
"""

from __future__ import annotations

import json
import logging
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import zenoh
from google.protobuf.message import DecodeError, Message
from pydantic import Field

from services.core.config import Frozen
from services.core.topics import Topic

log = logging.getLogger(__name__)


class BusConfig(Frozen):
    mode: Literal["peer", "client", "router"] = "peer"  # zenoh session mode
    listen: list[str] = Field(default_factory=list)  # endpoints to listen on, e.g. tcp/0.0.0.0:7447
    connect: list[str] = Field(default_factory=list)  # endpoints to connect to (a router or peer)
    multicast_scouting: bool = False  # off by default: sessions find each other only via `connect`
    namespace: str = "vs"  # prefix of every key expression, so sessions can share a network
    connect_timeout_s: float = 30.0  # keep retrying `connect` endpoints this long at start-up (router still booting)


def free_tcp_port() -> int:
    """A port the OS just handed out on loopback (for tests and local sessions)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _zenoh_config(cfg: BusConfig) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    # A peer with no explicit listen endpoint would listen on every interface; stay local.
    listen = cfg.listen or (["tcp/127.0.0.1:0"] if cfg.mode == "peer" else [])
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    if cfg.connect:
        conf.insert_json5("connect/timeout_ms", json.dumps(int(cfg.connect_timeout_s * 1000)))
        conf.insert_json5("connect/retry", "{period_init_ms: 100, period_max_ms: 1000, period_increase_factor: 2}")
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    return conf


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
        try:
            self.session = zenoh.open(_zenoh_config(cfg))
        except zenoh.ZError as exc:
            where = ", ".join(cfg.connect) or "(no endpoint)"
            raise ConnectionError(
                f"cannot open a Zenoh {cfg.mode} session to {where} "
                f"within {cfg.connect_timeout_s:.0f}s (is the router running?): {exc}"
            ) from exc
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
        for reply in self.session.get(self.key(key), payload=payload, timeout=timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            raise RuntimeError(f"query {key} failed: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise TimeoutError(f"no reply on {self.key(key)} within {timeout:.1f}s (is the service running?)")

    # -- liveliness ---------------------------------------------------------------------
    def announce(self, service: str) -> None:
        """Declare a liveliness token ``<ns>/alive/<service>`` held until close."""
        self._keep.append(self.session.liveliness().declare_token(self.key(f"alive/{service}")))

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


def router(listen: list[str]) -> Bus:
    """A zenoh router session (what `viewscale router` and local sessions run as the hub)."""
    return Bus(BusConfig(mode="router", listen=listen))


__all__ = ["Bus", "BusConfig", "Publisher", "Received", "decode", "free_tcp_port", "router", "DecodeError"]
