"""The checkpoint folders a run keeps: the newest ``keep``, ``latest`` naming the newest, and no
``.partial`` folder of a save that was cut short (a run stopped at once mid-save left one behind)."""

import re

import torch

from services.policy.checkpoint import latest_checkpoint, save_checkpoint


def _save(run, step):
    return save_checkpoint(run, step, {"w": torch.full((2,), float(step))}, {"note": "test"}, {"t": torch.zeros(1)}, {})


def test_a_save_keeps_the_newest_and_drops_the_folders_of_cut_saves(tmp_path):
    run = tmp_path / "run"
    _save(run, 1)
    cut = run / "checkpoints" / "step_0000002.partial"  # what a save stopped mid-way leaves
    cut.mkdir()
    (cut / "model.safetensors").write_bytes(b"\0" * 10)
    assert latest_checkpoint(run).name == "step_0000001"  # a cut save is never the latest
    _save(run, 3)
    _save(run, 4)
    assert sorted(p.name for p in (run / "checkpoints").iterdir() if p.is_dir()) == ["step_0000003", "step_0000004"]
    assert latest_checkpoint(run).name == "step_0000004"


def test_a_served_checkpoint_is_kept_until_its_server_ends(tmp_path):
    """A policy server (and its workers) hold their checkpoint for reading while they serve; a
    worker started again loads it again (before: the run's next saves removed it under them)."""
    from services.core.runtime import reading

    run = tmp_path / "run"
    served = _save(run, 1)
    with reading(served, "policy server"):
        _save(run, 2)
        _save(run, 3)
        _save(run, 4)
        assert sorted(p.name for p in (run / "checkpoints").iterdir() if p.is_dir()) == [
            "step_0000001",
            "step_0000003",
            "step_0000004",
        ]
        assert (served / "model.safetensors").is_file()
    _save(run, 5)  # nothing serves it any more: the next save removes it
    assert sorted(p.name for p in (run / "checkpoints").iterdir() if p.is_dir()) == ["step_0000004", "step_0000005"]


def test_a_save_that_cannot_be_written_is_one_error_naming_the_checkpoint_kept(tmp_path):
    """(a full disk at a save: safetensors' traceback, and the training's end without a word on
    what was kept)"""
    import pytest

    from services.policy.checkpoint import CheckpointError

    run = tmp_path / "run"
    kept = _save(run, 1)
    blocked = run / "checkpoints" / "step_0000002.partial"
    blocked.write_text("in the way")  # a file where the save makes its folder: an OSError, as a full disk is
    with pytest.raises(
        CheckpointError,
        match=rf"^cannot save checkpoint step_0000002 in {run}: .*; the newest saved is {kept}: the same",
    ):
        _save(run, 2)
    assert latest_checkpoint(run) == kept


def test_resolving_a_checkpoint_says_what_the_path_is_instead(tmp_path):
    import pytest

    from services.policy.checkpoint import CheckpointError, resolve_checkpoint

    run = tmp_path / "run"
    step = _save(run, 5)
    assert resolve_checkpoint(run) == step == resolve_checkpoint(step)
    assert resolve_checkpoint(run / "checkpoints") == step  # the run's checkpoints folder: its latest (was refused)
    (tmp_path / "file.txt").write_text("")
    (tmp_path / "started" / "checkpoints").mkdir(parents=True)  # a run before its first save
    (tmp_path / "cut").mkdir()
    (tmp_path / "cut" / "policy.json").write_text("{}")
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "manifest.json").write_text("{}")
    (tmp_path / "ds" / "meta.json").write_text("{}")
    (tmp_path / "empty").mkdir()
    # each of these said "is neither a checkpoint folder nor a run directory with checkpoints"
    for name, says in [
        ("nowhere", f"checkpoint {tmp_path / 'nowhere'} does not exist"),
        ("file.txt", "is a file: give a checkpoint folder or a run directory"),
        ("started", "has no complete checkpoint yet"),
        ("cut", "is an incomplete checkpoint: it has no model.safetensors"),
        ("ds", "is a dataset, not a checkpoint: train a policy on it"),
        ("empty", "is neither a checkpoint folder nor a run directory with checkpoints"),
    ]:
        with pytest.raises(CheckpointError, match=re.escape(says)):
            resolve_checkpoint(tmp_path / name)
