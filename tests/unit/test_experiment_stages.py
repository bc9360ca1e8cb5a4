"""Experiment stages are keyed by the cell, not by the cells a run selected: what ``--only N=10``
finished, the whole grid (or ``--only N=10 --only N=25``) finds in the cache."""

from __future__ import annotations

from services.experiment.runner import Runner


def test_demos_finished_by_a_subset_run_serve_the_whole_grid(tmp_path):
    said: list[str] = []
    subset = Runner("q1", "lift", "tiny", tmp_path, progress=said.append, only=["N=10"])
    grid = Runner("q1", "lift", "tiny", tmp_path, progress=said.append)
    assert {c["N"] for c in subset.cells} == {10} and {c["N"] for c in grid.cells} == {10, 25, 50}

    done = subset.demos_stage(10)
    done.dir.mkdir(parents=True)
    done.finish(episodes=10)  # as the subset run leaves it

    got = grid.demos(10)  # the grid's N=10 cells: no new collection
    assert got.hash == done.hash and said == []
    assert grid.demos_stage(25).hash != done.hash and grid.demos_stage(50).hash != done.hash
    two = Runner("q1", "lift", "tiny", tmp_path, only=["N=10", "N=25"])
    assert two.demos_stage(10).hash == done.hash


def test_a_run_waits_for_a_stage_another_run_is_making(tmp_path):
    import threading
    import time

    first = Runner("q1", "lift", "tiny", tmp_path, only=["N=10"])
    said: list[str] = []
    second = Runner("q1", "lift", "tiny", tmp_path, progress=said.append, only=["N=10"])
    st = first.demos_stage(10)
    holding, release = threading.Event(), threading.Event()

    def make() -> None:  # the first run, in the middle of making the stage
        with st.claimed(lambda _: None):
            st.dir.mkdir(parents=True)
            holding.set()
            release.wait(10)
            (st.dir / "raw").mkdir()
            st.finish(episodes=10)

    t = threading.Thread(target=make)
    t.start()
    assert holding.wait(10)
    got: list = []
    waiter = threading.Thread(target=lambda: got.append(second.demos(10)))
    waiter.start()
    deadline = time.monotonic() + 10
    while not said and time.monotonic() < deadline:
        time.sleep(0.01)
    assert said and said[0].startswith("waiting for another run making") and not got  # blocked, not collecting
    release.set()
    t.join(10)
    waiter.join(10)
    assert got and got[0].hash == st.hash and got[0].done
    assert len(said) == 1  # it found the stage finished: no collection of its own


def test_seeds_other_than_the_scales_add_cells_and_keep_seed_0s_stages(tmp_path):
    import pytest

    from services.core.config import ConfigError

    one = Runner("q1", "lift", "tiny", tmp_path, only=["N=10", "space=camera", "train=F"])
    three = Runner("q1", "lift", "tiny", tmp_path, only=["N=10", "space=camera", "train=F"], seeds=[0, 1, 2])
    assert [c["seed"] for c in one.cells] == [0] and [c["seed"] for c in three.cells] == [0, 1, 2]
    # seed 0 is the same training whichever list it came from; another seed is another training
    # on the same dataset
    t0, t1 = three.training_stage(three.cells[0]), three.training_stage(three.cells[1])
    assert t0.hash == one.training_stage(one.cells[0]).hash and t1.hash != t0.hash
    assert three.dataset_stage(three.cells[1]).hash == three.dataset_stage(three.cells[0]).hash
    assert Runner("q1", "lift", "tiny", tmp_path, only=["seed=2"], seeds=[0, 2]).cells[0]["seed"] == 2
    for bad in ([], [0, 0], [-1]):
        with pytest.raises(ConfigError, match="seeds"):
            Runner("q1", "lift", "tiny", tmp_path, seeds=bad)
