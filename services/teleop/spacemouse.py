"""A 3Dconnexion SpaceMouse as a teleop device (``driver: {type: spacemouse}``), read through
``pyspacemouse`` (``pip install -e '.[hardware]'``; it needs the system's hidapi,
``apt install libhidapi-hidraw0``, and read access to ``/dev/hidraw*``, usually a udev rule).

    teleop:
      driver: {type: spacemouse, task: pour, rig: five15}                  # the first one found
      driver: {type: spacemouse, device: SpaceMouseCompact, yaw_deg: 90}   # a model, turned 90 degrees

The puck (pyspacemouse's right-handed Z-up convention, ``AxisConvention.HID_Z_UP``; turned
``yaw_deg`` about z into the base frame, 0: the puck's axes are the base's)::

    push right / away / lift   +x / +y / +z of the EEF, at speed x max_dp per tick at full deflection
    tilt and twist             rotation about x / y / z, at speed x max_drot per tick (``rotation: false``: off)

Buttons (by pyspacemouse's names; the two-button models call them LEFT and RIGHT)::

    gripper_button (LEFT)  click: toggle the gripper       long press (``long_press_s``): stop the episode as a failure
    episode_button (RIGHT) long press: start an episode when the recorder is idle, stop it as a success when recording
    both, long press       discard the episode being recorded (its file is deleted)

Each axis reads zero inside ``deadzone`` and is rescaled outside it, so the command rises from
zero at the deadzone's edge. Deadman: a displaced puck reports every ~8 ms (the SpaceNavigator's
rate, FreeSpacenav/spacenavd#108); with no report for ``deadman_ms`` (unplugged, stalled) the EEF
holds still.

HID reports are decoded by pyspacemouse (``SpaceMouseDevice.read``: report id 1 translation and,
on the six-axis-per-report models, rotation, as little-endian int16 pairs at the byte offsets of
its ``devices.toml``; id 2 rotation on the older models; id 3 the button bits), scaled by its
``axis_scale`` (350) to about [-1, 1]. This module adds no decoding of its own: it reads the
decoded state on a thread every ``poll_ms`` and turns it into deflections and button gestures.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import threading
import time
from typing import Any

import numpy as np

from services.core.config import ConfigError
from services.core.geometry import rot_z
from services.teleop.config import SpaceMouseTeleopConfig
from services.teleop.device import Clock, DeviceTeleop

log = logging.getLogger(__name__)

PIP_HINT = "pip install pyspacemouse (or pip install -e '.[hardware]')"
HIDAPI_HINT = "apt install libhidapi-hidraw0"
_MAX_REPORTS_PER_POLL = 256  # reports queued in the HID buffer are drained, up to this many per poll


def apply_deadzone(v: np.ndarray, deadzone: float) -> np.ndarray:
    """Per axis: 0 inside ``deadzone``, then linear from 0 at its edge to 1 at full deflection."""
    v = np.clip(np.asarray(v, dtype=np.float64), -1.0, 1.0)
    return np.sign(v) * np.clip((np.abs(v) - deadzone) / (1.0 - deadzone), 0.0, 1.0)


class ButtonGestures:
    """Clicks and long presses from the set of buttons down, sampled over time.

    ``update`` returns ``("click", {name})`` when a button goes up before ``long_press_s``, and
    ``("long", names)`` once when buttons have been held that long: ``names`` is every button
    down at that moment that has not fired yet (two held together: both). A button that fired a
    long press gives no click when it goes up."""

    def __init__(self, long_press_s: float):
        self.long_press_s = long_press_s
        self._down: dict[str, float] = {}  # button -> time it went down
        self._fired: set[str] = set()  # down buttons whose long press has fired

    def update(self, pressed: set[str], t: float) -> list[tuple[str, frozenset[str]]]:
        events: list[tuple[str, frozenset[str]]] = []
        for name in pressed - self._down.keys():
            self._down[name] = t
        for name in [n for n in self._down if n not in pressed]:
            start = self._down.pop(name)
            if name in self._fired:
                self._fired.discard(name)
            elif t - start < self.long_press_s:
                events.append(("click", frozenset({name})))
            else:  # held long but released between two samples
                events.append(("long", frozenset({name})))
        if any(n not in self._fired and t - s >= self.long_press_s for n, s in self._down.items()):
            group = frozenset(n for n in self._down if n not in self._fired)
            self._fired |= group
            events.append(("long", group))
        return events


def open_spacemouse(cfg: SpaceMouseTeleopConfig) -> Any:
    """Open the configured SpaceMouse with pyspacemouse; a ConfigError says what is missing."""
    try:
        import pyspacemouse
    except (ImportError, OSError) as exc:
        raise ConfigError(f"teleop driver spacemouse needs the pyspacemouse package ({exc}): {PIP_HINT}") from None
    convention = pyspacemouse.AxisConvention.HID_Z_UP
    which = cfg.path or cfg.device or "the first one found"
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):  # it prints "<name> found" where our ready line goes
            if cfg.path:
                device = pyspacemouse.open_by_path(cfg.path, axis_convention=convention)
            else:
                device = pyspacemouse.open(device=cfg.device, device_index=cfg.device_index, axis_convention=convention)
    except (RuntimeError, ValueError, OSError, AttributeError) as exc:  # AttributeError: no hidapi library
        raise ConfigError(
            f"cannot open a SpaceMouse ({which}): {str(exc).rstrip('.')}. Check that one is plugged in, that this "
            f"user may read /dev/hidraw* (a udev rule) and that the hidapi library is installed ({HIDAPI_HINT})"
        ) from None
    log.info("%s", printed.getvalue().strip() or f"SpaceMouse {device.name} open")
    return device


class SpaceMouseTeleop(DeviceTeleop):
    """``device``: an open ``pyspacemouse.SpaceMouseDevice`` (default: ``open_spacemouse(cfg)``)."""

    def __init__(self, cfg: SpaceMouseTeleopConfig, device: Any = None, clock: Clock = time.monotonic):
        self.device = device if device is not None else open_spacemouse(cfg)
        names = list(self.device.info.button_names)
        for field in ("gripper_button", "episode_button"):
            if getattr(cfg, field) not in names:
                self.device.close()
                raise ConfigError(
                    f"spacemouse {field} {getattr(cfg, field)!r}: the {self.device.info.name} has buttons "
                    f"{', '.join(names) or '(none)'}"
                )
        super().__init__(cfg, clock)
        self._button_index = {name: names.index(name) for name in (cfg.gripper_button, cfg.episode_button)}
        self._frame = rot_z(math.radians(cfg.yaw_deg))
        self.gestures = ButtonGestures(cfg.long_press_s)
        self.reports = 0  # reports decoded so far
        self._axes = np.zeros(6)  # x, y, z, roll, pitch, yaw of the newest report
        self._last_report: float | None = None  # clock time of the newest report
        self._pressed: set[str] = set()
        self._seen_t = -1.0  # pyspacemouse stamps the state at every decoded report
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read_loop, name="teleop-spacemouse", daemon=True)
        self._thread.start()

    # -- the reader thread --------------------------------------------------------------------
    def poll(self) -> int:
        """Decode every report waiting (pyspacemouse reads one per call); returns how many."""
        n = 0
        for _ in range(_MAX_REPORTS_PER_POLL):
            state = self.device.read()
            if state.t == self._seen_t:
                break
            self._seen_t = state.t
            now = self.clock()
            pressed = {name for name, i in self._button_index.items() if i < len(state.buttons) and state.buttons[i]}
            with self._lock:
                self._axes = np.array([state.x, state.y, state.z, state.roll, state.pitch, state.yaw], dtype=np.float64)
                self._last_report = now
                self._pressed = pressed
            self._on_gestures(self.gestures.update(pressed, now))
            n += 1
        self._on_gestures(self.gestures.update(self._pressed, self.clock()))  # a long press needs no report
        self.reports += n
        return n

    def _on_gestures(self, events: list[tuple[str, frozenset[str]]]) -> None:
        grip, episode = self.cfg.gripper_button, self.cfg.episode_button
        for kind, names in events:
            if kind == "click" and names == {grip}:
                self.toggle_gripper()
                log.info("gripper toggled")
            elif kind == "long" and names == {episode}:
                self.episodes.post("start_or_stop")
            elif kind == "long" and names == {grip}:
                self.episodes.post("stop_failure")
            elif kind == "long" and {grip, episode} <= names:
                self.episodes.post("discard")

    def _read_loop(self) -> None:
        poll_s = self.cfg.poll_ms / 1e3
        while not self._stop.wait(poll_s):
            try:
                self.poll()
            except Exception as exc:  # unplugged: the HID read fails from now on
                log.warning("SpaceMouse read failed (%s): holding still; restart the teleop once it is back", exc)
                return

    # -- the driver ---------------------------------------------------------------------------
    def deflection(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            axes, last = self._axes.copy(), self._last_report
        if last is None or now - last > self.cfg.deadman_ms / 1e3:
            return np.zeros(3), np.zeros(3)
        v = apply_deadzone(axes, self.cfg.deadzone)
        rotation = self._frame @ v[3:] if self.cfg.rotation else np.zeros(3)
        return self._frame @ v[:3], rotation

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        with contextlib.suppress(Exception):
            self.device.close()
        super().close()
