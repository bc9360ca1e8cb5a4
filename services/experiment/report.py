"""An experiment's table (markdown) and plot (success rate against N, Wilson 95% intervals)."""

from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path
from typing import Any

from services.core.stats import wilson


def _label(cell: dict[str, Any]) -> str:
    t = cell["train"]
    return t.get("label") or f"{','.join(t['views'])} ({t['rig']})"


def _group(results: dict[str, Any]) -> dict[tuple, list[dict[str, Any]]]:
    """(train label, space, eval views) -> the cells, all N and seeds."""
    out: dict[tuple, list] = defaultdict(list)
    for c in results["cells"]:
        out[(_label(c), c["space"], ",".join(c["eval_views"]))].append(c)
    return out


def _pooled(cells: list[dict[str, Any]]) -> tuple[int, int]:
    return sum(c["successes"] for c in cells), sum(c["episodes"] for c in cells)


def describe_only(only: list[str]) -> str:
    """``["N=10", "train=F", "train=five15"]`` -> ``N=10 and train=F or five15`` (values of one axis: either)."""
    axes: dict[str, list[str]] = {}
    for item in only:
        axis, _, value = item.partition("=")
        axes.setdefault(axis, []).append(value)
    return " and ".join(f"{axis}={' or '.join(values)}" for axis, values in axes.items())


def command_line(results: dict[str, Any]) -> str:
    """The ``viewscale experiment`` command that makes ``results`` again (its cache makes it quick)."""
    q = str(results["question"]).lower()
    cmd = f"viewscale experiment {q} --task {results['task']} --scale {results['scale']}"
    if results.get("seeds"):
        cmd += " --seeds " + ",".join(str(x) for x in results["seeds"])
    return cmd + "".join(f" --only {o}" for o in results.get("only") or [])


def stage_wall_s(cells: list[dict[str, Any]]) -> tuple[float, float]:
    """(training s, evaluation s) the cells' stages took when they ran; a stage shared by cells counts once."""
    train: dict[str, float] = {}
    evals: dict[str, float] = {}
    for c in cells:
        train[c["stages"]["train"]] = c.get("train_wall_s") or 0.0
        evals[c["stages"]["eval"]] = c.get("eval_wall_s") or 0.0
    return sum(train.values()), sum(evals.values())


def write_table(results: dict[str, Any], path: Path) -> None:
    ns = sorted({c["N"] for c in results["cells"]})
    seeds = sorted({c["seed"] for c in results["cells"]})
    lines = [
        f"# {results['question']}: {results['title']}",
        "",
        f"Task `{results['task']}`, scale `{results['scale']}` (preset {results['scale_settings']['preset']}, "
        f"{results['scale_settings']['steps']} steps, {len(seeds)} training seed(s) per cell: "
        f"{', '.join(map(str, seeds))}, {results['scale_settings']['episodes']} evaluation episodes per seed, "
        "the same evaluation seeds for every cell). Success k/n pooled over training seeds, Wilson 95% "
        "over the pooled episodes; with several seeds, each seed's successes after it, in seed order.",
        *(
            [f"Only the cells with {describe_only(results['only'])} (`--only`): part of the question's grid."]
            if results.get("only")
            else []
        ),
        "",
        "| training views | space | eval views | " + " | ".join(f"N={n}" for n in ns) + " |",
        "|---|---|---|" + "---|" * len(ns),
    ]
    for (label, space, ev), cells in sorted(_group(results).items()):
        row = []
        for n in ns:
            here = sorted((c for c in cells if c["N"] == n), key=lambda c: c["seed"])
            k, m = _pooled(here)
            if m == 0:
                row.append("-")
                continue
            lo, hi = wilson(k, m)
            # with several training seeds, each one's count: the spread between training runs,
            # which the pooled interval (over episodes) does not cover
            each = "; seeds " + ", ".join(f"{c['successes']}" for c in here) if len(here) > 1 else ""
            row.append(f"{k / m:.2f} ({k}/{m}, {lo:.2f}-{hi:.2f}{each})")
        lines.append(f"| {label} | {space} | {ev} | " + " | ".join(row) + " |")
    missing = results.get("missing") or []
    if missing:
        lines += ["", f"Not evaluated yet ({len(missing)} cells of the selection, left out of the table):"]
        lines += [f"- {m}" for m in missing]
    hosts = sorted({c.get("train_host") or "not recorded" for c in results["cells"]})
    lines += [
        "",
        f"Trained on {', '.join(hosts)}. A cell trained again on another CPU model can come out as "
        "differently as with another training seed (its float kernels round differently).",
    ]
    train_h, eval_h = (v / 3600 for v in stage_wall_s(results["cells"]))
    lines += [
        "",
        f"Wall time: training {train_h:.2f} h and evaluation {eval_h:.2f} h for these cells (each stage as "
        f"long as it took when it ran, a shared one once), this run {results['wall_s'] / 3600:.2f} h "
        "(cached stages are not run again); versions: " + ", ".join(f"{k} {v}" for k, v in results["versions"].items()),
    ]
    path.write_text("\n".join(lines) + "\n")


def write_plot(results: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _group(results)
    panels = sorted({(space, ev) for _, space, ev in groups})
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), dpi=100, squeeze=False)
    for ax, (space, ev) in zip(axes[0], panels):
        for (label, s, e), cells in sorted(groups.items()):
            if (s, e) != (space, ev):
                continue
            ns = sorted({c["N"] for c in cells})
            rates, lo, hi = [], [], []
            for n in ns:
                k, m = _pooled([c for c in cells if c["N"] == n])
                a, b = wilson(k, m)
                rates.append(k / m)
                lo.append(k / m - a)
                hi.append(b - k / m)
            ax.errorbar(ns, rates, yerr=[lo, hi], marker="o", capsize=3, label=label)
        ax.set_title(f"{space} space, eval from {ev}")
        ax.set_xlabel("expert demonstrations N")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{results['question']} ({results['task']}, {results['scale']})")
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
