"""The checkpoint folders a run keeps: the newest ``keep``, ``latest`` naming the newest, and no
``.partial`` folder of a save that was cut short (a run stopped at once mid-save left one behind)."""

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
