"""When an episode counts as a success: the task's condition held for settle_ticks ticks, then kept.

The sequences are the cube heights of two recorded evaluation rollouts (lift, seeds 100006 and
100000): in the first the cube was lifted for four ticks and slipped as the pause landed, which
the session used to record as a failure."""

from __future__ import annotations

from services.core.success import SuccessWatch


def feed(watch: SuccessWatch, flags: list[bool]) -> list[bool]:
    out = []
    for tick, ok in enumerate(flags):
        watch.update(tick, ok)
        out.append(watch.held)
    return out


def test_a_success_held_for_the_settle_ticks_stays_a_success_when_the_object_slips():
    flags = [False] * 31 + [True] * 4 + [False]  # seed 100006: lifted at 31..34, slipping at 35
    held = feed(SuccessWatch(3), flags)
    assert held.index(True) == 34 and held[-1] is True


def test_a_flicker_shorter_than_the_settle_ticks_is_not_a_success():
    flags = [False] * 10 + [True, True, False] + [True, True, False] * 3
    w = SuccessWatch(3)
    assert not any(feed(w, flags)) and w.since is None and w.tick == len(flags) - 1


def test_the_run_of_successful_ticks_restarts_after_a_miss():
    w = SuccessWatch(2)
    for tick, ok in enumerate([True, True, False, True, True, True]):
        w.update(tick, ok)
        if tick == 1:
            assert not w.held  # 1 - 0 < 2
    assert w.held and w.since == 3


def test_with_no_settle_ticks_the_first_successful_tick_counts():
    w = SuccessWatch(0)
    w.update(5, True)
    assert w.held
