"""The pure parts of the teleop devices: key parsing, held keys, deadzone, button gestures, the
EEF delta mapping and caps, and their configs."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pydantic import ValidationError

from services.pb.episode_pb2 import EpisodeCommand
from services.recorder.control import COMMANDS, episode_request
from services.recorder.writer import check_episode_id
from services.teleop.config import TELEOP_DRIVERS, KeyboardTeleopConfig, SpaceMouseTeleopConfig, TeleopConfig
from services.teleop.device import eef_delta
from services.teleop.keyboard import HeldKeys, deflection_of, parse_keys
from services.teleop.spacemouse import ButtonGestures, apply_deadzone


def test_eef_delta_scales_and_caps_like_the_expert():
    d = eef_delta(np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 0.5, 0.02, 0.1, 1.0)
    np.testing.assert_allclose(d.dp, [0.01, 0, 0])
    np.testing.assert_allclose(d.drot, [0, 0, -0.05])
    assert d.gripper == 1.0
    # full deflection on every axis and out-of-range inputs: never more than the per-tick caps
    big = eef_delta(np.array([5.0, -5.0, 5.0]), np.array([3.0, 3.0, 3.0]), 1.0, 0.02, 0.1, 7.0)
    assert np.linalg.norm(big.dp) == pytest.approx(0.02)
    assert np.linalg.norm(big.drot) == pytest.approx(0.1)
    assert big.gripper == 1.0


def test_parse_keys_letters_arrows_and_split_escape_sequences():
    keys, rest = parse_keys(b"wA \x1b[Dx\x1b[1;5C\x01\xc3\xa9?")
    assert keys == ["w", "a", " ", "left", "x", "?"]  # ctrl+arrow, control and non-ASCII bytes skipped
    assert rest == b""
    keys, rest = parse_keys(b"d\x1b[")  # an arrow cut between two reads
    assert keys == ["d"] and rest == b"\x1b["
    keys, rest = parse_keys(rest + b"Bs")
    assert keys == ["down", "s"] and rest == b""
    assert parse_keys(b"\x1bw") == (["w"], b"")  # Alt+w / a lone ESC
    assert parse_keys(b"\x1bOA") == (["up"], b"")  # application cursor mode


def test_held_keys_deadman_and_repeat_windows():
    keys = HeldKeys(deadman_s=0.6, repeat_s=0.15)
    keys.press("w", 10.0)
    assert keys.held(10.5) == ["w"]  # waiting for the terminal's first repeat
    assert keys.held(10.61) == []  # no repeat: let go
    keys.press("w", 11.0)
    keys.press("w", 11.4)  # the first repeat, after the repeat delay
    keys.press("w", 11.44)
    assert keys.held(11.55) == ["w"]
    assert keys.held(11.6) == []  # repeats stopped for 160 ms: released
    keys.press("a", 12.0)
    assert keys.held(12.0) == ["a"]  # a fresh press holds for the deadman window again
    keys.clear()
    assert keys.held(12.0) == []


def test_held_keys_add_up_without_going_faster():
    t, r = deflection_of(["w", "a"])
    np.testing.assert_allclose(t, [1 / np.sqrt(2), 1 / np.sqrt(2), 0])
    assert not r.any()
    t, r = deflection_of(["w", "s", "j"])  # opposite keys cancel
    np.testing.assert_allclose(t, [0, 0, 0])
    np.testing.assert_allclose(r, [0, 0, 1])
    t, r = deflection_of(["up", "right", "f", "o"])
    np.testing.assert_allclose(t, np.array([1, -1, -1]) / np.sqrt(3))
    np.testing.assert_allclose(r, [-1, 0, 0])


def test_deadzone_is_zero_inside_and_continuous_at_its_edge():
    out = apply_deadzone(np.array([0.04, -0.05, 0.525, -1.0, 1.4, 0.0]), 0.05)
    np.testing.assert_allclose(out, [0, 0, 0.5, -1.0, 1.0, 0.0])


def test_button_gestures_click_long_press_and_both():
    g = ButtonGestures(long_press_s=1.0)
    assert g.update({"LEFT"}, 0.0) == []
    assert g.update(set(), 0.3) == [("click", frozenset({"LEFT"}))]
    assert g.update({"RIGHT"}, 1.0) == []
    assert g.update({"RIGHT"}, 1.9) == []
    assert g.update({"RIGHT"}, 2.0) == [("long", frozenset({"RIGHT"}))]
    assert g.update({"RIGHT"}, 3.5) == []  # fires once per press
    assert g.update(set(), 3.6) == []  # and no click when it goes up
    assert g.update({"LEFT", "RIGHT"}, 5.0) == []
    assert g.update({"LEFT", "RIGHT"}, 6.1) == [("long", frozenset({"LEFT", "RIGHT"}))]
    assert g.update(set(), 6.2) == []
    assert g.update({"LEFT"}, 7.0) == []
    assert g.update(set(), 8.5) == [("long", frozenset({"LEFT"}))]  # held long, sampled only at release


def test_device_configs_are_registered_and_checked():
    assert {"keyboard", "spacemouse"} <= set(TELEOP_DRIVERS.names)
    cfg = TeleopConfig.model_validate({"world": "real", "driver": {"type": "keyboard", "tty": "/dev/pts/9"}})
    assert isinstance(cfg.driver, KeyboardTeleopConfig) and cfg.driver.tty == "/dev/pts/9"
    cfg = TeleopConfig.model_validate({"world": "real", "driver": {"type": "spacemouse", "yaw_deg": 90}})
    assert isinstance(cfg.driver, SpaceMouseTeleopConfig) and cfg.driver.yaw_deg == 90
    with pytest.raises(ValidationError, match="repeat_ms"):
        KeyboardTeleopConfig(deadman_ms=100, repeat_ms=200)
    with pytest.raises(ValidationError):
        SpaceMouseTeleopConfig(buttons="LEFT")  # an unknown key is an error
    with pytest.raises(ValidationError):
        KeyboardTeleopConfig(max_dp=0.5)  # a per-tick step no arm should take


def test_episode_requests_are_the_cli_ones():
    req = episode_request("start", task="pour", rig="five15", control_hz=15.0)
    assert req.command == EpisodeCommand.EPISODE_COMMAND_START
    assert req.episode_id.startswith("pour-five15-") and req.control_hz == 15.0
    stop = episode_request("stop", success=True)
    assert stop.command == COMMANDS["stop"] and stop.success and stop.episode_id == ""
    with pytest.raises(ValueError, match="unknown episode action"):
        episode_request("pause")


def test_starts_a_key_press_apart_are_two_episodes():
    """Two starts within a second, a stop between them (before: one id per second, the second
    start refused as 'already exists')."""
    first = episode_request("start", task="pour", rig="five15").episode_id
    time.sleep(0.005)
    second = episode_request("start", task="pour", rig="five15").episode_id
    assert first != second
    check_episode_id(first)  # a valid file name
