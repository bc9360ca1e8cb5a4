"""Record an experiment's table in bench/RESULTS.md: what each cell measured and how it was run.

    python bench/experiment_table.py runs/experiments/q1-lift-tiny

Reads the ``results.json`` that ``viewscale experiment`` writes and appends one row: the command
that reproduces it, the scale's settings, per cell the training views, action space, N, training
seed, evaluation views, successes out of episodes with the Wilson 95% interval, and the wall time
of its training and evaluation stages as they ran. The experiment cache lives in ``runs/`` (never
in git); this row is what stays.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="an experiment's output folder (or its results.json)")
    args = ap.parse_args()
    path = args.results / "results.json" if args.results.is_dir() else args.results
    if not path.is_file():
        raise SystemExit(f"error: {path} does not exist (run viewscale experiment first)")

    from services.experiment.report import command_line, stage_wall_s

    res = json.loads(path.read_text())
    command = command_line(res)
    train_s, eval_s = stage_wall_s(res["cells"])
    cells = [
        {
            "train": c["train"].get("label") or ",".join(c["train"]["views"]),
            "space": c["space"],
            "N": c["N"],
            "seed": c["seed"],
            "eval": ",".join(c["eval_views"]),
            "success": f"{c['successes']}/{c['episodes']}",
            "wilson95": [round(x, 3) for x in c["wilson95"]],
            "train_min": round((c.get("train_wall_s") or 0) / 60, 1),
            "eval_min": round((c.get("eval_wall_s") or 0) / 60, 1),
        }
        for c in res["cells"]
    ]
    report(
        "experiment",
        {
            "question": res["question"],
            "task": res["task"],
            "scale": res["scale"],
            "command": command,
            "settings": {k: v for k, v in res["scale_settings"].items() if k != "train_set"},
            "cells": cells,
            "not_evaluated": res.get("missing") or [],  # cells of the selection missing from a --table-only run
            "train_hosts": sorted({c.get("train_host") or "not recorded" for c in res["cells"]}),
            "train_h": round(train_s / 3600, 2),
            "eval_h": round(eval_s / 3600, 2),
            "git": res.get("versions", {}).get("git", ""),
        },
    )


if __name__ == "__main__":
    main()
