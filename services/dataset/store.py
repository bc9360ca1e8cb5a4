"""The read side of a built dataset: its layout, and ``DatasetStore`` (torch-free).

Layout of a dataset directory::

    manifest.json        written last: build parameters, source MCAPs and their sha256. Its
                         presence marks the dataset complete; a build removes it first.
    meta.json            action space, state frame, views, To/Tp/Ta, image size, per-view
                         calibration (K at the cached size, R_ext, position), source episodes,
                         and the split: which episodes train and which are held out
    normalizer.json      services.core.normalizer.Normalizer, fitted on the training episodes only
    summary.json         counts, drops by reason, action statistics
    contact_sheet.png    first/middle/last frame of each view of a few episodes, with the
                         trajectory drawn from the pseudo-demo's own actions
    episodes/<stem>/     one MCAP's pseudo-demos: episode.json and, per view,
                         <view>.frames.npy (n, H, W, 3) uint8, <view>.state.npy (n, D) float32,
                         <view>.action.npy (n, 7) float32, <view>.tick.npy, <view>.stamp_ns.npy,
                         <view>.ends.npy (segment ends)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.core.normalizer import Normalizer
from services.core.runtime import DATASET, RECORDINGS, output_kind

VERSION = 1
MANIFEST = "manifest.json"
META = "meta.json"
NORMALIZER = "normalizer.json"
SUMMARY = "summary.json"
CONTACT_SHEET = "contact_sheet.png"
EPISODES = "episodes"
ARRAYS = ("frames", "state", "action", "tick", "stamp_ns", "ends")


class DatasetError(ValueError):
    """A user-facing problem with a dataset build or load; one clear line."""


DAMAGED = "the dataset is damaged; build it again with `viewscale dataset build`, or copy it again"


@dataclass
class StoredDemo:
    """A pseudo-demo in the cache: where its arrays live and their length."""

    episode_id: str
    episode_dir: Path
    view: str
    view_index: int
    rows: int
    calib: dict[str, Any] | None

    def path(self, name: str) -> Path:
        return self.episode_dir / f"{self.view}.{name}.npy"

    def load(self, name: str, mmap: bool = True) -> np.ndarray:
        """One of the pseudo-demo's arrays; a file missing, cut short (a copy interrupted) or of
        the wrong length is a ``DatasetError`` naming it."""
        path = self.path(name)
        try:
            arr = np.load(path, mmap_mode="r" if mmap else None)
        except FileNotFoundError:
            raise DatasetError(f"{path} is missing: {DAMAGED}") from None
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(f"{path} cannot be read ({exc}): {DAMAGED}") from None
        if name != "ends" and len(arr) != self.rows:  # (ends: one per segment)
            raise DatasetError(f"{path} holds {len(arr)} rows, not the {self.rows} the dataset lists: {DAMAGED}")
        return arr


class DatasetStore:
    """A complete dataset directory: meta, normalizer, pseudo-demos. Refuses incomplete builds."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            what = "is a file, not a folder" if self.path.exists() else "does not exist"
            raise DatasetError(f"dataset {self.path} {what}")
        manifest = self.path / MANIFEST
        if not manifest.is_file():
            kind = output_kind(self.path)  # (a run, a checkpoint, recordings: said as what they are)
            if kind not in (None, DATASET):
                build = f": build one from them with `viewscale dataset build --raw {self.path}`"
                raise DatasetError(f"{self.path} is {kind}, not a dataset" + (build if kind == RECORDINGS else ""))
            hint = (
                " (a build did not finish: run `viewscale dataset build` again)"
                if (self.path / EPISODES).is_dir()
                else ""
            )
            raise DatasetError(f"{self.path} is not a complete dataset: no {MANIFEST}{hint}")
        try:
            self.manifest = json.loads(manifest.read_text())
            self.meta = json.loads((self.path / META).read_text())
            self.normalizer = Normalizer.load(self.path / NORMALIZER)
            self.summary = json.loads((self.path / SUMMARY).read_text())
        except (OSError, ValueError, KeyError) as exc:
            raise DatasetError(f"{self.path} is damaged: {exc}") from exc
        if not self.manifest.get("complete"):
            raise DatasetError(f"{self.path} is not a complete dataset")
        self.views: list[str] = list(self.meta["views"])
        self.demos: list[StoredDemo] = []
        for e in self.meta["episodes"]:
            d = self.path / EPISODES / e["dir"]
            for vi, v in enumerate(self.views):
                ev = e["views"][v]
                calib = ev["calib"] if "calib" in ev else self.meta["cameras"].get(v)
                self.demos.append(StoredDemo(e["id"], d, v, vi, int(ev["rows"]), calib))

    @property
    def episode_ids(self) -> list[str]:
        return [e["id"] for e in self.meta["episodes"]]

    def split(self, name: str) -> list[str]:
        """Episode ids of the ``train`` or ``val`` split, as the build decided them."""
        if name not in ("train", "val"):
            raise DatasetError(f"unknown split {name!r}; choose train or val")
        split = self.meta.get("split")
        if not isinstance(split, dict) or name not in split:
            raise DatasetError(
                f"{self.path} has no train/val split recorded: rebuild it with `viewscale dataset build`"
            )
        return list(split[name])
