"""A request's views on one worker: each step of theirs is one forward pass, and nobody waits
for a view that has gone."""

from __future__ import annotations

import threading
import time

import pytest

from services.policy.worker import ViewGroup


class Recorder:
    """A compute function that records the batches it was given (the engine's pass, stood in)."""

    def __init__(self, fail: bool = False):
        self.calls: list[list[tuple]] = []
        self.fail = fail

    def __call__(self, items: list[tuple]) -> list[str]:
        self.calls.append(list(items))
        if self.fail:
            raise RuntimeError("the pass failed")
        return [f"out-{it[0]}" for it in items]


def run_members(group: ViewGroup, members: dict[str, list[tuple]], call) -> dict[str, object]:
    out: dict[str, object] = {}

    def one(name: str) -> None:
        try:
            out[name] = call(group, members[name])
        except Exception as exc:  # noqa: BLE001  (the test looks at what each member got)
            out[name] = exc

    threads = [threading.Thread(target=one, args=(n,)) for n in members]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert not any(t.is_alive() for t in threads), "a member never got its share"
    return out


def test_every_member_s_step_is_one_pass_and_each_gets_its_own_share():
    g = ViewGroup(size=3, wait_s=30.0)
    for _ in range(3):
        g.join()
    comp = Recorder()
    members = {"F": [("F",)], "FL": [("FL",), ("FL-uncond",)], "FR": [("FR",)]}
    got = run_members(g, members, lambda grp, items: grp.step(7, items, comp))
    assert len(comp.calls) == 1 and sorted(comp.calls[0]) == sorted(it for m in members.values() for it in m)
    assert got == {"F": ["out-F"], "FL": ["out-FL", "out-FL-uncond"], "FR": ["out-FR"]}
    # the next step is a pass of its own, and the encode waits for the group's size
    got = run_members(g, members, lambda grp, items: grp.step(5, items, comp))
    assert len(comp.calls) == 2 and got["FR"] == ["out-FR"]
    got = run_members(g, members, lambda grp, items: grp.encode(items, comp))
    assert len(comp.calls) == 3 and len(comp.calls[2]) == 4


def test_a_member_that_leaves_does_not_hold_the_others_back():
    g = ViewGroup(size=3, wait_s=30.0)
    for _ in range(3):
        g.join()
    comp = Recorder()
    threading.Timer(0.2, g.leave).start()  # FR's stream ends (the server dropped the view)
    t0 = time.monotonic()
    got = run_members(g, {"F": [("F",)], "FL": [("FL",)]}, lambda grp, items: grp.step(3, items, comp))
    assert time.monotonic() - t0 < 10  # released by the leave, not by the 30 s bound
    assert got == {"F": ["out-F"], "FL": ["out-FL"]} and len(comp.calls) == 1


def test_a_silent_member_costs_at_most_the_wait_bound():
    g = ViewGroup(size=2, wait_s=0.2)
    g.join()
    g.join()  # the second member is open but never sends its step
    comp = Recorder()
    t0 = time.monotonic()
    assert g.step(3, [("F",)], comp) == ["out-F"]
    assert 0.15 < time.monotonic() - t0 < 10
    assert comp.calls == [[("F",)]]


def test_a_failed_pass_fails_every_member():
    g = ViewGroup(size=2, wait_s=30.0)
    g.join()
    g.join()
    comp = Recorder(fail=True)
    got = run_members(g, {"F": [("F",)], "FL": [("FL",)]}, lambda grp, items: grp.step(1, items, comp))
    assert len(comp.calls) == 1 and all(isinstance(v, RuntimeError) for v in got.values())
    with pytest.raises(RuntimeError, match="the pass failed"):
        raise got["F"]
