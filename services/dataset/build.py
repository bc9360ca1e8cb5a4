"""The dataset build: recorded episodes -> pseudo-demos as memory-mappable numpy arrays.

The directory layout is described in ``services.dataset.store``. Builds are incremental: an
episode directory is reused when its source hash and the parameters that shaped its arrays are
unchanged, and the whole build is skipped when nothing changed. A source whose path, size and
mtime match the last complete build keeps its recorded hash instead of being read again
(``--force`` rehashes and rebuilds everything). Each episode is written under a temporary name
and renamed into place when complete; the manifest, written last, marks the dataset complete.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.core.action_spaces import ACTION_DIM, STATE_NAMES, check_space, needs_calibration, resolve_state_frame
from services.core.normalizer import Normalizer, NormalizerStats
from services.core.rig import CALIBRATION_MAX_AGE_DAYS
from services.core.runtime import LOCK_FILE
from services.core.tensors import FrameSizeError, decode_resized
from services.core.text import first_few
from services.dataset.calibration import calibration_problems, problems_of_info
from services.dataset.contact_sheet import write_contact_sheet
from services.dataset.episodes import (
    EpisodeError,
    align,
    episode_id,
    load_raw_episode,
    segments,
)
from services.dataset.pseudo_demos import PseudoDemo, chunk_starts, longest_segment, make_pseudo_demo, no_chunk_fits
from services.dataset.store import CONTACT_SHEET, EPISODES, MANIFEST, META, NORMALIZER, SUMMARY, VERSION, DatasetError
from services.dataset.summary import ACTION_LAYOUT, EMPTY, FAILED, ROLLOUT, left_out_lines, summarise
from services.recorder.reader import EpisodeReadError, read_episode
from services.recorder.writer import PART_SUFFIX


@dataclass(frozen=True)
class BuildParams:
    views: tuple[str, ...]  # camera names, in the order their pseudo-demos are indexed
    space: str = "camera"  # action space: base, eef or camera
    state_frame: str = "auto"  # robot state frame: auto (follows the space), base or camera
    image_size: tuple[int, int] = (84, 84)  # cached frame (width, height)
    max_frame_age_ms: float | None = None  # a frame older than this at its tick is stale; default per camera
    drop_stale_actions: bool = False  # also drop ticks whose applied action was a hold for want of a command
    To: int = 2  # observation horizon
    Tp: int = 16  # prediction horizon
    Ta: int = 8  # action steps executed per chunk (sets the end padding, as diffusion_policy)
    pad_actions: str = "edge"  # edge: repeat the edge row (diffusion_policy); hold: zero motion past the ends
    val_fraction: float = 0.1  # share of episodes held out for validation (at least one when there are two)
    split_seed: int = 0  # seeds which episodes are held out
    rig: str | None = None  # calibrated rig file to check camera-space episodes against; default: each episode's
    max_calibration_age_days: float = CALIBRATION_MAX_AGE_DAYS  # a calibration older at recording time is stale

    def __post_init__(self):
        if not self.views:
            raise DatasetError("empty view selection: name at least one camera, e.g. --views F,FL,FR")
        if len(set(self.views)) != len(self.views):
            raise DatasetError(f"view selection {','.join(self.views)} names a camera twice")
        try:
            check_space(self.space)
            object.__setattr__(self, "state_frame", resolve_state_frame(self.state_frame, self.space))
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        w, h = self.image_size
        if w < 8 or h < 8:
            raise DatasetError(f"image size {w}x{h} is too small")
        if not 0.0 <= self.val_fraction < 1.0:
            raise DatasetError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.max_frame_age_ms is not None and not self.max_frame_age_ms > 0:  # (it dropped every frame)
            raise DatasetError(f"max_frame_age_ms must be positive, got {self.max_frame_age_ms}")
        if not self.max_calibration_age_days > 0:
            raise DatasetError(f"max_calibration_age_days must be positive, got {self.max_calibration_age_days}")
        if self.pad_actions not in ("edge", "hold"):
            raise DatasetError(f"pad_actions must be edge or hold, not {self.pad_actions!r}")
        try:
            chunk_starts(np.zeros(0, np.int64), self.To, self.Tp, self.Ta)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None

    def array_key(self) -> dict[str, Any]:
        """What shapes the cached arrays; a change rebuilds every episode."""
        return {
            "version": VERSION,
            "views": list(self.views),
            "space": self.space,
            "state_frame": self.state_frame,
            "image_size": list(self.image_size),
            "max_frame_age_ms": self.max_frame_age_ms,
            "drop_stale_actions": self.drop_stale_actions,
        }

    @property
    def needs_calibration(self) -> bool:
        return needs_calibration(self.space, self.state_frame)

    def calibration_problems(self, info: dict[str, Any]) -> list[str]:
        """Why a built episode's calibration is missing or stale (services/dataset/calibration.py)."""
        if not self.needs_calibration:
            return []
        return problems_of_info(info, self.views, self.rig, self.max_calibration_age_days)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["views"], d["image_size"] = list(self.views), list(self.image_size)
        return d


