"""The experiment runner: a question end to end at the smoke scale, cached stages skipped on a second
run, and a run killed mid-way resumes without redoing what was finished."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from cli_process import user_env

from services.core.runtime import host_description

ROOT = Path(__file__).resolve().parents[2]


def experiment(root: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "services.cli",
        "experiment",
        "q5",
        "--task",
        "lift",
        "--scale",
        "smoke",
        "--root",
        str(root),
        *extra,
    ]


def test_a_question_runs_caches_its_stages_and_resumes_after_a_kill(tmp_path):
    """Run as a user runs it in a folder of their own, with a relative --root (before, its stages ran
    in the source tree and wrote there, and the first stage found no demos where it had looked)."""
    root = tmp_path / "exp"

    def experiment_here(*extra: str) -> list[str]:
        return experiment(Path("exp"), *extra)

    proc = subprocess.Popen(
        experiment_here(), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env()
    )
    seen = []
    for line in proc.stdout:  # kill it in the middle of its first evaluation
        seen.append(line)
        if line.lstrip().startswith("evaluating from"):
            time.sleep(2.0)
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait(timeout=60)
    assert any("collecting 2 lift demos" in s for s in seen) and any(s.lstrip().startswith("training") for s in seen)
    assert not (root / "q5-lift-smoke" / "results.json").exists()

    nothing = subprocess.run(experiment_here("--table-only"), cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert nothing.returncode == 2 and "none of the 3 selected cells is evaluated yet" in nothing.stderr
    assert not (root / "q5-lift-smoke" / "results.json").exists()

    resumed = subprocess.run(experiment_here(), cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    out = resumed.stdout
    assert "collecting" not in out and "building" not in out and "training" not in out  # finished stages kept
    assert out.count("evaluating from") == 3  # the interrupted evaluation and the two not yet run
    results = json.loads((root / "q5-lift-smoke" / "results.json").read_text())
    cells = results["cells"]
    assert [c["eval_views"] for c in cells] == [["F"], ["F", "FL", "FR"], ["F", "FL", "FR", "FU", "FD"]]
    assert len({c["stages"]["train"] for c in cells}) == 1  # one checkpoint serves every evaluation
    assert all(c["episodes"] == 1 for c in cells) and results["versions"]["torch"]
    assert {c["train_host"] for c in cells} == {host_description()}  # where the weights were made
    table = (root / "q5-lift-smoke" / "table.md").read_text()
    assert table.startswith("# Q5") and table.count("| five15 |") == 3
    assert f"Trained on {host_description()}." in table
    assert (root / "q5-lift-smoke" / "success_vs_n.png").stat().st_size > 5000

    again = subprocess.run(experiment_here(), cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "evaluating from" not in again.stdout  # everything cached
    assert json.loads((root / "q5-lift-smoke" / "results.json").read_text())["cells"] == cells

    one = subprocess.run(experiment_here("--only", "eval_views=F,FL,FR"), cwd=tmp_path, capture_output=True, text=True)
    assert one.returncode == 0 and "[1/1]" in one.stdout and "evaluating from" not in one.stdout
    results = json.loads((root / "q5-lift-smoke" / "results.json").read_text())
    assert results["cells"] == [cells[1]] and results["only"] == ["eval_views=F,FL,FR"] and results["seeds"] is None
    assert "Only the cells with eval_views=F,FL,FR" in (root / "q5-lift-smoke" / "table.md").read_text()

    # Q4 shares one cell with Q5 (five15 evaluated from F): --table-only tabulates it, lists the five
    # others and makes nothing
    stages = sorted(p.name for p in (root / "cache").iterdir())
    q4 = experiment_here("--table-only")
    q4[q4.index("q5")] = "q4"
    partial = subprocess.run(q4, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert partial.returncode == 0, partial.stdout[-3000:] + partial.stderr[-3000:]
    assert "not evaluated yet (5 of 6 cells" in partial.stdout and "evaluating" not in partial.stdout
    assert sorted(p.name for p in (root / "cache").iterdir()) == stages
    q4res = json.loads((root / "q4-lift-smoke" / "results.json").read_text())
    assert q4res["cells"] == [cells[0]] and len(q4res["missing"]) == 5
    assert "Not evaluated yet (5 cells" in (root / "q4-lift-smoke" / "table.md").read_text()


def test_an_unknown_question_or_scale_is_one_line(tmp_path):
    for args, text in [
        (["q9"], "unknown experiment 'q9'"),
        (["q1", "--scale", "huge"], "unknown scale 'huge'"),
        (["q1", "--only", "views=F"], "expected AXIS=VALUE with AXIS one of train, space, N"),
        (["q1", "--only", "N=7"], "this question's N values are 10, 25, 50"),
        # a file for --root: before, a NotADirectoryError traceback once the first stage started
        (
            ["q1", "--scale", "smoke", "--root", str(tmp_path / "a-file")],
            f"--root {tmp_path / 'a-file'}: not a directory",
        ),
    ]:
        (tmp_path / "a-file").write_text("")
        proc = subprocess.run(
            [sys.executable, "-m", "services.cli", "experiment", "--root", str(tmp_path), *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert proc.returncode == 2 and text in proc.stderr and "Traceback" not in proc.stderr


def test_an_interrupted_run_lets_its_training_stage_save_its_step(sim_dataset, tmp_path):
    """SIGTERM (or Ctrl-C) to a run passes one SIGINT on to the stage's command and waits for it:
    `viewscale train` saves a checkpoint at the step it was in, which the resumed stage continues
    from. Before, the command was killed 0.25 s on and lost its steps since the last checkpoint."""
    out, log = tmp_path / "train", tmp_path / "stage.log"
    args = ["train", "--data", str(sim_dataset), "--out", str(out), "--steps", "100000", "--workers", "0"]
    args += ["--no-progress", "--set", "checkpoint_every=100000"]
    code = (
        "import signal, sys\n"
        "from pathlib import Path\n"
        "from services.core.runtime import raise_interrupt\n"
        "from services.experiment.runner import viewscale\n"
        "for s in (signal.SIGINT, signal.SIGTERM):\n"
        "    signal.signal(s, raise_interrupt)\n"
        "try:\n"
        f"    viewscale({args!r}, Path({str(log)!r}))\n"
        "except KeyboardInterrupt as exc:\n"
        "    print('interrupted', exc)\n"
        "    sys.exit(130)\n"
    )
    run = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 120
        while not ((out / "log.jsonl").is_file() and (out / "log.jsonl").stat().st_size):
            assert run.poll() is None and time.monotonic() < end, log.read_text()[-3000:] if log.exists() else ""
            time.sleep(0.1)
        run.send_signal(signal.SIGTERM)  # to the run alone: the stage's command hears of it from the run
        said = run.communicate(timeout=60)[0]
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 130 and "interrupted SIGTERM" in said, said
    [saved] = sorted((out / "checkpoints").glob("step_*"))
    step = int(saved.name.removeprefix("step_"))
    assert f"stopped at step {step} of 100000" in log.read_text()
    assert "SIGINT: stopping after this step" in log.read_text()
