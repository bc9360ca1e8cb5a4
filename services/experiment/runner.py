"""``viewscale experiment q1|q2|q3|q4|q5 --task can --scale tiny|paper``: the paper's questions.

Each question is a config under ``experiments/`` (``q1.yaml`` ...): a grid of cells (training
source -- a rig and its views --, action space, number of demos N, evaluation views), each of
which is collect -> (re-render) -> dataset build -> train -> eval. Scales (``experiments/
scales.yaml``) set the preset, training steps, seeds, frame size and evaluation episodes.

Every stage is cached under ``runs/experiments/cache/<stage>-<hash>/``, the hash taken over its
config and the hashes of its inputs; a stage's ``stage.json`` is written last, when it is
complete. A second run skips complete stages; after an interruption a stage starts again (a
training resumes from its last checkpoint, as ``viewscale train`` does). ``--table-only`` makes no
stage: it tabulates what the cache holds (a grid half done, runs still going) and lists the rest.
A stage is made under a lock, so runs over one cache can go in parallel (``--only train=F`` and
``--only train=five15`` on a machine with the cores): one that needs a stage another is making
waits for it.

The N demos of a cell are the task's first N expert episodes (seeds 0 .. N-1; a collection per N,
so a cell's stages do not depend on which other cells a run selected); other rigs see
re-renderings of the same demos (``viewscale rerender``). Results go to
``runs/experiments/<question>-<task>-<scale>/``: ``results.json`` (every cell, seeds, versions),
``table.md`` and ``success_vs_n.png`` (success rate against N per training source, Wilson 95%
intervals).
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.metadata as md
import itertools
import json
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.core.config import ConfigError, read_yaml
from services.core.rig import load_rig
from services.core.runtime import child_env, host_description
from services.experiment.report import write_plot, write_table

ROOT = Path(__file__).resolve().parents[2]
EXPERIMENTS = ROOT / "experiments"
VERSION = 1  # bump when a stage's output changes meaning: every cache key changes with it
# What an evaluation counts as a success (services.core.success.SuccessWatch); a new rule
# evaluates again without training again.
SUCCESS_RULE = "held settle_ticks, then kept"


class ExperimentError(RuntimeError):
    """An experiment could not run; the message names the stage."""


def stage_hash(key: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps({"v": VERSION, **key}, sort_keys=True).encode()).hexdigest()[:12]


@dataclass
class Stage:
    """One cached stage: ``dir`` holds its output, ``stage.json`` marks it complete."""

    kind: str
    key: dict[str, Any]
    root: Path

    @property
    def hash(self) -> str:
        return stage_hash({"kind": self.kind, **self.key})

    @property
    def dir(self) -> Path:
        return self.root / f"{self.kind}-{self.hash}"

    @property
    def done(self) -> bool:
        return (self.dir / "stage.json").is_file()

    def finish(self, **facts: Any) -> None:
        tmp = self.dir / "stage.json.tmp"
        tmp.write_text(json.dumps({"kind": self.kind, "key": self.key, "hash": self.hash, **facts}, indent=2))
        tmp.replace(self.dir / "stage.json")

    def facts(self) -> dict[str, Any]:
        return json.loads((self.dir / "stage.json").read_text())

    @contextmanager
    def claimed(self, progress: Callable[[str], None]) -> Iterator[Stage]:
        """Hold this stage's lock while checking and making it: a second run over the same cache
        (another ``--only`` selection in parallel, or the same command twice) waits for it instead
        of making it too and clobbering the first one's files. The OS drops the lock of a run that
        dies, killed or not. A finished stage is nobody's to hold: taking its lock never waits."""
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / f"{self.kind}-{self.hash}.lock", "w") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                progress(f"waiting for another run making {self.dir}")
                fcntl.flock(fh, fcntl.LOCK_EX)
            yield self


