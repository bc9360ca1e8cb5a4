"""`make demo`'s script (deploy/demo.sh) as a user runs it with their own settings: it replaces its
OUT folder on every run, so it must never remove a folder it did not make (OUT=data, OUT=~)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def demo(tmp_path: Path, **env: str) -> subprocess.CompletedProcess:
    """Run the script in a process group of its own: should a guard let it through, the whole demo
    it starts (collect, train, serve) is stopped with it, not left running after the test."""
    proc = subprocess.Popen(
        ["bash", str(ROOT / "deploy" / "demo.sh")],
        env={**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # (whatever it started, it started in this group)
        proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_an_out_folder_it_did_not_make_is_left_as_it_is(tmp_path):
    """(before: `rm -rf "$OUT"` on whatever OUT named)"""
    mine = tmp_path / "data"
    (mine / "raw").mkdir(parents=True)
    (mine / "raw" / "lab-episode.mcap").write_bytes(b"a recording")
    run = demo(tmp_path, OUT=str(mine))
    assert run.returncode == 2
    assert run.stderr.strip() == (
        f"error: OUT={mine} holds files no demo run made (no .viewscale-demo in it), and a run replaces its OUT: "
        "choose another OUT, or empty this one yourself"
    )
    assert (mine / "raw" / "lab-episode.mcap").read_bytes() == b"a recording"
    run = demo(tmp_path, OUT=str(mine / "raw" / "lab-episode.mcap"))
    assert run.returncode == 2 and run.stderr.strip().endswith("is a file: choose a folder")
    assert (mine / "raw" / "lab-episode.mcap").read_bytes() == b"a recording"


def test_its_own_out_folder_is_replaced_and_a_bad_rig_is_one_line(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / ".viewscale-demo").write_text("made by deploy/demo.sh\n")
    (out / "stale.txt").write_text("from the last run")
    run = demo(tmp_path, OUT=str(out), EPISODES="0")  # replaced, then collect refuses 0 episodes
    assert run.returncode != 0 and "--episodes must be at least 1, got 0" in run.stderr
    assert sorted(p.name for p in out.iterdir()) == [".viewscale-demo"]
    run = demo(tmp_path, OUT=str(tmp_path / "other"), RIG="five51")
    assert run.returncode == 2
    assert run.stderr.strip() == (
        "error: RIG: unknown rig 'five51'; presets: five15, front, front_side_top, three15, three30"
    )
    assert not (tmp_path / "other").exists()
