"""Grippers an arm driver commands: a closure in [0, 1] (0 open, 1 closed), chosen by config.

An arm driver that has a gripper on its flange takes a ``gripper`` config entry (``type: none``,
``type: robotiq`` or a lab's own ``type: mylab.grippers:MyGripper``; ``services.robot.config``)
and builds it through ``GRIPPERS``. A gripper raises ``OSError`` when it cannot be reached; the
arm driver reports that as a fault (the arm stops, the episode is flagged) and calls
``reconnect`` while it recovers.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from abc import ABC, abstractmethod
from typing import Any

log = logging.getLogger(__name__)


class Gripper(ABC):
    """A parallel gripper driven by a target closure in [0, 1] (0 open, 1 closed)."""

    @classmethod
    def from_config(cls, cfg: Any, *, arm_host: str) -> Gripper:
        """Build from the gripper's typed config; ``arm_host`` is the arm controller's address."""
        return cls(cfg)  # type: ignore[call-arg]

    @abstractmethod
    def move(self, closure: float) -> None:
        """Start moving to ``closure``; returns without waiting for the fingers."""

    @abstractmethod
    def position(self) -> float:
        """The fingers' closure now, in [0, 1]."""

    def reconnect(self) -> None:
        """After a communication error: connect again (raises OSError if it still cannot)."""

    def close(self) -> None:
        """Release the connection (default: nothing to release)."""


class NullGripper(Gripper):
    """No gripper (or one driven by something else): the commanded closure is reported back."""

    def __init__(self, cfg: Any = None):
        self._closure = 0.0

    def move(self, closure: float) -> None:
        self._closure = float(closure)

    def position(self) -> float:
        return self._closure


class RobotiqGripper(Gripper):
    """A Robotiq 2F-85 / 2F-140 / Hand-E through the Robotiq URCap's socket on the UR controller.

    The URCap serves a line protocol on TCP port 63352: a request is one ASCII line, ``SET <VAR>
    <value> [<VAR> <value> ...]\\n`` answered ``ack``, or ``GET <VAR>\\n`` answered ``<VAR> <value>``.
    Variables used here: ``ACT`` (1 activates), ``STA`` (3 once activated), ``GTO`` (1: go to the
    requested position), ``POS`` (0 open .. 255 closed), ``SPE`` and ``FOR`` (speed and force,
    0 .. 255). A closure c maps to ``POS round(255 c)``, the gripper's raw range. A move to the
    position last sent on this connection sends nothing: each request is a round trip in the robot's
    control tick, and a policy's closure often moves by less than the gripper's step (1/255) from
    one tick to the next.
    """

    def __init__(self, cfg: Any, host: str):
        self.cfg = cfg
        self.host = host
        self._lock = threading.Lock()  # one request at a time (the control loop and a recovery thread)
        self._sock: socket.socket | None = None
        self._buf = b""
        self._sent_pos: int | None = None  # POS last sent on this connection
        self.connect()

    @classmethod
    def from_config(cls, cfg: Any, *, arm_host: str) -> RobotiqGripper:
        try:
            return cls(cfg, cfg.host or arm_host)
        except OSError as exc:
            raise ConnectionError(
                f"cannot reach the Robotiq gripper at {cfg.host or arm_host}:{cfg.port}: {exc} "
                "(is the Robotiq URCap installed and the gripper plugged in?)"
            ) from exc

    # -- the protocol -------------------------------------------------------------------
    def _request(self, line: str) -> str:
        with self._lock:
            if self._sock is None:
                raise OSError("not connected")
            try:
                self._sock.sendall(line.encode("ascii") + b"\n")
                while b"\n" not in self._buf:
                    chunk = self._sock.recv(1024)
                    if not chunk:
                        raise OSError("the gripper socket closed")
                    self._buf += chunk
            except OSError:
                self._drop()
                raise
            reply, _, self._buf = self._buf.partition(b"\n")
            return reply.decode("ascii", "replace").strip()

    def _set(self, **values: int) -> None:
        line = "SET " + " ".join(f"{k} {int(v)}" for k, v in values.items())
        reply = self._request(line)
        if reply != "ack":
            raise OSError(f"{line!r} answered {reply!r}, not 'ack'")

    def _get(self, var: str) -> int:
        reply = self._request(f"GET {var}")
        name, _, value = reply.partition(" ")
        if name != var or not value.strip().lstrip("-").isdigit():
            raise OSError(f"'GET {var}' answered {reply!r}")
        return int(value)

    # -- Gripper ------------------------------------------------------------------------
    def connect(self) -> None:
        sock = socket.create_connection((self.host, self.cfg.port), timeout=self.cfg.timeout_s)
        sock.settimeout(self.cfg.timeout_s)
        with self._lock:
            self._drop()
            self._sock, self._buf = sock, b""
        if self._get("STA") != 3:
            if not self.cfg.activate:
                raise OSError("the gripper is not activated (activate it on the pendant, or set activate: true)")
            log.info("activating the Robotiq gripper at %s (the fingers open and close once)", self.host)
            self._set(ACT=1)
            deadline = time.monotonic() + self.cfg.activation_timeout_s
            while self._get("STA") != 3:
                if time.monotonic() > deadline:
                    raise OSError(f"the gripper did not activate within {self.cfg.activation_timeout_s:g} s")
                time.sleep(0.05)
        self._set(GTO=1, SPE=self.cfg.speed, FOR=self.cfg.force)

    def move(self, closure: float) -> None:
        pos = round(255 * min(max(float(closure), 0.0), 1.0))
        if pos == self._sent_pos and self._sock is not None:
            return
        self._set(POS=pos, SPE=self.cfg.speed, FOR=self.cfg.force, GTO=1)
        self._sent_pos = pos

    def position(self) -> float:
        return min(max(self._get("POS") / 255.0, 0.0), 1.0)

    def reconnect(self) -> None:
        self.connect()

    def _drop(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock = None
        self._sent_pos = None  # a new connection sends its first position, whatever it is

    def close(self) -> None:
        with self._lock:
            self._drop()