def viewscale(args: list[str], log: Path) -> None:
    """One ``viewscale`` command as a process (as a user would run it, in this process's folder, so a
    relative --root means the same to it); its output goes to ``log``.

    An interrupt of this run (Ctrl-C, SIGTERM: a KeyboardInterrupt here) is passed on to the command
    as one SIGINT, and its end awaited before the interrupt goes on: the command stops in its own way
    (a training run saves a checkpoint at its step, a collection keeps the episode it was in). The
    command has a session of its own, so a terminal's Ctrl-C reaches it only this way, once; a
    second interrupt is passed on too (it stops at once), a third kills it."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write(f"$ viewscale {' '.join(args)}\n")
        f.flush()
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *args],
            stdout=f,
            stderr=f,
            env=child_env(),
            start_new_session=True,
        )
        interrupted: KeyboardInterrupt | None = None
        passed_on = 0
        while True:
            try:
                rc = proc.wait()
                break
            except KeyboardInterrupt as exc:
                interrupted = interrupted or exc
                if passed_on == 2:
                    proc.kill()
                    continue
                proc.send_signal(signal.SIGINT)
                passed_on += 1
        if interrupted is not None:
            raise interrupted
    if rc != 0:
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-12:])
        raise ExperimentError(f"viewscale {args[0]} failed (exit {rc}); the end of {log}:\n{tail}")


def load_question(name: str) -> dict[str, Any]:
    path = EXPERIMENTS / f"{name.lower()}.yaml"
    if not path.is_file():
        have = ", ".join(sorted(p.stem for p in EXPERIMENTS.glob("q*.yaml")))
        raise ConfigError(f"unknown experiment {name!r}; experiments: {have}")
    return read_yaml(path)


def load_scale(name: str) -> dict[str, Any]:
    scales = read_yaml(EXPERIMENTS / "scales.yaml")
    if name not in scales:
        raise ConfigError(f"unknown scale {name!r}; scales: {', '.join(scales)}")
    return scales[name]


def cells(q: dict[str, Any], scale: dict[str, Any]) -> list[dict[str, Any]]:
    """The grid's cells: every combination of its axes, once per training seed of the scale."""
    grid = dict(q["grid"])
    if "N" in scale:  # a scale may shrink the demo counts (smoke)
        grid["N"] = scale["N"]
    axes = ["train", "space", "N", "eval_views"]
    values = [grid[a] for a in axes]
    out = []
    for combo in itertools.product(*values, scale["seeds"]):
        cell = dict(zip([*axes, "seed"], combo))
        cell["N"] = int(cell["N"])
        out.append(cell)
    return out


AXES = ("train", "space", "N", "eval_views", "seed")


def cell_value(cell: dict[str, Any], axis: str) -> str:
    """How ``--only`` names a cell's value on ``axis``: the training label, ``F,FL,FR``, ``10``..."""
    if axis == "train":
        return cell["train"].get("label") or ",".join(cell["train"]["views"])
    if axis == "eval_views":
        return ",".join(cell["eval_views"])
    return str(cell[axis])


def select(all_cells: list[dict[str, Any]], only: list[str]) -> list[dict[str, Any]]:
    """The cells matching every ``AXIS=VALUE`` filter (several filters on one axis: any of them)."""
    wanted: dict[str, set[str]] = {}
    for item in only:
        axis, sep, value = item.partition("=")
        if not sep or axis not in AXES:
            raise ConfigError(f"--only {item!r}: expected AXIS=VALUE with AXIS one of {', '.join(AXES)}")
        known = sorted({cell_value(c, axis) for c in all_cells})
        if value not in known:
            raise ConfigError(f"--only {item!r}: this question's {axis} values are {', '.join(known)}")
        wanted.setdefault(axis, set()).add(value)
    return [c for c in all_cells if all(cell_value(c, a) in v for a, v in wanted.items())]


