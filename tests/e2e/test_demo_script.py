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
    run = demo(tmp_path, OUT=str(out), TASK="cube")  # replaced, then collect refuses the task
    assert run.returncode != 0 and "unknown task 'cube'; tasks: lift, can, square" in run.stderr
    assert sorted(p.name for p in out.iterdir()) == [".viewscale-demo"]
    run = demo(tmp_path, OUT=str(tmp_path / "other"), RIG="five51")
    assert run.returncode == 2
    assert run.stderr.strip() == (
        "error: RIG: unknown rig 'five51'; presets: five15, front, front_side_top, three15, three30"
    )
    assert not (tmp_path / "other").exists()


def test_a_setting_that_cannot_work_is_one_line_before_anything_starts(tmp_path):
    """(before: COMPOSE naming a camera the rig lacks failed once the policy server started, after
    the collection and the training; a STEPS, EVAL_EPISODES or WORKERS that is no number failed at
    the stage that used it)"""
    out = tmp_path / "demo"
    for env, said in [
        ({"RIG": "three30", "COMPOSE": "F,FL,FR"}, "error: COMPOSE=F,FL,FR: rig three30 has no camera 'FL', 'FR'; "),
        ({"COMPOSE": "F,,FL"}, "error: COMPOSE=F,,FL: rig five15 has no camera ''; its cameras: F, FL, FR, FU, FD"),
        ({"STEPS": "2k"}, "error: STEPS=2k: give a whole number, at least 1"),
        ({"EVAL_EPISODES": "0"}, "error: EVAL_EPISODES=0: give a whole number, at least 1"),
        ({"WORKERS": "-1"}, "error: WORKERS=-1: give a whole number, at least 0"),
        ({"SPACE": "world"}, "error: SPACE=world: one of camera, base, eef"),
    ]:
        run = demo(tmp_path, OUT=str(out), **env)
        assert run.returncode == 2 and run.stderr.startswith(said), (env, run.stderr)
        assert not out.exists()  # nothing collected, nothing made


def test_a_tiny_demo_on_a_rig_without_fl_and_fr_composes_the_rigs_views(tmp_path):
    """The whole script end to end, at tiny settings, on the 30-degree rig (F, FL30, FR30): before,
    its default COMPOSE=F,FL,FR failed once the policy server started."""
    out = tmp_path / "demo"
    run = demo(tmp_path, OUT=str(out), RIG="three30", EPISODES="2", STEPS="5", EVAL_EPISODES="1", WORKERS="1")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "closed-loop episodes from F, then composed over F,FL30,FR30" in run.stdout
    summary = (out / "summary.md").read_text()
    assert "| F | " in summary and "| F,FL30,FR30 | " in summary
    assert (out / "eval-F" / "report.json").is_file() and (out / "eval-composed" / "videos").is_dir()
