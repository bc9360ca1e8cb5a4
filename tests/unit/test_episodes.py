"""Alignment at control ticks and diffusion_policy-style chunking, on in-memory episodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.dataset.episodes import EpisodeError, RawEpisode, align, default_max_frame_age_ns, segments
from services.dataset.pseudo_demos import chunk_rows, chunk_starts, longest_segment, pad_hold, shortest_chunked

PERIOD = 50_000_000  # 20 Hz
T0 = 1_700_000_000_000_000_000


def raw(n=10, frames=None, action_ticks=None, stale=(), state_ticks=None) -> RawEpisode:
    ticks = np.arange(n) if state_ticks is None else np.asarray(state_ticks)
    a_ticks = np.arange(n) if action_ticks is None else np.asarray(action_ticks)
    act = np.zeros((len(a_ticks), 7))
    act[:, 0] = a_ticks  # dp_x = tick, so a test can see which action landed where
    frames = frames if frames is not None else {"F": T0 + np.arange(n) * PERIOD}
    return RawEpisode(
        path=Path("ep.mcap"),
        episode_id="ep",
        meta={},
        state_tick=ticks.astype(np.int64),
        state_ns=(T0 + ticks * PERIOD).astype(np.int64),
        eef_pos=np.c_[ticks, np.zeros((len(ticks), 2))].astype(float),
        eef_quat_wxyz=np.tile([1.0, 0, 0, 0], (len(ticks), 1)),
        gripper=np.zeros(len(ticks)),
        action_tick=a_ticks.astype(np.int64),
        action=act,
        action_stale=np.isin(a_ticks, list(stale)),
        frame_ns={k: np.asarray(v, np.int64) for k, v in frames.items()},
        frame_data={k: [b""] * len(v) for k, v in frames.items()},
        control_hz=20.0,
    )


def test_sim_frames_share_the_tick_time_and_all_align():
    al = align(raw(), ["F"])
    np.testing.assert_array_equal(al.tick, np.arange(10))
    np.testing.assert_array_equal(al.frame_index["F"], np.arange(10))
    np.testing.assert_array_equal(al.action[:, 0], al.tick)  # the action of the same tick
    np.testing.assert_array_equal(al.eef_pos[:, 0], al.tick)
    assert al.drops["views"]["F"] == {"missing_frame": 0, "stale_frame": 0}


def test_frame_is_the_newest_at_or_before_the_tick_never_after():
    # Real-rig style: frames 3 ms before each tick, plus one 1 ms after tick 4's state.
    f = T0 + np.arange(10) * PERIOD - 3_000_000
    f[4] = T0 + 4 * PERIOD + 1_000_000
    al = align(raw(frames={"F": f}), ["F"], max_frame_age_ns=10_000_000)
    idx = al.frame_index["F"]
    assert idx[3] == 3 and idx[5] == 5
    # Tick 4's own frame came after the state; the one before it is 53 ms old: stale, dropped.
    assert idx[4] == -1
    assert al.drops["views"]["F"]["stale_frame"] == 1
    # With a larger tolerance tick 4 takes frame 3 (the newest at or before), never frame 4.
    al2 = align(raw(frames={"F": f}), ["F"], max_frame_age_ns=60_000_000)
    assert al2.frame_index["F"][4] == 3


def test_missing_frames_and_actions_are_dropped_and_counted_not_filled():
    f = np.delete(T0 + np.arange(10) * PERIOD, [0, 6])  # no frame before tick 0; frame 6 lost
    ep = raw(frames={"F": f, "FL": T0 + np.arange(10) * PERIOD}, action_ticks=[0, 1, 2, 3, 4, 5, 6, 7, 8])
    al = align(ep, ["F", "FL"])
    assert al.drops["no_action"] == 1  # tick 9 has no applied action: gone for every view
    assert list(al.tick) == list(range(9))
    assert al.drops["views"]["F"] == {"missing_frame": 1, "stale_frame": 1}
    assert al.drops["views"]["FL"] == {"missing_frame": 0, "stale_frame": 0}
    np.testing.assert_array_equal(al.valid("F"), [t not in (0, 6) for t in range(9)])
    assert al.valid("FL").all()
    # The valid ticks of F make two runs: 1..5 and 7..8.
    np.testing.assert_array_equal(segments(al.tick[al.valid("F")]), [5, 7])


def test_stale_actions_are_counted_and_kept_unless_asked():
    al = align(raw(stale=[3, 4]), ["F"])
    assert al.drops["stale_action"] == 2 and len(al.tick) == 10
    al = align(raw(stale=[3, 4]), ["F"], drop_stale_actions=True)
    assert list(al.tick) == [0, 1, 2, 5, 6, 7, 8, 9]


def test_duplicate_states_and_orphan_actions_are_counted():
    al = align(raw(n=5, state_ticks=[0, 1, 1, 2, 3, 4], action_ticks=[0, 1, 2, 3, 4, 5, 6]), ["F"])
    assert al.drops["duplicate_state"] == 1
    assert al.drops["action_without_state"] == 2
    assert list(al.tick) == [0, 1, 2, 3, 4]


def test_unknown_view_names_the_file_and_the_cameras():
    with pytest.raises(EpisodeError, match=r"ep\.mcap.*'FX'.*F"):
        align(raw(), ["FX"])


def test_default_tolerance_in_sim_is_half_a_period():
    al = align(raw(), ["F"])
    assert al.frame_tolerance_ns["F"] == PERIOD // 2
    assert default_max_frame_age_ns(20.0) == PERIOD // 2
    assert default_max_frame_age_ns(None) == 50_000_000


def test_a_free_running_camera_is_fresh_up_to_a_frame_old_and_stale_after_a_lost_frame():
    """A real camera at 20 fps on its own clock: its newest frame is 0..50 ms old at a tick."""
    rng = np.random.default_rng(0)
    n = 200
    f = T0 - 31_000_000 + np.arange(n) * PERIOD + rng.integers(-2_000_000, 2_000_000, n)
    al = align(raw(n=n, frames={"F": f}), ["F"])
    assert al.drops["views"]["F"] == {"missing_frame": 0, "stale_frame": 0}
    np.testing.assert_array_equal(al.frame_index["F"], np.arange(n))
    lost = np.delete(f, 120)  # the frame before tick 120 never arrived
    al = align(raw(n=n, frames={"F": lost}), ["F"])
    assert al.drops["views"]["F"] == {"missing_frame": 0, "stale_frame": 1}
    assert al.frame_index["F"][120] == -1 and al.frame_index["F"][121] == 120


def test_frames_a_little_after_the_tick_give_the_previous_frame_consistently():
    f = T0 + np.arange(10) * PERIOD + 3_000_000
    al = align(raw(frames={"F": f}), ["F"])
    assert al.frame_index["F"][0] == -1 and al.drops["views"]["F"]["missing_frame"] == 1
    np.testing.assert_array_equal(al.frame_index["F"][1:], np.arange(9))  # tick k: frame k-1, never k
    assert al.drops["views"]["F"]["stale_frame"] == 0


def test_chunks_match_diffusion_policy_sampler():
    """diffusion_policy create_indices with pad_before=To-1, pad_after=Ta-1, written out by hand."""
    To, Tp, Ta = 2, 16, 8
    L = 20
    starts = chunk_starts(np.array([L]), To, Tp, Ta)
    # sequence starts idx in [-1, L - Tp + Ta - 1] = [-1, 11]  -> 13 samples, current = idx + 1
    np.testing.assert_array_equal(starts[:, 0], np.arange(0, 13))
    rows, inside = chunk_rows(0, 0, L, To, Tp)
    np.testing.assert_array_equal(rows, [0] + list(range(0, 15)))  # first row repeated (edge pad)
    assert not inside[0] and inside[1:].all()
    rows, inside = chunk_rows(12, 0, L, To, Tp)
    np.testing.assert_array_equal(rows, list(range(11, 20)) + [19] * 7)
    # the Ta actions executed from the current step are all real
    assert inside[To - 1 : To - 1 + Ta].all()
    # segments are sampled separately and never mix
    two = chunk_starts(np.array([L, L + 12]), To, Tp, Ta)
    assert len(two) == 13 + (12 - Tp + Ta + To - 1)
    assert (two[13:, 1] == L).all() and (two[13:, 2] == L + 12).all()
    # a segment too short for one chunk gives none
    assert len(chunk_starts(np.array([7]), To, Tp, Ta)) == 0
    with pytest.raises(ValueError):
        chunk_starts(np.array([L]), 3, 2, 1)


@pytest.mark.parametrize("To, Tp, Ta", [(2, 16, 8), (1, 4, 4), (3, 10, 1), (2, 500, 8)])
def test_the_shortest_segment_named_in_errors_is_the_one_that_gives_a_chunk(To, Tp, Ta):
    n = shortest_chunked(To, Tp, Ta)
    assert len(chunk_starts(np.array([n]), To, Tp, Ta)) == 1
    assert len(chunk_starts(np.array([n - 1]), To, Tp, Ta)) == 0
    assert longest_segment(np.array([1, 1 + n, 2 + n])) == n and longest_segment(np.array([], np.int64)) == 0


def test_hold_padding_zeroes_motion_and_keeps_the_gripper():
    a = np.arange(4 * 7, dtype=float).reshape(4, 7)
    out = pad_hold(a, np.array([False, True, True, False]))
    np.testing.assert_array_equal(out[[0, 3], :6], 0.0)
    np.testing.assert_array_equal(out[:, 6], a[:, 6])
    np.testing.assert_array_equal(out[1:3], a[1:3])
