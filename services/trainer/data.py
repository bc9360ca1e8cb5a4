"""The training dataset: chunks of pseudo-demos from a built cache, as a torch Dataset.

    ds = load_dataset("data/ds", split="train")
    item = ds[0]
    item["obs"]     # (To, 3, H, W) float32 in [-1, 1]
    item["state"]   # (To, D) float32, min-max normalised to [-1, 1]
    item["action"]  # (Tp, 7) float32, normalised (isotropic per block, no offset)
    item["view"]    # int, index into ds.views

Robot states and actions are small and loaded whole; frames stay in memory-mapped ``.npy``
files opened lazily in each worker process (nothing open is pickled to a DataLoader worker).
The train/val split is the dataset's (by episode, decided and recorded by the build, which fits
the normaliser on the training episodes only).
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from services.dataset.pseudo_demos import chunk_rows, chunk_starts, longest_segment, pad_hold
from services.dataset.store import DatasetError, DatasetStore

SPLITS = ("train", "val", "all")


class PseudoDemoDataset(Dataset):
    """Every (pseudo-demo, current step) chunk of the chosen split and views."""

    max_open = 256  # frame files kept mapped per process (each mapping holds a file descriptor)

    def __init__(
        self,
        path: str | Path,
        split: str = "train",
        views: list[str] | None = None,
        To: int | None = None,
        Tp: int | None = None,
        Ta: int | None = None,
        pad_actions: str | None = None,
    ):
        if split not in SPLITS:
            raise DatasetError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
        store = DatasetStore(path)
        self.path = store.path
        self.meta: dict[str, Any] = store.meta
        self.normalizer = store.normalizer
        self.views: list[str] = store.views  # view indices refer to this list
        self.To = int(To or self.meta["To"])
        self.Tp = int(Tp or self.meta["Tp"])
        self.Ta = int(Ta or self.meta["Ta"])
        self.pad_actions = pad_actions or self.meta["pad_actions"]
        chosen_views = list(views) if views is not None else list(self.views)
        unknown = [v for v in chosen_views if v not in self.views]
        if unknown or not chosen_views:
            raise DatasetError(
                f"view {', '.join(unknown) or '(none)'} is not in {self.path} (views: {', '.join(self.views)})"
            )
        self.episode_ids = store.episode_ids if split == "all" else store.split(split)
        keep_eps = set(self.episode_ids)
        self.demos = [d for d in store.demos if d.episode_id in keep_eps and d.view in chosen_views]

        states, actions, index, offsets = [], [], [], [0]
        self.longest_segment = 0  # ticks (what a chunk needs is said when none fits)
        for j, d in enumerate(self.demos):
            states.append(d.load("state", mmap=False))
            actions.append(d.load("action", mmap=False))
            ends = d.load("ends", mmap=False)
            d.load("frames", mmap=True)  # (mapped and let go: a file cut short is said now, not mid-run)
            self.longest_segment = max(self.longest_segment, longest_segment(ends))
            starts = chunk_starts(ends, self.To, self.Tp, self.Ta)
            index.append(np.concatenate([np.full((len(starts), 1), j, np.int64), starts], axis=1))
            offsets.append(offsets[-1] + d.rows)
        D = int(self.meta["state_dim"])
        self._state = np.concatenate(states) if states else np.zeros((0, D), np.float32)  # (rows, D)
        self._action = np.concatenate(actions) if actions else np.zeros((0, 7), np.float32)  # (rows, 7)
        self._offset = np.asarray(offsets, np.int64)  # demo j's rows start at _offset[j]
        self.index = np.concatenate(index) if index else np.zeros((0, 4), np.int64)  # (N, 4): demo, cur, s, e
        self._frames: OrderedDict[int, np.ndarray] = OrderedDict()

    def __len__(self) -> int:
        return len(self.index)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_frames"] = OrderedDict()  # each worker maps its own files
        return state

    def _frames_of(self, j: int) -> np.ndarray:
        arr = self._frames.get(j)
        if arr is None:
            arr = self.demos[j].load("frames", mmap=True)
            self._frames[j] = arr
            if len(self._frames) > self.max_open:
                self._frames.popitem(last=False)
        else:
            self._frames.move_to_end(j)
        return arr

    def __getitem__(self, i: int) -> dict[str, Any]:
        j, cur, s, e = (int(x) for x in self.index[i])
        obs_rows = np.clip(np.arange(cur - self.To + 1, cur + 1), s, e - 1)  # (To,)
        act_rows, inside = chunk_rows(cur, s, e, self.To, self.Tp)  # (Tp,)
        off = int(self._offset[j])
        frames = np.asarray(self._frames_of(j)[obs_rows])  # (To, H, W, 3) uint8
        obs = self.normalizer.normalize_image(frames).transpose(0, 3, 1, 2)  # (To, 3, H, W)
        state = self.normalizer.normalize_state(self._state[off + obs_rows])  # (To, D)
        action = self._action[off + act_rows]  # (Tp, 7)
        if self.pad_actions == "hold":
            action = pad_hold(action, inside)
        action = self.normalizer.normalize_action(action)
        return {
            "obs": torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32)),
            "state": torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)),
            "action": torch.from_numpy(np.ascontiguousarray(action, dtype=np.float32)),
            "view": self.demos[j].view_index,
        }

    def camera(self, view: str) -> dict[str, Any] | None:
        """Calibration of ``view`` at the cached image size (K, R_ext, position)."""
        return self.meta["cameras"].get(view)


def load_dataset(path: str | Path, split: str = "train", **kwargs: Any) -> PseudoDemoDataset:
    """Open a built dataset; keyword arguments as ``PseudoDemoDataset``."""
    return PseudoDemoDataset(path, split=split, **kwargs)