@dataclass
class BuildResult:
    out: Path
    up_to_date: bool  # nothing changed: the existing dataset was kept as it was
    built: int = 0  # episodes decoded in this run
    reused: int = 0  # episodes kept from an earlier build
    frames: int = 0  # frames decoded into the cache in this run
    seconds: float = 0.0  # the whole build
    episode_seconds: float = 0.0  # reading, aligning, decoding and writing episodes (the part that scales)
    summary: dict[str, Any] = field(default_factory=dict)


# -- helpers --------------------------------------------------------------------------------------


def sha256_file(path: Path, block: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def find_episodes(raw: Path | list[Path], unique: bool = True) -> list[Path]:
    """Episode files under a directory (recursively) or given one by one, sorted by path; with
    ``unique``, DatasetError for two files of one episode id (``unique_names``)."""
    paths = raw if isinstance(raw, list) else [raw]
    found: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found += sorted(q for q in p.rglob("*.mcap") if q.is_file())
        elif p.is_file() or p.suffix == ".mcap":
            if not p.is_file():
                raise DatasetError(f"episode file {p} does not exist")
            found.append(p)
        else:
            raise DatasetError(f"raw data path {p} does not exist")
    seen: set[Path] = set()  # one file reached twice (a folder and a file in it, overlapping folders): once
    found = [q for q in found if not (q.resolve() in seen or seen.add(q.resolve()))]
    if not found:
        unfinished = unfinished_episodes(paths)
        raise DatasetError(
            f"no episode files (*.mcap) under {', '.join(str(p) for p in paths)}"
            + (f"; {unfinished_line(unfinished)}" if unfinished else "")
        )
    if unique:
        unique_names(found)
    return found


def unfinished_episodes(raw: Path | list[Path]) -> list[Path]:
    """The ``.mcap.part`` files under the folders of ``raw`` with no ``.mcap`` beside them: episodes
    being recorded, or whose recorder stopped before it closed them (recover makes the ``.mcap``)."""
    paths = raw if isinstance(raw, list) else [raw]
    return sorted(
        q
        for p in map(Path, paths)
        if p.is_dir()
        for q in p.rglob("*.mcap" + PART_SUFFIX)
        if not q.with_name(q.name[: -len(PART_SUFFIX)]).exists()
    )


def unfinished_line(unfinished: list[Path]) -> str:
    folders = sorted({str(p.parent) for p in unfinished})
    n = len(unfinished)
    return (
        f"{n} episode{'s' if n != 1 else ''} not finished, being recorded or left by a recorder that stopped "
        f"({first_few([p.name for p in unfinished])}): not built; `python -m services.recorder.recover "
        f"{' '.join(folders[:3])}{' ...' if len(folders) > 3 else ''}` rescues what they hold"
    )


def unique_names(files: list[Path]) -> None:
    """DatasetError for two files of one name: their episodes would be built into one folder."""
    stems: dict[str, Path] = {}
    for f in files:
        if f.stem in stems:
            raise DatasetError(f"two episodes named {f.stem}: {stems[f.stem]} and {f}")
        stems[f.stem] = f


# EefCommand.source of a policy's commands: the teleop service sends its driver's type, and the
# policy driver's is this (PolicyTeleopConfig.type; not imported: it would bring in the bus)
POLICY_SOURCE = "policy"


def demonstrations(
    sources: list[Path], include_failed: bool = False, include_rollouts: bool = False
) -> tuple[list[Path], list[dict[str, str]], dict[Path, dict[str, Any]]]:
    """The episode files to learn from, the others as {file, episode, reason}, and the metadata of
    those kept. Left out: not marked successful (a demonstration stopped as a failure, an
    evaluation's failed rollout, a recovered episode nobody stopped), driven by a policy (a
    rollout, successful or not: what the policy already does, not a demonstration), or holding
    no robot state (started and stopped with no arm on the bus). Only each
    file's metadata is read; a file whose metadata cannot be read is kept, so that the build
    reports it (or --skip-bad skips it)."""
    kept: list[Path] = []
    left: list[dict[str, str]] = []
    metas: dict[Path, dict[str, Any]] = {}
    for src in sources:
        try:
            md = read_episode(src, topics=()).metadata
        except EpisodeReadError:
            kept.append(src)
            continue
        why = [
            reason
            for reason, leave in (
                (FAILED, not md.get("success") and not include_failed),
                (ROLLOUT, POLICY_SOURCE in md.get("command_sources", []) and not include_rollouts),
                (EMPTY, md.get("ticks") == 0),  # (before: the whole build failed on it, 'no frames of camera')
            )
            if leave
        ]
        if why:
            left.append({"file": str(src), "episode": episode_id(src, md), "reason": ", ".join(why)})
        else:
            kept.append(src)
            metas[src] = md
    return kept, left, metas


def _by(metas: dict[Path, dict[str, Any]], key: str) -> dict[Any, list[str]]:
    """The episodes' ids by the value of metadata ``key`` (those that have one)."""
    out: dict[Any, list[str]] = {}
    for src, md in metas.items():
        if md.get(key):
            out.setdefault(md[key], []).append(episode_id(src, md))
    return dict(sorted(out.items()))


def check_mix(metas: dict[Path, dict[str, Any]], progress: Callable[[str], None]) -> None:
    """Refuse episodes recorded at different control rates: their actions are per-tick deltas, so
    one rate's steps are another's multiple, and the policy serves at one rate. Warn about
    episodes of several tasks: the policy is not told which task it is in."""
    rates = _by(metas, "control_hz")
    if len(rates) > 1:
        raise DatasetError(
            "episodes recorded at different control rates ("
            + "; ".join(f"{hz:g} Hz: {first_few(ids)}" for hz, ids in rates.items())
            + "): an action is one tick's motion, so they do not mix; build each rate's episodes on "
            "their own (--raw FILE ... or one folder per rate)"
        )
    tasks = _by(metas, "task")
    if len(tasks) > 1:
        progress(
            f"warning: episodes of {len(tasks)} tasks ("
            + ", ".join(f"{t} {len(ids)}" for t, ids in tasks.items())
            + "): a policy trained on them is not told which task it is in"
        )


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data[:2] == b"\xff\xd8" else None
    return None if img is None else (img.shape[1], img.shape[0])


# -- one episode ----------------------------------------------------------------------------------


def build_episode(src: Path, sha: str, dest: Path, params: BuildParams) -> dict[str, Any]:
    """Decode one MCAP into ``dest`` (which must not exist); returns its episode.json content."""
    ep = load_raw_episode(src, list(params.views))
    if params.needs_calibration:
        calib = {v: ep.calib.get(v) for v in params.views}
        problems = calibration_problems(src.name, calib, ep.meta, params.rig, params.max_calibration_age_days)
        if problems:
            raise EpisodeError("; ".join(problems))
    age_ns = int(params.max_frame_age_ms * 1e6) if params.max_frame_age_ms is not None else None
    al = align(ep, list(params.views), age_ns, params.drop_stale_actions)
    size = tuple(params.image_size)
    dest.mkdir(parents=True)
    views_info: dict[str, Any] = {}
    frames_done = 0
    for v in params.views:
        calib = ep.calib.get(v)
        pd = make_pseudo_demo(al, v, params.space, params.state_frame, calib, source=src.name)
        # Source size: the calibration's (K belongs to it); without one, the first frame's.
        if calib is not None:
            src_size = (calib.width, calib.height)
        else:
            firsts = (_jpeg_size(ep.frame_data[v][int(fi)]) for fi in pd.frame_index)
            src_size = next((s for s in firsts if s is not None), size)
        frames = np.zeros((len(pd.tick), size[1], size[0], 3), np.uint8)
        ok = np.ones(len(pd.tick), bool)
        for row, fi in enumerate(pd.frame_index):
            try:
                img = decode_resized(ep.frame_data[v][int(fi)], size, src_size)
            except FrameSizeError as exc:
                raise EpisodeError(
                    f"{src.name}: camera {v!r} frame at tick {int(pd.tick[row])} is {exc} "
                    f"but the camera's calibration says {src_size[0]}x{src_size[1]}"
                ) from None
            if img is None:
                ok[row] = False
            else:
                frames[row] = img
        frames_done += int(ok.sum())
        al.drops["views"][v]["bad_frame"] = int((~ok).sum())
        if not ok.all():  # an undecodable frame drops its tick for this view, like a missing one
            pd = PseudoDemo(
                pd.episode_id,
                v,
                pd.tick[ok],
                pd.stamp_ns[ok],
                pd.frame_index[ok],
                pd.state[ok],
                pd.action[ok],
                segments(pd.tick[ok]),
            )
            frames = frames[ok]
        np.save(dest / f"{v}.frames.npy", frames)
        np.save(dest / f"{v}.state.npy", pd.state.astype(np.float32))
        np.save(dest / f"{v}.action.npy", pd.action.astype(np.float32))
        np.save(dest / f"{v}.tick.npy", pd.tick)
        np.save(dest / f"{v}.stamp_ns.npy", pd.stamp_ns)
        np.save(dest / f"{v}.ends.npy", pd.ends)
        views_info[v] = {
            "rows": int(len(pd.tick)),
            "segments": int(len(pd.ends)),
            "calib": calib.to_json(*size) if calib is not None else None,
        }
    md = ep.meta
    info = {
        "version": VERSION,
        "episode_id": ep.episode_id,
        "source": {"path": str(src.resolve()), "sha256": sha, "size": src.stat().st_size},
        "key": params.array_key(),
        "meta": {
            k: md.get(k)
            for k in ("task", "seed", "rig", "success", "control_hz", "achieved_hz", "flags", "start_ns", "end_ns")
            if k in md
        },
        "ticks": int(len(ep.state_tick)),
        "aligned_ticks": int(len(al.tick)),
        "max_frame_age_ns": al.frame_tolerance_ns,
        "drops": al.drops,
        "frames_decoded": frames_done,
        "views": views_info,
    }
    _write_json(dest / "episode.json", info)
    return info


def _build_one(src: Path, sha: str, tmp: Path, params: BuildParams) -> tuple[dict | None, Exception | None, float]:
    t = time.perf_counter()
    try:
        return build_episode(src, sha, tmp, params), None, time.perf_counter() - t
    except EpisodeError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        return None, exc, time.perf_counter() - t
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _build_many(
    todo: list[Path], hashes: dict[Path, str], root: Path, params: BuildParams, jobs: int
) -> Iterator[tuple[dict | None, Exception | None, float]]:
    """Build ``todo`` into ``root/.tmp-<stem>``, yielding results in order; closing it cancels the rest.

    Threads, not processes: JPEG decoding, resizing, zstd and file writes release the GIL, and
    threads start instantly.
    """
    tmps = [root / f".tmp-{src.stem}" for src in todo]
    try:
        if jobs <= 1 or len(todo) <= 1:
            for src, tmp in zip(todo, tmps):
                yield _build_one(src, hashes[src], tmp, params)
            return
        with ThreadPoolExecutor(max_workers=min(jobs, len(todo)), thread_name_prefix="dataset-build") as pool:
            futures = [pool.submit(_build_one, src, hashes[src], tmp, params) for src, tmp in zip(todo, tmps)]
            try:
                for f in futures:
                    yield f.result()
            finally:
                for f in futures:
                    f.cancel()
    finally:
        for tmp in tmps:  # anything not renamed into place by the caller
            shutil.rmtree(tmp, ignore_errors=True)


# -- the build, step by step ------------------------------------------------------------------


def _read_manifest(out: Path) -> dict[str, Any]:
    try:
        return json.loads((out / MANIFEST).read_text()) if (out / MANIFEST).is_file() else {}
    except ValueError:
        return {}


def _check_output(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise DatasetError(f"output {out} exists and is not a directory")
    # (LOCK_FILE: the lock a build holds while it writes, ``viewscale dataset build``)
    if (
        out.is_dir()
        and any(p.name != LOCK_FILE for p in out.iterdir())
        and not ((out / MANIFEST).exists() or (out / EPISODES).is_dir())
    ):
        raise DatasetError(f"output {out} is a non-empty directory that is not a viewscale dataset")


def _hash_sources(
    sources: list[Path], old: dict[str, Any], force: bool, progress: Callable[[str], None]
) -> tuple[dict[Path, str], dict[Path, os.stat_result]]:
    """sha256 of every source; one whose path, size and mtime match the last build keeps its hash."""
    known = {e.get("path"): e for e in old.get("sources", []) if isinstance(e, dict)} if not force else {}
    stats = {s: s.stat() for s in sources}
    hashes: dict[Path, str] = {}
    to_hash = []
    for src in sources:
        k, st = known.get(str(src.resolve())), stats[src]
        if k and k.get("size") == st.st_size and k.get("mtime_ns") == st.st_mtime_ns and k.get("sha256"):
            hashes[src] = k["sha256"]
        else:
            to_hash.append(src)
    if to_hash:
        progress(f"hashing {len(to_hash)} episode files")
    for src in to_hash:
        hashes[src] = sha256_file(src)
    return hashes, stats


def _manifest(
    params: BuildParams, sources: list[Path], hashes: dict[Path, str], stats: dict[Path, os.stat_result]
) -> dict[str, Any]:
    return {
        "version": VERSION,
        "params": params.to_json(),
        "sources": [
            {
                "path": str(s.resolve()),
                "sha256": hashes[s],
                "size": stats[s].st_size,
                "mtime_ns": stats[s].st_mtime_ns,
                "dir": s.stem,
            }
            for s in sources
        ],
    }


def _is_up_to_date(out: Path, old: dict[str, Any], wanted: dict[str, Any]) -> bool:
    same = {k: old.get(k) for k in wanted} == wanted and old.get("complete")
    return bool(same) and all((out / f).is_file() for f in (META, NORMALIZER, SUMMARY))


def _calibrations_hold(out: Path, old: dict[str, Any], params: BuildParams) -> bool:
    """Every built episode's calibration still passes (the rig file may have changed since)."""
    if not params.needs_calibration:
        return True
    for s in old.get("sources", []):
        path = out / EPISODES / str(s.get("dir")) / "episode.json"
        if not path.is_file():
            continue  # skipped in that build (--skip-bad)
        try:
            info = json.loads(path.read_text())
        except ValueError:
            return False
        if params.calibration_problems(info):
            return False
    return True


def _tree_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else 0


def _check_space(out: Path, todo: list[Path], metas: dict[Path, dict[str, Any]], params: BuildParams) -> None:
    """DatasetError, before anything is decoded or removed, when the episodes to build cannot fit
    on ``out``'s disk: their frames are stored raw (uint8, at the image size, once per view). What
    the build frees as it goes counts as free: the leftovers of a build that was cut short, and the
    earlier build's folders of the episodes built again. (Before, a full disk was found by the
    episode that filled it, minutes or hours in: ``No space left on device``, with no word of how
    much the build needs.) An episode whose metadata cannot be read counts as nothing here."""
    w, h = params.image_size
    per_view = w * h * 3 + 4 * (len(STATE_NAMES) + ACTION_DIM) + 16  # a tick's frame, state, action, tick, stamp
    per_tick = len(params.views) * per_view
    ticks = sum(int(metas.get(src, {}).get("ticks") or 0) for src in todo)
    need = ticks * per_tick
    if need == 0:
        return
    free = shutil.disk_usage(next(p for p in (out, *out.parents) if p.exists())).free
    if need <= free:  # (most builds: nothing else to look at)
        return
    episodes = out / EPISODES
    freed = sum(_tree_bytes(p) for p in episodes.glob(".tmp-*")) + sum(_tree_bytes(episodes / s.stem) for s in todo)
    if need > free + freed:
        raise DatasetError(
            f"the {len(todo)} episodes to build need about {_gib(need)} in {out} ({ticks} ticks, "
            f"{len(params.views)} views of {w}x{h} frames stored raw), and {_gib(free + freed)} is free "
            f"there{' with what the build replaces' if freed else ''}: free some space, write the dataset "
            "on another disk (--out), or build fewer views or a smaller --image-size"
        )


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _start_rebuild(out: Path) -> None:
    """From here on the directory is not a complete dataset until the new manifest lands."""
    (out / EPISODES).mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).unlink(missing_ok=True)
    for leftover in (out / EPISODES).glob(".tmp-*"):
        shutil.rmtree(leftover)


def _reusable(
    out: Path, sources: list[Path], hashes: dict[Path, str], key: dict[str, Any], force: bool
) -> dict[Path, dict[str, Any]]:
    """Episode directories of an earlier build made from the same bytes with the same array key."""
    reuse: dict[Path, dict[str, Any]] = {}
    for src in sources:
        dest = out / EPISODES / src.stem
        if dest.is_dir() and not force:
            try:
                prev = json.loads((dest / "episode.json").read_text())
                if prev["source"]["sha256"] == hashes[src] and prev["key"] == key:
                    reuse[src] = prev
            except (OSError, ValueError, KeyError):
                pass
    return reuse


def _describe_built(info: dict[str, Any], views: tuple[str, ...], secs: float) -> str:
    rows = ", ".join(f"{v} {info['views'][v]['rows']}" for v in views)
    dropped = "; ".join(
        f"{v} " + " ".join(f"{n} {k}" for k, n in c.items() if n)
        for v, c in info["drops"]["views"].items()
        if any(c.values())
    )
    if info["drops"]["no_action"]:
        dropped = f"{info['drops']['no_action']} without action" + (f"; {dropped}" if dropped else "")
    return f"{info['ticks']} ticks -> rows {rows} ({secs:.1f} s)" + (f"; dropped {dropped}" if dropped else "")


@dataclass
class _Collected:
    episodes: list[dict[str, Any]] = field(default_factory=list)  # {id, dir, info}, in source order
    skipped: list[dict[str, str]] = field(default_factory=list)
    built: int = 0
    reused: int = 0
    frames: int = 0


def _build_episodes(
    out: Path,
    sources: list[Path],
    hashes: dict[Path, str],
    reuse: dict[Path, dict[str, Any]],
    params: BuildParams,
    jobs: int,
    skip_bad: bool,
    progress: Callable[[str], None],
) -> _Collected:
    """Build what cannot be reused, rename each into place, report one line per episode."""
    got = _Collected()
    todo = [s for s in sources if s not in reuse]
    results = _build_many(todo, hashes, out / EPISODES, params, jobs)
    try:
        for i, src in enumerate(sources, 1):
            info = reuse.get(src)
            problems = params.calibration_problems(info) if info is not None else []
            if problems:  # the rig file changed since the earlier build
                if not skip_bad:
                    raise EpisodeError("; ".join(problems))
                got.skipped.append({"file": str(src), "error": "; ".join(problems)})
                progress(f"[{i}/{len(sources)}] {src.name}: SKIPPED: {'; '.join(problems)}")
                continue
            if info is not None:
                got.reused += 1
                progress(f"[{i}/{len(sources)}] {src.name}: unchanged, reused")
            else:
                info, err, secs = next(results)
                if err is not None:
                    if not skip_bad:
                        raise err
                    got.skipped.append({"file": str(src), "error": str(err)})
                    progress(f"[{i}/{len(sources)}] {src.name}: SKIPPED: {err}")
                    continue
                dest = out / EPISODES / src.stem
                if dest.exists():
                    shutil.rmtree(dest)
                os.replace(out / EPISODES / f".tmp-{src.stem}", dest)
                got.built += 1
                got.frames += info["frames_decoded"]
                progress(f"[{i}/{len(sources)}] {src.name}: {_describe_built(info, params.views, secs)}")
            got.episodes.append({"id": info["episode_id"], "dir": src.stem, "info": info})
    finally:
        results.close()  # stops the workers and removes unfinished temporary directories
    return got


def _prune(out: Path, episodes: list[dict[str, Any]]) -> None:
    """Remove episode directories of sources no longer in the build; refuse an empty or ambiguous one."""
    keep = {e["dir"] for e in episodes}
    for d in (out / EPISODES).iterdir():
        if d.is_dir() and d.name not in keep:
            shutil.rmtree(d)
    if not episodes:
        raise DatasetError("no usable episodes: every one was skipped (see the messages above)")
    ids = [e["id"] for e in episodes]
    if len(set(ids)) != len(ids):
        dup = sorted({x for x in ids if ids.count(x) > 1})
        raise DatasetError(f"episode id {dup[0]} appears in more than one file")


def split_episodes(
    ids: list[str], val_fraction: float = 0.1, seed: int = 0, groups: dict[str, str] | None = None
) -> tuple[list[str], list[str]]:
    """(train ids, val ids), by episode and deterministic: episodes ranked by a hash of (seed, id),
    the first ``val_fraction`` of them held out; at least one when there are two or more.

    ``groups`` (id -> group) keeps the episodes of one group on one side: a demonstration and its
    re-renderings are one trajectory, and one of them held out while another is trained on would
    be validation on training data. An episode alone in its group here, and every episode without
    groups, is ranked by its own id: a build of re-renderings alone splits as it always did."""
    groups = groups or {}
    sizes = Counter(groups.get(i, i) for i in ids)

    def key(i: str) -> str:
        g = groups.get(i, i)
        return g if sizes[g] > 1 else i

    keys = list(dict.fromkeys(key(i) for i in ids))
    ranked = sorted(keys, key=lambda k: hashlib.sha256(f"{seed}:{k}".encode()).hexdigest())
    n_val = max(1, round(val_fraction * len(keys))) if val_fraction > 0 and len(keys) >= 2 else 0
    n_val = min(n_val, len(keys) - 1) if keys else 0
    val = set(ranked[:n_val])
    return [i for i in ids if key(i) not in val], [i for i in ids if key(i) in val]


def trajectory_groups(metas: dict[Path, dict[str, Any]]) -> dict[str, str]:
    """Episode id -> the id of the recording it was re-rendered from (``viewscale rerender`` names
    its source file, <episode id>.mcap, in ``rerendered_from``), for the re-rendered ones."""
    return {
        episode_id(src, md): Path(md["rerendered_from"]).stem for src, md in metas.items() if md.get("rerendered_from")
    }


def _fit_normalizer(out: Path, episodes: list[dict[str, Any]], views: tuple[str, ...], train: list[str]) -> Normalizer:
    """Fitted on the training episodes only: held-out data must not shape the model's units."""
    stats = NormalizerStats()
    keep = set(train)
    for e in (e for e in episodes if e["id"] in keep):
        d = out / EPISODES / e["dir"]
        for v in views:
            stats.add_actions(np.load(d / f"{v}.action.npy"))
            stats.add_states(np.load(d / f"{v}.state.npy"))
    if stats.state_min is None:
        raise DatasetError("no samples: every tick was dropped (each episode's line above says why)")
    return stats.normalizer(STATE_NAMES)


def _cameras(episodes: list[dict[str, Any]], views: tuple[str, ...]) -> tuple[dict[str, Any], dict[str, bool]]:
    """Per view: the first calibrated episode's calibration, and whether any episode differs from it."""
    cameras: dict[str, Any] = {}
    varies: dict[str, bool] = {}
    for v in views:
        cals = [e["info"]["views"][v]["calib"] for e in episodes if e["info"]["views"][v]["calib"] is not None]
        cameras[v] = cals[0] if cals else None
        varies[v] = any(
            not np.allclose(c["R_ext"], cals[0]["R_ext"], atol=1e-6)
            or not np.allclose(c["position"], cals[0]["position"], atol=1e-6)
            or not np.allclose(c["K"], cals[0]["K"], atol=1e-6)
            for c in cals[1:]
        )
    return cameras, varies


def _episode_view(info: dict[str, Any], camera: dict[str, Any] | None) -> dict[str, Any]:
    """An episode's view entry in meta.json; its calibration only where it differs from the view's."""
    out: dict[str, Any] = {"rows": info["rows"]}
    c = info["calib"]
    same = (
        c is not None
        and camera is not None
        and all(np.allclose(c[k], camera[k], atol=1e-9) for k in ("K", "R_ext", "position"))
    )
    if not same:
        out["calib"] = c
    return out


def _meta(params: BuildParams, episodes: list[dict[str, Any]], train: list[str], val: list[str]) -> dict[str, Any]:
    cameras, varies = _cameras(episodes, params.views)
    rates = sorted({float(e["info"]["meta"]["control_hz"]) for e in episodes if e["info"]["meta"].get("control_hz")})
    tasks = sorted({e["info"]["meta"]["task"] for e in episodes if e["info"]["meta"].get("task")})
    rigs = sorted({e["info"]["meta"]["rig"] for e in episodes if e["info"]["meta"].get("rig")})
    return {
        "version": VERSION,
        "control_hz": rates[0] if len(rates) == 1 else None,  # None: the episodes disagree (or never said)
        "tasks": tasks,
        "rigs": rigs,
        "action_space": params.space,
        "state_frame": params.state_frame,
        "action_dim": ACTION_DIM,
        "action_layout": ACTION_LAYOUT,
        "state_dim": len(STATE_NAMES),
        "state_names": list(STATE_NAMES),
        "views": list(params.views),
        "To": params.To,
        "Tp": params.Tp,
        "Ta": params.Ta,
        "pad_actions": params.pad_actions,
        "image_size": {"width": params.image_size[0], "height": params.image_size[1]},
        "cameras": cameras,  # per view, from the first calibrated episode; an episode that differs says so
        "calibration_varies": varies,
        "episodes": [
            {
                "id": e["id"],
                "dir": e["dir"],
                "source": e["info"]["source"]["path"],
                "sha256": e["info"]["source"]["sha256"],
                "task": e["info"]["meta"].get("task"),
                "success": e["info"]["meta"].get("success"),
                "views": {v: _episode_view(e["info"]["views"][v], cameras[v]) for v in params.views},
            }
            for e in episodes
        ],
        "split": {"val_fraction": params.val_fraction, "seed": params.split_seed, "train": train, "val": val},
    }


def build_dataset(
    raw: Path | list[Path],
    out: str | Path,
    params: BuildParams,
    *,
    progress: Callable[[str], None] = lambda msg: None,
    skip_bad: bool = False,
    force: bool = False,
    contact_episodes: int = 3,
    jobs: int = 1,
    include_failed: bool = False,
    include_rollouts: bool = False,
) -> BuildResult:
    """Build (or bring up to date) the dataset at ``out`` from the demonstrations under ``raw``:
    the episodes marked successful that no policy drove (``demonstrations``), unless
    ``include_failed`` / ``include_rollouts`` take those too.

    ``jobs`` > 1 decodes that many episodes at once (threads); results are taken in order.
    """
    t0 = time.perf_counter()
    out = Path(out)
    sources = find_episodes(raw, unique=False)  # (names need be unique among the episodes built only)
    _check_output(out)
    unfinished = unfinished_episodes(raw)
    if unfinished:  # (left out without a word before)
        progress(f"warning: {unfinished_line(unfinished)}")
    sources, left_out, metas = demonstrations(sources, include_failed, include_rollouts)
    for line in left_out_lines(left_out):
        progress(line)
    if not sources:
        raise DatasetError(
            f"none of the {len(left_out)} episodes is a demonstration to learn from ("
            + "; ".join(left_out_lines(left_out))
            + ")"
        )
    unique_names(sources)
    check_mix(metas, progress)
    old = _read_manifest(out)
    hashes, stats = _hash_sources(sources, old, force, progress)
    wanted = _manifest(params, sources, hashes, stats)
    if old and not force and _is_up_to_date(out, old, wanted) and _calibrations_hold(out, old, params):
        summary = json.loads((out / SUMMARY).read_text())
        if summary.get("left_out_episodes", []) != left_out:  # (the files left out may differ from the last build's)
            summary["left_out_episodes"] = left_out
            _write_json(out / SUMMARY, summary)
        progress(f"{out} is up to date ({len(sources)} episodes unchanged)")
        return BuildResult(out, True, reused=len(sources), seconds=time.perf_counter() - t0, summary=summary)

    reuse = _reusable(out, sources, hashes, params.array_key(), force)
    _check_space(out, [s for s in sources if s not in reuse], metas, params)
    _start_rebuild(out)
    t_eps = time.perf_counter()
    got = _build_episodes(out, sources, hashes, reuse, params, jobs, skip_bad, progress)
    episode_seconds = time.perf_counter() - t_eps
    _prune(out, got.episodes)

    train, val = split_episodes(
        [e["id"] for e in got.episodes], params.val_fraction, params.split_seed, trajectory_groups(metas)
    )
    norm = _fit_normalizer(out, got.episodes, params.views, train)
    norm.save(out / NORMALIZER)
    meta = _meta(params, got.episodes, train, val)
    _write_json(out / META, meta)
    w, h = params.image_size
    smaller = [
        f"{v} {c['source_width']}x{c['source_height']}"
        for v, c in meta["cameras"].items()
        if c and (w > c["source_width"] or h > c["source_height"])
    ]
    if smaller:  # (2000x2000 from 84x84 frames: 1.1 GB for 97 frames, no detail gained)
        progress(
            f"warning: image size {w}x{h} is larger than the recorded frames ({', '.join(smaller)}): "
            "they are upscaled, which adds no detail and costs disk and memory"
        )
    summary = summarise(out, params, got.episodes, norm, got.skipped, (train, val), left_out)
    if summary["samples"] == 0:  # (before: "samples 0" in the summary, and later "the training set is empty")
        longest = max(
            (
                longest_segment(np.load(out / EPISODES / e["dir"] / f"{v}.ends.npy"))
                for e in got.episodes
                for v in params.views
            ),
            default=0,
        )
        progress(
            f"warning: no samples: {no_chunk_fits(params.To, params.Tp, params.Ta, longest)} "
            "(a shorter --Tp, or a training run with a shorter model.pred_horizon, gets some)"
        )
    summary["build_s"] = round(time.perf_counter() - t0, 3)
    _write_json(out / SUMMARY, summary)
    if contact_episodes > 0:
        write_contact_sheet(out, meta, out / CONTACT_SHEET, max_episodes=contact_episodes)

    manifest = dict(wanted, complete=True, built_at=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    _write_json(out / MANIFEST, manifest)
    return BuildResult(
        out,
        False,
        built=got.built,
        reused=got.reused,
        frames=got.frames,
        seconds=time.perf_counter() - t0,
        episode_seconds=episode_seconds,
        summary=summary,
    )
