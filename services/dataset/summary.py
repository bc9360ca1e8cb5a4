"""A dataset's summary: counts, drops by reason and action statistics (``summary.json``), and the
text ``viewscale dataset build`` and ``info`` print from it."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.core.action_spaces import ACTION_DIM
from services.core.normalizer import Normalizer
from services.core.text import first_few
from services.dataset.pseudo_demos import chunk_starts
from services.dataset.store import EPISODES

# why an episode is left out of a build: its reason, and the flag that builds it anyway
FAILED = "not marked successful"  # --include-failed
ROLLOUT = "driven by a policy"  # --include-rollouts
EMPTY = "with no robot state recorded"  # (no flag: nothing to learn from)


def left_out_lines(left_out: Sequence[dict[str, str]], head: str = "left out ") -> list[str]:
    """One line per reason: how many episodes, which, and the flag that builds them anyway."""
    lines = []
    for reason, flag in ((FAILED, "--include-failed"), (ROLLOUT, "--include-rollouts"), (EMPTY, None)):
        ids = [x["episode"] for x in left_out if reason in x["reason"]]
        if ids:
            then = f"{flag} builds them" if flag else "nothing to learn from (no robot service or sim ran?)"
            lines.append(f"{head}{len(ids)} episodes {reason} ({first_few(ids, 5)}): {then}")
    return lines


ACTION_LAYOUT = ["dp_x", "dp_y", "dp_z", "drot_x", "drot_y", "drot_z", "gripper"]
EPISODE_DROPS = ("duplicate_state", "no_action", "stale_action", "action_without_state")
VIEW_DROPS = ("missing_frame", "stale_frame", "bad_frame")


def summarise(
    store_dir: Path,
    params,
    episodes: list[dict[str, Any]],
    norm: Normalizer,
    skipped: list[dict[str, str]],
    split: tuple[list[str], list[str]],
    left_out: Sequence[dict[str, str]] = (),
) -> dict[str, Any]:
    """The summary of a build: ``episodes`` as the build lists them (id, dir, info); ``split``
    the (train, val) episode ids; ``left_out`` the episodes not built ({file, episode, reason})."""
    acts, samples_per_view, rows_per_view = [], {v: 0 for v in params.views}, {v: 0 for v in params.views}
    drops: dict[str, Any] = {k: 0 for k in EPISODE_DROPS}
    drops["views"] = {v: {k: 0 for k in VIEW_DROPS} for v in params.views}
    for e in episodes:
        d = store_dir / EPISODES / e["dir"]
        info = e["info"]
        for k in EPISODE_DROPS:
            drops[k] += int(info["drops"].get(k, 0))
        for v in params.views:
            for k, n in info["drops"]["views"][v].items():
                drops["views"][v][k] = drops["views"][v].get(k, 0) + int(n)
            a = np.load(d / f"{v}.action.npy")
            acts.append(a)
            rows_per_view[v] += len(a)
            samples_per_view[v] += len(chunk_starts(np.load(d / f"{v}.ends.npy"), params.To, params.Tp, params.Ta))
    a = np.concatenate(acts) if acts else np.zeros((0, ACTION_DIM))
    a_n = norm.normalize_action(a) if len(a) else a

    def stat(f) -> list[float] | None:
        return [round(float(x), 6) for x in f(a, axis=0)] if len(a) else None

    return {
        "episodes": len(episodes),
        "views": list(params.views),
        "pseudo_demos": len(episodes) * len(params.views),
        "action_space": params.space,
        "state_frame": params.state_frame,
        "image_size": list(params.image_size),
        "To": params.To,
        "Tp": params.Tp,
        "Ta": params.Ta,
        "ticks": sum(int(e["info"]["ticks"]) for e in episodes),
        "rows": sum(rows_per_view.values()),
        "rows_per_view": rows_per_view,
        "samples": sum(samples_per_view.values()),
        "samples_per_view": samples_per_view,
        "successful_episodes": sum(1 for e in episodes if e["info"]["meta"].get("success")),
        "flagged_episodes": {e["id"]: e["info"]["meta"]["flags"] for e in episodes if e["info"]["meta"].get("flags")},
        "drops": drops,
        "skipped_episodes": skipped,
        "left_out_episodes": list(left_out),
        "action_stats": {
            "layout": ACTION_LAYOUT,
            "mean": stat(np.mean),
            "std": stat(np.std),
            "min": stat(np.min),
            "max": stat(np.max),
            "pos_norm_max": float(np.linalg.norm(a[:, 0:3], axis=1).max()) if len(a) else 0.0,
            "rot_norm_max": float(np.linalg.norm(a[:, 3:6], axis=1).max()) if len(a) else 0.0,
            "normalised_abs_max": [round(float(x), 6) for x in np.abs(a_n).max(axis=0)] if len(a) else None,
        },
        "normalizer": {"pos_scale": norm.pos_scale, "rot_scale": norm.rot_scale},
        "split": {"train": len(split[0]), "val": len(split[1]), "val_episodes": list(split[1])},
    }


def _fmt_vec(v: list[float] | None) -> str:
    return "-" if v is None else "[" + ", ".join(f"{x:+.4f}" for x in v) + "]"


def format_summary(s: dict[str, Any], path: Path | None = None) -> str:
    lines = []
    if path is not None:
        lines.append(f"dataset {path}")
    lines += [
        f"  episodes      {s['episodes']} ({s['successful_episodes']} successful)",
        f"  views         {', '.join(s['views'])}  -> {s['pseudo_demos']} pseudo-demos",
        f"  action space  {s['action_space']}   state frame {s['state_frame']}",
        f"  image size    {s['image_size'][0]}x{s['image_size'][1]}   To={s['To']} Tp={s['Tp']} Ta={s['Ta']}",
        f"  ticks         {s['ticks']} recorded, {s['rows']} kept over all views",
        f"  samples       {s['samples']}  (" + ", ".join(f"{v} {n}" for v, n in s["samples_per_view"].items()) + ")",
    ]
    d = s["drops"]
    view_drops = ", ".join(
        f"{v}: " + " ".join(f"{k}={n}" for k, n in c.items() if n) for v, c in d["views"].items() if any(c.values())
    )
    lines.append(
        f"  dropped       no_action={d['no_action']} duplicate_state={d['duplicate_state']} "
        f"stale_action={d['stale_action']}{' (kept)' if d['stale_action'] else ''}"
        + (f"; frames {view_drops}" if view_drops else "; no frames dropped")
    )
    a = s["action_stats"]
    lines += [
        "  actions       (dp_x dp_y dp_z drot_x drot_y drot_z gripper)",
        f"    mean        {_fmt_vec(a['mean'])}",
        f"    std         {_fmt_vec(a['std'])}",
        f"    min         {_fmt_vec(a['min'])}",
        f"    max         {_fmt_vec(a['max'])}",
        f"    |normed|max {_fmt_vec(a['normalised_abs_max'])}",
        f"  normalizer    pos_scale {s['normalizer']['pos_scale']:.5f} m   "
        f"rot_scale {s['normalizer']['rot_scale']:.5f} rad (fitted on the training episodes)",
    ]
    if "split" in s:
        sp = s["split"]
        lines.append(
            f"  split         {sp['train']} training, {sp['val']} held-out episodes"
            + (f" ({first_few(sp['val_episodes'], 5)})" if sp["val"] else "")
        )
    if s.get("flagged_episodes"):
        lines.append(
            f"  flagged       {len(s['flagged_episodes'])} episodes: "
            + "; ".join(f"{k}: {', '.join(v)}" for k, v in list(s["flagged_episodes"].items())[:5])
        )
    lines += left_out_lines(s.get("left_out_episodes", []), head="  left out      ")
    if s.get("skipped_episodes"):
        lines.append(
            f"  skipped       {len(s['skipped_episodes'])} episodes: "
            + "; ".join(x["error"] for x in s["skipped_episodes"][:5])
        )
    return "\n".join(lines)
