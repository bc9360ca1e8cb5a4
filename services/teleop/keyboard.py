"""The keyboard of a plain terminal as a teleop device (``driver: {type: keyboard}``): no X server,
works over SSH and on a Linux console.

    teleop:
      driver: {type: keyboard, task: pour, rig: five15}   # keys from stdin, which must be a terminal
      driver: {type: keyboard, tty: /dev/pts/3}           # or from another terminal

Keys (a letter and its capital do the same; base frame, z up)::

    w / s   +x / -x   (arrow up / down too)       u / o   roll  + / -  (about x)
    a / d   +y / -y   (arrow left / right too)    i / k   pitch + / -  (about y)
    r / f   +z / -z   (up / down)                 j / l   yaw   + / -  (about z)
    space   toggle the gripper (open <-> closed)
    - / =   slower / faster (the speed is divided / multiplied by ``speed_step``; ``+`` also faster)
    b       begin: start recording an episode
    y       stop the episode as a success         n   stop it as a failure (the file is kept)
    x       discard the episode (its file is deleted)
    h / ?   log this help

A held key moves the EEF at ``speed`` x ``max_dp`` m (``max_drot`` rad) per tick; keys held
together add up (a diagonal is no faster than one axis). A terminal sends no key-up: a key counts
as held while its bytes keep coming. The first repeat of a held key comes after the terminal's
key-repeat delay (typically 250-600 ms), so a key pressed once holds for ``deadman_ms``; once it
repeats (every 30-40 ms), it holds for ``repeat_ms`` after its last repeat. No key: the EEF holds
still (a zero delta).

The terminal is put in cbreak mode without echo (``termios``: ICANON and ECHO off, reads return
at once); Ctrl-C still interrupts. It is restored on ``close`` and, if the process exits without
closing, at interpreter exit. Episode keys drive the recorder through ``services.recorder.control``
(``services/teleop/device.py``), the same requests as ``viewscale episode``.
"""

from __future__ import annotations

import atexit
import logging
import os
import select
import sys
import termios
import threading
import time

import numpy as np

from services.core.config import ConfigError
from services.teleop.config import KeyboardTeleopConfig
from services.teleop.device import Clock, DeviceTeleop

log = logging.getLogger(__name__)

# key -> (axis, sign) of the translation and of the rotation (base frame)
TRANSLATE = {
    "w": (0, 1.0),
    "s": (0, -1.0),
    "a": (1, 1.0),
    "d": (1, -1.0),
    "r": (2, 1.0),
    "f": (2, -1.0),
    "up": (0, 1.0),
    "down": (0, -1.0),
    "left": (1, 1.0),
    "right": (1, -1.0),
}
ROTATE = {"u": (0, 1.0), "o": (0, -1.0), "i": (1, 1.0), "k": (1, -1.0), "j": (2, 1.0), "l": (2, -1.0)}
EPISODE_KEYS = {"b": "start", "y": "stop_success", "n": "stop_failure", "x": "discard"}
GRIPPER_KEY = " "
SLOWER, FASTER = ("-",), ("=", "+")
HELP = (
    "keyboard teleop: w/s a/d r/f move x/y/z, u/o i/k j/l rotate about x/y/z, space gripper, "
    "-/= speed, b start, y stop (success), n stop (failure), x discard, h help"
)
_ARROWS = {ord("A"): "up", ord("B"): "down", ord("C"): "right", ord("D"): "left"}
_ESC = 0x1B
MIN_SPEED = 0.05


def parse_keys(buf: bytes) -> tuple[list[str], bytes]:
    """Terminal bytes -> key names, plus the bytes of an escape sequence not complete yet.

    Printable ASCII gives the character (letters in lower case), the arrow keys' escape sequences
    (``ESC [ A`` .. ``ESC [ D``, or ``ESC O A`` in application mode) give up/down/right/left; other
    escape sequences, control bytes and non-ASCII bytes are skipped."""
    keys: list[str] = []
    i, n = 0, len(buf)
    while i < n:
        b = buf[i]
        if b == _ESC:
            if i + 1 == n:
                return keys, buf[i:]  # the rest of the sequence may come with the next read
            if buf[i + 1] not in (ord("["), ord("O")):
                i += 1  # ESC alone (or Alt+key): skip the ESC, read the key
                continue
            j = i + 2
            while j < n and not 0x40 <= buf[j] <= 0x7E:  # parameter bytes up to the final byte
                j += 1
            if j == n:
                return keys, buf[i:]
            if j == i + 2 and buf[j] in _ARROWS:
                keys.append(_ARROWS[buf[j]])
            i = j + 1
            continue
        if 0x20 <= b < 0x7F:
            keys.append(chr(b).lower())
        i += 1
    return keys, b""


class HeldKeys:
    """Which motion keys count as held at time ``t``, from the times their bytes arrived.

    A key seen once holds for ``deadman_s`` (the terminal's repeat delay comes first); a key whose
    previous arrival was within ``deadman_s`` is auto-repeating and holds for ``repeat_s`` after its
    last arrival, so letting go stops the arm within ``repeat_s``."""

    def __init__(self, deadman_s: float, repeat_s: float):
        self.deadman_s = deadman_s
        self.repeat_s = repeat_s
        self._last: dict[str, float] = {}
        self._repeating: dict[str, bool] = {}

    def press(self, key: str, t: float) -> None:
        prev = self._last.get(key)
        self._repeating[key] = prev is not None and t - prev <= self.deadman_s
        self._last[key] = t

    def held(self, t: float) -> list[str]:
        out = []
        for key, last in self._last.items():
            window = self.repeat_s if self._repeating[key] else self.deadman_s
            if 0 <= t - last <= window:
                out.append(key)
        return out

    def clear(self) -> None:
        self._last.clear()
        self._repeating.clear()


