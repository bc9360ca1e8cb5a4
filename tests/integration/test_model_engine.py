"""The model engine behind workers and the in-process server: what is queued together is computed
in one forward pass, nothing waits for a batch to fill, and batching does not change the numbers."""

from __future__ import annotations

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
