"""The model engine behind workers and the in-process server: what is queued together is computed
in one forward pass, nothing waits for a batch to fill, and batching does not change the numbers."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

from services.policy.worker import ModelEngine

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def engine(tiny_checkpoint):
    e = ModelEngine.open(tiny_checkpoint)
    yield e
    e.close()


def _inputs(engine: ModelEngine, n: int, seed: int = 0):
    info = engine.loaded.info
    H, W = info["model"]["image_size"]
    To, D = info["model"]["obs_horizon"], info["model"]["state_dim"]
    rng = np.random.default_rng(seed)
    frames = [rng.integers(0, 255, (To, H, W, 3), dtype=np.uint8) for _ in range(n)]
    states = [rng.uniform(-1, 1, (To, D)).astype(np.float32) for _ in range(n)]
    return frames, states


def test_a_request_of_several_views_is_one_forward_pass_with_the_single_view_numbers(engine):
    frames, states = _inputs(engine, 3)
    conds = [engine.encode(f, s).result(timeout=30) for f, s in zip(frames, states)]
    xs = [np.random.default_rng(i).standard_normal((16, 7)).astype(np.float32) for i in range(3)]
    alone = [engine.step(c, x, 7).result(timeout=30) for c, x in zip(conds, xs)]
    passes, items = engine.passes, engine.batched_items
    together = engine.step_many([(c, x, 7) for c, x in zip(conds, xs)]).result(timeout=30)
    assert (engine.passes - passes, engine.batched_items - items) == (1, 3)  # one pass for the three views
    for a, b in zip(alone, together):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)
    many = engine.encode_many(list(zip(frames, states))).result(timeout=30)
    for a, b in zip(conds, many):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


def test_work_queued_while_the_engine_computes_is_merged_and_a_lone_job_does_not_wait(engine):
    frames, states = _inputs(engine, 48, seed=1)
    cond = engine.encode(frames[0], states[0]).result(timeout=30)
    passes, items = engine.passes, engine.batched_items
    busy = engine.encode_many(list(zip(frames, states)))  # keeps the engine busy for a while
    steps = [engine.step(cond, np.zeros((16, 7), np.float32), k) for k in range(4)]  # four callers meanwhile
    busy.result(timeout=60)
    assert all(f.result(timeout=30).shape == (16, 7) for f in steps)
    assert (engine.passes - passes, engine.batched_items - items) == (2, 48 + 4)  # the four steps: one pass
    passes = engine.passes
    assert engine.step(cond, np.zeros((16, 7), np.float32), 3).result(timeout=5).shape == (16, 7)
    assert engine.passes == passes + 1  # alone, computed at once


def test_callers_computing_in_their_own_threads_share_passes_and_get_the_engine_numbers(engine):
    """The worker's path: each stream's thread computes, whatever is queued meanwhile joins its pass."""
    frames, states = _inputs(engine, 64, seed=2)
    cond = engine.encode(frames[0], states[0]).result(timeout=30)
    x = np.random.default_rng(3).standard_normal((16, 7)).astype(np.float32)
    alone = engine.step(cond, x, 5).result(timeout=30)
    torch.set_num_threads(2)  # a thread made before the model loaded (a health check's) computes with 2
    try:
        _callers_join_a_held_pass(engine, frames, states, cond, x, alone)
    finally:
        torch.set_num_threads(1)  # also when it fails: a later test's in-process reference computes in this thread


def _callers_join_a_held_pass(engine, frames, states, cond, x, alone) -> None:
    got, threads_seen = {}, {}

    def caller(i: int) -> None:
        got[i] = engine.compute_steps([(cond, x, 5)])[0]
        threads_seen[i] = torch.get_num_threads()

    # The long encode's pass is held open (the real encode, then a wait) until the callers have
    # queued behind it: on a loaded machine the encode alone could end before they queue, and the
    # loops below would wait for a pass that had already gone (seen once in a fresh-clone CI run).
    release = threading.Event()
    encode = engine._encode

    def held_encode(items):
        out = encode(items)
        release.wait(30)
        return out

    engine._encode = held_encode
    passes, items = engine.passes, engine.batched_items
    busy = threading.Thread(target=lambda: got.setdefault("busy", engine.compute_encode(list(zip(frames, states)))))
    callers: list[threading.Thread] = []
    try:
        busy.start()
        deadline = time.monotonic() + 30
        while not engine._pass.locked():  # the long encode has the pass ...
            assert time.monotonic() < deadline
            time.sleep(0.001)
        callers += [threading.Thread(target=caller, args=(i,)) for i in range(4)]
        for t in callers:
            t.start()
        while len(engine._jobs) < 4:  # ... and the four callers queue behind it
            assert time.monotonic() < deadline
            time.sleep(0.001)
        assert busy.is_alive(), "the encode ended before the callers queued: the test proves nothing"
    finally:
        release.set()
        del engine._encode  # the class's again
    for t in [busy, *callers]:
        t.join(timeout=60)
    assert len(got["busy"]) == 64
    assert engine.passes - passes == 2 and engine.batched_items - items == 64 + 4  # the four: one pass
    for i in range(4):
        np.testing.assert_allclose(got[i], alone, rtol=0, atol=1e-5)
    assert set(threads_seen.values()) == {engine.threads}  # each caller computed with the engine's count


def test_precision_bf16_computes_under_bfloat16_and_answers_float32_near_the_float32_numbers(engine, tiny_checkpoint):
    bf16 = ModelEngine.open(tiny_checkpoint, precision="bf16")  # a policy of its own: it casts its weights
    try:
        frames, states = _inputs(engine, 2, seed=3)
        x = np.random.default_rng(3).standard_normal((16, 7)).astype(np.float32)
        c32 = engine.compute_encode(list(zip(frames, states)))
        c16 = bf16.compute_encode(list(zip(frames, states)))
        e32 = engine.compute_steps([(c, x, 5) for c in c32])
        e16 = bf16.compute_steps([(c, x, 5) for c in c32])  # the same conditions: the step's own rounding
        for a, b in [*zip(c32, c16), *zip(e32, e16)]:
            assert b.dtype == np.float32
            scale = float(np.abs(a).max())
            err = float(np.abs(a - b).max())
            assert 0 < err < 0.05 * scale, (err, scale)  # bfloat16's 8 bits of mantissa: near, never equal
        assert all(p.dtype == torch.float32 for p in engine.policy.parameters())  # the fp32 engine's: untouched
        assert any(p.dtype == torch.bfloat16 for p in bf16.policy.parameters())
    finally:
        bf16.close()
    with pytest.raises(ValueError, match="precision 'fp16': fp32 or bf16"):
        ModelEngine(engine.loaded, precision="fp16")