def deflection_of(keys: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Held keys -> (translation, rotation), each summed over its keys and scaled to norm <= 1."""
    vec = {"t": np.zeros(3), "r": np.zeros(3)}
    for key in keys:
        for table, name in ((TRANSLATE, "t"), (ROTATE, "r")):
            if key in table:
                axis, sign = table[key]
                vec[name][axis] += sign
    return tuple(v / max(1.0, float(np.linalg.norm(v))) for v in (vec["t"], vec["r"]))  # type: ignore[return-value]


def _open_tty(path: str | None) -> tuple[int, bool]:
    """(fd, whether we opened it) of the terminal to read; a ConfigError says why it cannot be used."""
    if path:
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        except OSError as exc:
            raise ConfigError(f"keyboard teleop: cannot open the terminal {path}: {exc.strerror or exc}") from None
        if not os.isatty(fd):
            os.close(fd)
            raise ConfigError(
                f"keyboard teleop: {path} is not a terminal (driver.tty must name a tty, e.g. /dev/pts/3)"
            )
        return fd, True
    try:
        fd = sys.stdin.fileno()
    except (AttributeError, ValueError, OSError):
        fd = -1
    if fd < 0 or not os.isatty(fd):
        raise ConfigError(
            "keyboard teleop needs a terminal: stdin is not one (run the teleop in a terminal, "
            "in compose with `stdin_open: true` and `tty: true`, or set driver.tty=/dev/pts/N)"
        )
    if _in_background(fd):  # (before: the terminal stopped it, SIGTTOU, with no word said)
        raise ConfigError(
            "keyboard teleop: it runs in the background of its terminal (started with &?), where the "
            "keys do not reach it: run it in the foreground, or set driver.tty=/dev/pts/N of another terminal"
        )
    return fd, False


def _in_background(fd: int) -> bool:
    """Whether ``fd`` is this process's controlling terminal and another process group has it:
    setting its mode would stop this process (SIGTTOU), and its keys go to the foreground group."""
    try:
        return os.tcgetpgrp(fd) != os.getpgrp()
    except OSError:  # not this process's controlling terminal: no job control applies
        return False


class KeyboardTeleop(DeviceTeleop):
    def __init__(self, cfg: KeyboardTeleopConfig, clock: Clock = time.monotonic):
        self._fd, self._own_fd = _open_tty(cfg.tty)
        try:
            self._saved = termios.tcgetattr(self._fd)
            mode = termios.tcgetattr(self._fd)
            mode[3] &= ~(termios.ICANON | termios.ECHO)  # lflag: key by key, no echo; ISIG stays (Ctrl-C)
            mode[6][termios.VMIN] = 0  # a read returns at once with what is there
            mode[6][termios.VTIME] = 0
            termios.tcsetattr(self._fd, termios.TCSANOW, mode)
        except termios.error as exc:
            if self._own_fd:
                os.close(self._fd)
            raise ConfigError(f"keyboard teleop: cannot set the terminal's mode: {exc}") from None
        atexit.register(self._restore)
        super().__init__(cfg, clock)
        self.keys = HeldKeys(cfg.deadman_ms / 1e3, cfg.repeat_ms / 1e3)
        self.keys_read = 0  # keys parsed so far (a progress counter for tests and logs)
        self._restored = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read_loop, name="teleop-keyboard", daemon=True)
        self._thread.start()
        log.info("%s (terminal %s)", HELP, cfg.tty or "stdin")

    # -- the reader thread --------------------------------------------------------------------
    def _read_loop(self) -> None:
        rest = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._fd], [], [], 0.05)
                data = os.read(self._fd, 256) if ready else None
            except OSError as exc:  # EIO: the terminal hung up (its window closed)
                log.warning("keyboard teleop: the terminal is gone (%s): holding still from now on", exc)
                return
            if data is None:
                continue
            if not data:  # readable but empty: hung up
                self._stop.wait(0.05)
                continue
            keys, rest = parse_keys(rest + data)
            now = self.clock()
            for key in keys:
                self._on_key(key, now)
            self.keys_read += len(keys)

    def _on_key(self, key: str, now: float) -> None:
        if key in TRANSLATE or key in ROTATE:
            with self._lock:
                self.keys.press(key, now)
        elif key == GRIPPER_KEY:
            self.toggle_gripper()
            log.info("gripper toggled")
        elif key in SLOWER or key in FASTER:
            step = self.cfg.speed_step if key in FASTER else 1.0 / self.cfg.speed_step
            self.speed = float(np.clip(self.speed * step, MIN_SPEED, 1.0))
            log.info(
                "speed %.2f (%.3f m, %.3f rad per tick)",
                self.speed,
                self.speed * self.cfg.max_dp,
                self.speed * self.cfg.max_drot,
            )
        elif key in EPISODE_KEYS:
            self.episodes.post(EPISODE_KEYS[key])
        elif key in ("h", "?"):
            log.info(HELP)

    # -- the driver ---------------------------------------------------------------------------
    def deflection(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return deflection_of(self.keys.held(now))

    def reset(self, task: str, episode_id: str = "") -> None:
        super().reset(task, episode_id)
        with self._lock:
            self.keys.clear()  # a key from before the episode does not move the arm in it

    def _restore(self) -> None:
        if getattr(self, "_restored", False):
            return
        self._restored = True
        try:
            termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)
        except termios.error as exc:  # the terminal is gone: nothing to restore
            log.debug("terminal not restored: %s", exc)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        self._restore()
        atexit.unregister(self._restore)
        if self._own_fd and self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        super().close()
