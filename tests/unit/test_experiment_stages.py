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
