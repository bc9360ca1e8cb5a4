"""The experiment table: success pooled over seeds with its Wilson interval, per N, and the wall
time the cells' stages took (a checkpoint shared by two evaluations counted once)."""

from __future__ import annotations

from services.experiment.report import command_line, stage_wall_s, write_table


def cell(label, views, n, seed, k, train, ev, train_s, eval_s):
    return {
        "train": {"rig": "five15", "views": views, "label": label},
        "space": "camera",
        "N": n,
        "seed": seed,
        "eval_views": ["F"],
        "successes": k,
        "episodes": 50,
        "success_rate": k / 50,
        "train_wall_s": train_s,
        "eval_wall_s": eval_s,
        "stages": {"train": train, "eval": ev},
    }


def results(cells):
    return {
        "question": "Q1",
        "title": "Can multiple pseudo-demonstrations improve imitation learning?",
        "task": "lift",
        "scale": "tiny",
        "scale_settings": {"preset": "tiny", "steps": 6000, "episodes": 50},
        "only": ["space=camera", "train=F", "train=five15"],
        "versions": {"torch": "2.x"},
        "cells": cells,
        "wall_s": 36.0,
    }


def test_the_table_pools_seeds_per_n_and_says_what_the_stages_took(tmp_path):
    cells = [
        cell("F", ["F"], 10, 0, 28, "t1", "e1", 1200.0, 120.0),
        cell("F", ["F"], 10, 1, 30, "t2", "e2", 1300.0, 110.0),
        cell("five15", ["F", "FL", "FR", "FU", "FD"], 10, 0, 45, "t3", "e3", 1500.0, 100.0),
        cell("five15", ["F", "FL", "FR", "FU", "FD"], 25, 0, 49, "t4", "e4", 1600.0, 90.0),
    ]
    path = tmp_path / "table.md"
    write_table(results(cells), path)
    text = path.read_text()
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    # F at N=10: two seeds pooled, 58/100; no N=25 cell for F
    assert "0.58 (58/100, 0.48-0.67; seeds 28, 30)" in rows["F"] and rows["F"].rstrip().endswith("| - |")
    assert "0.90 (45/50, 0.79-0.96) |" in rows["five15"] and "0.98 (49/50, 0.90-1.00)" in rows["five15"]
    assert "| training views | space | eval views | N=10 | N=25 |" in text
    assert "Only the cells with space=camera and train=F or five15 (`--only`)" in text
    # 5600 s of training and 420 s of evaluation, against this run's 36 s
    assert "training 1.56 h and evaluation 0.12 h" in text and "this run 0.01 h" in text


def test_a_checkpoint_shared_by_evaluations_counts_once():
    a = cell("F", ["F"], 10, 0, 20, "t1", "e1", 1000.0, 100.0)
    b = cell("F", ["F"], 10, 0, 25, "t1", "e2", 1000.0, 150.0)  # same training, another evaluation
    assert stage_wall_s([a, b]) == (1000.0, 250.0)


def test_the_command_line_repeats_the_selection_and_the_seeds():
    res = results([])
    assert command_line(res) == (
        "viewscale experiment q1 --task lift --scale tiny --only space=camera --only train=F --only train=five15"
    )
    res["seeds"] = [0, 1, 2]
    assert command_line(res) == (
        "viewscale experiment q1 --task lift --scale tiny --seeds 0,1,2"
        " --only space=camera --only train=F --only train=five15"
    )