class Runner:
    def __init__(
        self,
        question: str,
        task: str,
        scale: str,
        root: Path,
        progress: Callable[[str], None] = print,
        only: list[str] = (),
        seeds: list[int] | None = None,
    ):
        self.name = question.lower()
        self.q = load_question(self.name)
        self.scale_name = scale
        self.scale = load_scale(scale)
        self.seeds = None if seeds is None else list(seeds)  # recorded: the command that repeats the run names them
        if seeds is not None:  # training seeds other than the scale's (several per cell on a CPU, overnight)
            if not seeds or any(not isinstance(x, int) or x < 0 for x in seeds) or len(set(seeds)) != len(seeds):
                raise ConfigError(f"seeds {seeds!r}: expected distinct non-negative integers")
            self.scale = {**self.scale, "seeds": list(seeds)}
        self.task = task
        self.root = Path(root)
        self.cache = self.root / "cache"
        self.out = self.root / f"{self.name}-{task}-{scale}"
        self.progress = progress
        self.only = list(only)
        self.cells = select(cells(self.q, self.scale), self.only)
        if not self.cells:
            raise ConfigError(f"{self.name}: the grid has no cells")

    # -- stages ---------------------------------------------------------------------------------
    def demos_stage(self, n: int) -> Stage:
        """The stage of the first ``n`` expert demos. Keyed by ``n``, never by which cells a run
        selected: a cell of ``--only N=10`` and the same cell of the whole grid share every stage."""
        rig = self.q.get("demos", {}).get("rig", "five15")
        return Stage("demos", {"task": self.task, "rig": rig, "N": n, "size": self.scale["size"]}, self.cache)

    def source_stage(self, rig: str, n: int) -> Stage:
        """The stage of the first ``n`` demos as seen by ``rig``: the collection, or its re-rendering."""
        demos = self.demos_stage(n)
        if rig == demos.key["rig"]:
            return demos
        return Stage("rerender", {"demos": demos.hash, "rig": rig}, self.cache)

    def dataset_stage(self, cell: dict[str, Any]) -> Stage:
        src = self.source_stage(cell["train"]["rig"], cell["N"])
        views = list(cell["train"]["views"])
        key = {"source": src.hash, "N": cell["N"], "views": views, "space": cell["space"], "size": self.scale["size"]}
        return Stage("dataset", key, self.cache)

    def training_stage(self, cell: dict[str, Any]) -> Stage:
        s = self.scale
        key = {
            "dataset": self.dataset_stage(cell).hash,
            "preset": s["preset"],
            "steps": s["steps"],
            "seed": cell["seed"],
            "set": list(s.get("train_set", [])),
        }
        return Stage("train", key, self.cache)

    def evaluation_stage(self, cell: dict[str, Any]) -> Stage:
        key = {
            "train": self.training_stage(cell).hash,
            "task": self.task,
            "views": list(cell["eval_views"]),
            "episodes": self.scale["episodes"],
            "rig": cell["train"]["rig"],
            "success_rule": SUCCESS_RULE,
        }
        return Stage("eval", key, self.cache)

    def demos(self, n: int) -> Stage:
        st = self.demos_stage(n)
        rig = st.key["rig"]
        with st.claimed(self.progress):
            if st.done:  # made before, or by another run while this one waited
                return st
            shutil.rmtree(st.dir, ignore_errors=True)  # an interrupted collection starts over
            st.dir.mkdir(parents=True)
            self.progress(f"collecting {n} {self.task} demos with {rig} -> {st.dir}")
            viewscale(
                [
                    "collect",
                    "--task",
                    self.task,
                    "--episodes",
                    str(n),
                    "--rig",
                    rig,
                    "--size",
                    str(self.scale["size"]),
                    "--fast",
                    "--out",
                    str(st.dir / "raw"),
                ],
                st.dir / "log.txt",
            )
            st.finish(episodes=len(list((st.dir / "raw").glob("*.mcap"))))
            return st

    def source(self, rig: str, n: int) -> tuple[Stage, Path]:
        """The first ``n`` demos as seen by ``rig``: the collection itself, or a re-rendering of it."""
        demos = self.demos(n)
        if rig == demos.key["rig"]:
            return demos, demos.dir / "raw"
        st = self.source_stage(rig, n)
        with st.claimed(self.progress):
            if not st.done:
                shutil.rmtree(st.dir, ignore_errors=True)
                st.dir.mkdir(parents=True)
                self.progress(f"re-rendering the demos through {rig} -> {st.dir}")
                viewscale(
                    ["rerender", "--raw", str(demos.dir / "raw"), "--rig", rig, "--out", str(st.dir / "raw")],
                    st.dir / "log.txt",
                )
                st.finish()
        return st, st.dir / "raw"

    def dataset(self, cell: dict[str, Any]) -> Stage:
        _, raw = self.source(cell["train"]["rig"], cell["N"])
        views = list(cell["train"]["views"])
        st = self.dataset_stage(cell)
        with st.claimed(self.progress):
            if st.done:  # made before, or by another run while this one waited
                return st
            files = sorted(raw.glob("*.mcap"))[: cell["N"]]
            if len(files) < cell["N"]:
                raise ExperimentError(f"{len(files)} demos where the cell needs {cell['N']}")
            st.dir.mkdir(parents=True, exist_ok=True)
            self.progress(f"building {cell['N']} x {len(views)} {cell['space']}-space pseudo-demos -> {st.dir}")
            size = self.scale["size"]
            viewscale(
                [
                    "dataset",
                    "build",
                    "--raw",
                    *map(str, files),
                    "--views",
                    ",".join(views),
                    "--space",
                    cell["space"],
                    "--image-size",
                    f"{size}x{size}",
                    "--out",
                    str(st.dir / "ds"),
                ],
                st.dir / "log.txt",
            )
            st.finish()
            return st

    def training(self, cell: dict[str, Any]) -> Stage:
        ds = self.dataset(cell)
        s = self.scale
        st = self.training_stage(cell)
        with st.claimed(self.progress):
            if st.done:  # made before, or by another run while this one waited
                return st
            st.dir.mkdir(parents=True, exist_ok=True)  # kept: an interrupted training resumes from its checkpoint
            self.progress(f"training {s['preset']} for {s['steps']} steps (seed {cell['seed']}) -> {st.dir}")
            t0 = time.monotonic()
            args = [
                "train",
                "--data",
                str(ds.dir / "ds"),
                "--preset",
                s["preset"],
                "--steps",
                str(s["steps"]),
                "--seed",
                str(cell["seed"]),
                "--out",
                str(st.dir / "run"),
                "--no-progress",
            ]
            for item in s.get("train_set", []):
                args += ["--set", item]
            viewscale(args, st.dir / "log.txt")
            st.finish(wall_s=round(time.monotonic() - t0, 1), host=host_description())
            return st

    def evaluation(self, cell: dict[str, Any]) -> Stage:
        tr = self.training(cell)
        views = list(cell["eval_views"])
        st = self.evaluation_stage(cell)
        with st.claimed(self.progress):
            if st.done:  # made before, or by another run while this one waited
                return st
            shutil.rmtree(st.dir, ignore_errors=True)  # an interrupted evaluation runs again from its first episode
            st.dir.mkdir(parents=True)
            self.progress(f"evaluating from {','.join(views)}: {self.scale['episodes']} episodes -> {st.dir}")
            t0 = time.monotonic()
            rig = self.q.get("demos", {}).get("rig", "five15")  # the scene the robot acts in: the demos' rig
            viewscale(
                [
                    "eval",
                    "--checkpoint",
                    str(tr.dir / "run"),
                    "--task",
                    self.task,
                    "--episodes",
                    str(self.scale["episodes"]),
                    "--views",
                    ",".join(views),
                    "--rig",
                    eval_rig(cell, rig),
                    "--out",
                    str(st.dir / "eval"),
                ],
                st.dir / "log.txt",
            )
            st.finish(wall_s=round(time.monotonic() - t0, 1))
            return st

    # -- the whole question -----------------------------------------------------------------------
    def run(self, table_only: bool = False) -> dict[str, Any]:
        """Every selected cell, each stage made unless cached; then results.json, the table and the plot.

        ``table_only``: make no stage; tabulate the cells already evaluated in the cache (by this or
        any other run, finished or still going) and list the others as not evaluated yet."""
        t0 = time.monotonic()
        rows, missing = [], []
        for i, cell in enumerate(self.cells, 1):
            if table_only:
                ev = self.evaluation_stage(cell)
                if not ev.done:
                    missing.append(describe(cell))
                    continue
            else:
                self.progress(f"[{i}/{len(self.cells)}] {describe(cell)}")
                ev = self.evaluation(cell)
            tr = self.training_stage(cell)  # made before its evaluation: no second walk through the stages
            trained = tr.facts() if tr.done else {}
            rep = json.loads((ev.dir / "eval" / "report.json").read_text())["summary"]
            rows.append(
                {
                    **cell,
                    "successes": rep["successes"],
                    "episodes": rep["episodes"],
                    "success_rate": rep["success_rate"],
                    "wilson95": rep["wilson95"],
                    "train_wall_s": trained.get("wall_s"),
                    "train_host": trained.get("host"),  # its weights depend on the CPU
                    "eval_wall_s": ev.facts().get("wall_s"),
                    "stages": {"train": tr.hash, "eval": ev.hash},
                }
            )
            if not table_only:
                self.progress(f"    {rep['successes']}/{rep['episodes']} successful")
        if missing:
            self.progress(f"not evaluated yet ({len(missing)} of {len(self.cells)} cells, left out of the table):")
            for m in missing:
                self.progress(f"    {m}")
        if not rows:
            raise ExperimentError(
                f"none of the {len(self.cells)} selected cells is evaluated yet in {self.cache}: "
                "run the question without --table-only to make them"
            )
        self.out.mkdir(parents=True, exist_ok=True)
        results = {
            "question": self.q.get("question", self.name),
            "title": self.q.get("title", ""),
            "task": self.task,
            "scale": self.scale_name,
            "scale_settings": self.scale,
            "only": self.only,  # the cells were filtered: the table is part of the question's grid
            "seeds": self.seeds,  # --seeds: training seeds other than the scale's (None: the scale's)
            "versions": versions(),
            "cells": rows,
            "missing": missing,  # cells of the selection not evaluated yet (--table-only)
            "wall_s": round(time.monotonic() - t0, 1),
        }
        (self.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
        write_table(results, self.out / "table.md")
        write_plot(results, self.out / "success_vs_n.png")
        self.progress(f"results {self.out / 'table.md'}, plot {self.out / 'success_vs_n.png'}")
        return results


def eval_rig(cell: dict[str, Any], demos_rig: str) -> str:
    """The rig the evaluation renders: the training rig when it has every evaluation view, else the demos'."""
    train_rig = cell["train"]["rig"]
    return train_rig if set(cell["eval_views"]) <= set(load_rig(train_rig).names) else demos_rig


def describe(cell: dict[str, Any]) -> str:
    train = cell["train"]
    return (
        f"train {train.get('label') or ','.join(train['views'])} ({train['rig']}), {cell['space']} space, "
        f"N={cell['N']}, seed {cell['seed']}; eval from {','.join(cell['eval_views'])}"
    )


def versions() -> dict[str, str]:
    out = {}
    for pkg in ("viewscale", "torch", "mujoco", "diffusers", "numpy"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    try:
        out["git"] = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return out
