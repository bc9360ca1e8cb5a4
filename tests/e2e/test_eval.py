"""The whole chain through real processes, tiny settings: recorded sim episodes (the session's
dataset), a tiny trained policy, `viewscale eval` driving the sim through the policy server, the
scripted-expert row through the same path, and `viewscale rerender`."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from cli_process import user_env, viewscale, viewscale_each

from services.camera.opencv import fourcc_text
from services.core.tensors import decode_jpeg
from services.dataset.build import BuildParams, build_dataset
from services.dataset.store import DatasetStore
from services.policy.checkpoint import resolve_checkpoint
from services.recorder.reader import read_episode
from services.session.config import EVAL_SEEDS

ROOT = Path(__file__).resolve().parents[2]


def test_eval_drives_the_sim_through_the_policy_server_and_records_every_rollout(tiny_checkpoint, tmp_path):
    """Run as a user runs it in a folder of their own, with paths relative to it (before, the
    policy server it starts ran in the source tree and did not find a relative --checkpoint)."""
    out = tmp_path / "eval"
    proc = viewscale(
        "eval",
        "--checkpoint",
        os.path.relpath(tiny_checkpoint, tmp_path),
        "--task",
        "lift",
        "--episodes",
        "2",
        "--views",
        "F,FL",
        "--workers",
        "2",
        "--max-ticks",
        "20",
        "--video",
        "1",
        "--out",
        "eval",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "lift: " in proc.stdout and "report " in proc.stdout
    assert (out / "logs" / "worker-0.log").is_file()  # the server's own logs, beside the evaluation's
    report = json.loads((out / "report.json").read_text())
    s, rows = report["summary"], report["episodes"]
    assert s["episodes"] == 2 and len(rows) == 2 and s["views"] == ["F", "FL"] and s["workers"] == 2
    assert [r["seed"] for r in rows] == [EVAL_SEEDS["lift"], EVAL_SEEDS["lift"] + 1]  # fixed, disjoint seeds
    assert 0 <= s["wilson95"][0] <= s["success_rate"] <= s["wilson95"][1] <= 1
    assert s["requests"] >= 2 * 3 and s["getaction_ms_p50"] > 0 and s["underruns"] == 0  # lockstep: no underrun
    for r in rows:
        ep = read_episode(tmp_path / r["path"])  # every rollout is a readable episode (path as --out was given)
        assert ep.metadata["ticks"] == r["ticks"] == 20 or r["success"]
        assert ep.metadata["lockstep"] is True and "-eval-s" in ep.metadata["episode_id"]
        commands = ep.messages("/teleop/command")
        assert commands and {c.msg.source for c in commands} == {"policy"}
        assert ep.metadata["command_sources"] == ["policy"]  # (a build leaves rollouts out by it)
        assert len(ep.messages("/robot/applied")) == r["ticks"]
        assert not any(a.msg.stale for a in ep.messages("/robot/applied"))  # the policy answered every tick
    assert (out / "report.md").read_text().startswith("# Evaluation: lift")
    video = out / "videos" / f"{Path(rows[0]['path']).stem}.mp4"
    assert video.is_file() and video.stat().st_size > 2000
    cap = cv2.VideoCapture(str(video))  # VP9, which browsers play (mp4v, before, they did not)
    assert fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)) == "VP90" and cap.read()[0]


def test_eval_against_a_running_server_single_view_then_composed(tiny_checkpoint, tmp_path):
    from services.session.evaluate import PolicyServer, _checkpoint_facts

    recorded_size = _checkpoint_facts(str(tiny_checkpoint))["size"][0]
    with PolicyServer(str(tiny_checkpoint), tmp_path / "serve", None, 2, "five15", "lift") as server:
        for views in ("F", "F,FL"):
            out = tmp_path / f"eval-{views}"
            proc = viewscale(
                "eval", "--server", server.address, "--task", "lift", "--episodes", "1", "--views", views,
                "--max-ticks", "12", "--out", str(out),
            )  # fmt: skip
            assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
            s = json.loads((out / "report.json").read_text())["summary"]
            assert s["server"] == server.address and s["views"] == views.split(",") and s["requests"] >= 2
            assert s["size"] == recorded_size and "served by" in s["checkpoint"]  # defaults read from GetPolicyInfo
        proc = viewscale("eval", "--server", server.address, "--views", "XX", "--out", str(tmp_path / "bad"))
        assert proc.returncode == 2 and "no camera XX" in proc.stderr and "Traceback" not in proc.stderr
        assert server.proc.poll() is None  # the same server answered both evaluations
    proc = viewscale("eval", "--server", server.address, "--out", str(tmp_path / "gone"))
    assert proc.returncode == 2 and "no policy server" in proc.stderr, proc.stderr[-2000:]
    assert "Connection refused" in proc.stderr  # why, not only DEADLINE_EXCEEDED
    # and while it retried, what it waited for (before: 15 s of nothing)
    assert f"waiting for the policy server at {server.address} (up to 15 s)" in proc.stdout


def test_an_eval_stopped_while_it_waits_for_its_server_says_it_recorded_nothing(tmp_path):
    """(before: "services stopped; rollouts so far are in OUT", a folder it had not made)"""
    from services.core.bus import free_tcp_port

    closed = f"127.0.0.1:{free_tcp_port()}"
    cmd = [sys.executable, "-m", "services.cli", "eval", "--server", closed, "--out", str(tmp_path / "eval")]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env())
    assert proc.stdout.readline().startswith(f"waiting for the policy server at {closed}")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err.strip() == "interrupted (SIGTERM): services stopped; no rollouts recorded"
    assert not (tmp_path / "eval" / "rollouts").exists()


def test_an_interrupted_evaluation_reports_the_episodes_that_ended_and_stops_at_once(tmp_path):
    """Ctrl-C in the middle of an evaluation: the episodes that ran to their end are reported
    (before: no report at all, only their rollouts), marked as interrupted, the one cut short kept
    among the rollouts and not counted; and it ends within seconds (before: up to 41 s, the sim
    waiting out its lockstep command timeout)."""
    out = tmp_path / "eval"
    cmd = [sys.executable, "-m", "services.cli", "eval", "--expert", "--episodes", "20", "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env())
    for line in proc.stdout:
        if line.startswith("[2/20]"):
            break
    rollouts = out / "rollouts"
    deadline = time.monotonic() + 60
    while len(list(rollouts.glob("*.mcap.part"))) < 1:  # the third episode is under way
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.02)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rest, err = proc.communicate(timeout=60)
    took = time.monotonic() - t0
    assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
    assert took < 10, f"{took:.1f} s from Ctrl-C to its end"
    report = json.loads((out / "report.json").read_text())
    s, rows = report["summary"], report["episodes"]
    n = s["episodes"]
    assert s["interrupted"] == "SIGINT" and s["episodes_asked"] == 20 and 2 <= n < 20 and len(rows) == n
    assert len(list(rollouts.glob("*.mcap"))) == n + 1  # and the one cut short, kept
    assert f"successful in the {n} of 20 episodes that ran to their end" in rest
    assert f"**Interrupted (SIGINT) after {n} of 20 episodes**" in (out / "report.md").read_text()


def test_the_expert_row_goes_through_the_same_path(tmp_path):
    out = tmp_path / "expert"
    proc = viewscale(
        "eval", "--expert", "--task", "lift", "--episodes", "2", "--rig", "three15", "--size", "32", "--out", str(out)
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    s = json.loads((out / "report.json").read_text())["summary"]
    assert (s["successes"], s["episodes"]) == (2, 2) and s["expert"]
    assert len(list((out / "rollouts").glob("*.mcap"))) == 2


def test_a_second_evaluation_into_a_folder_in_use_is_refused(tmp_path):
    """(it unlinked the first one's policy statistics and recorded over its rollouts)"""
    from services.core.runtime import exclusive

    out = tmp_path / "eval"
    out.mkdir()
    with exclusive(out, "evaluation"):  # as the first evaluation holds it
        proc = viewscale("eval", "--expert", "--task", "lift", "--episodes", "1", "--out", str(out))
    assert proc.returncode == 2 and "starting sim" not in proc.stdout, proc.stderr
    assert proc.stderr.strip().startswith(f"error: {out} is in use by another evaluation (pid ")
    assert not (out / "logs").exists() and not (out / "rollouts").exists()


def test_eval_refuses_bad_input_with_one_line_before_starting_anything(tiny_checkpoint, tmp_path):
    """Each is one error line within a second, nothing written: before, most of the numbers were
    found out a few seconds in by the sim's or the session's config (a multi-line validation error),
    --video-camera once every episode had run (a traceback), --video -1 not at all."""
    ck = ["--checkpoint", str(tiny_checkpoint)]
    note = tmp_path / "note.txt"
    note.write_text("keep me\n")
    garbled = tmp_path / "garbled"  # policy.json cut short: a JSON traceback before
    shutil.copytree(resolve_checkpoint(tiny_checkpoint), garbled)
    (garbled / "policy.json").write_text("{")
    rigless = tmp_path / "rigless"  # a policy that names no one rig (as a running server names none)
    shutil.copytree(resolve_checkpoint(tiny_checkpoint), rigless)
    info = json.loads((rigless / "policy.json").read_text())
    (rigless / "policy.json").write_text(json.dumps({**info, "rigs": []}))
    cases = [
        (["--checkpoint", str(garbled)], f"{garbled / 'policy.json'} cannot be read (Expecting property name"),
        ([*ck, "--task", "pour"], "unknown task 'pour'"),
        ([*ck, "--episodes", "0"], "--episodes must be at least 1, got 0"),
        (
            [*ck, "--views", "F,XX"],
            "--views: rig three15 (the policy's rig: --rig renders another) has no camera XX; its cameras: F, FL, FR",
        ),
        (
            ["--checkpoint", str(rigless), "--views", "F,XX"],
            "--views: rig five15 (the default: --rig names the rig the sim renders) has no camera XX",
        ),
        ([*ck, "--views", "F,FL,F"], "--views names F more than once"),
        ([*ck, "--rig", "front"], "--views (default: the policy's views, F,FL,FR): rig front has no camera FL, FR"),
        ([*ck, "--rig", "nosuch"], "--rig: unknown rig 'nosuch'"),
        (
            [*ck, "--video", "1", "--video-camera", "ZZ"],
            "--video-camera ZZ: rig three15 has no such camera (F, FL, FR)",
        ),
        ([*ck, "--video", "-1"], "--video must be at least 0, got -1"),
        ([*ck, "--max-ticks", "0"], "--max-ticks must be at least 1, got 0"),
        ([*ck, "--seed", "-5"], "--seed must be at least 0, got -5"),
        ([*ck, "--size", "5"], "--size must be 16..4096, got 5"),
        ([*ck, "--workers", "-2"], "--workers must be at least 0, got -2"),
        ([*ck, "--expert"], "--expert evaluates the scripted expert: leave out --checkpoint, --server and --tls-ca"),
        ([*ck, "--tls-ca", str(note)], "--tls-ca is for a running server that serves TLS: give it with --server"),
        (["--expert", "--views", "F,XX"], "--views and --workers are the policy's: not with --expert"),
        (["--expert", "--workers", "2"], "--views and --workers are the policy's: not with --expert"),
        (["--checkpoint", str(tmp_path / "none")], f"checkpoint {tmp_path / 'none'} does not exist"),
        ([*ck, "--out", str(note)], f"--out {note}: not a directory"),
        # another command's output: a report and rollouts in among its files (before: exit 0, they were)
        ([*ck, "--out", str(tiny_checkpoint)], f"--out {tiny_checkpoint} is a training run: choose another folder"),
    ]
    procs = viewscale_each([["eval", "--out", str(tmp_path / "x"), *args] for args, _ in cases])
    for (args, says), proc in zip(cases, procs):
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and proc.stderr.startswith("error: ")
        assert says in proc.stderr, (args, proc.stderr)
        assert not (tmp_path / "x").exists() and note.read_text() == "keep me\n"


def test_the_evaluation_process_never_imports_torch():
    """It reads the checkpoint's JSON and drives the sim through the client; the model lives in the
    server's processes. (A bad argument is an error in about a second, not after torch's import.)"""
    code = "import sys, services.cli, services.session.evaluate; print('TORCH', 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "TORCH False" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def test_rerendered_episodes_read_and_build_like_collected_ones(sim_dataset, tmp_path):
    raw = sim_dataset.parent / "raw"
    out = tmp_path / "raw-three30"
    proc = viewscale("rerender", "--raw", str(raw), "--rig", "three30", "--out", str(out))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    sources = sorted(raw.glob("*.mcap"))
    made = sorted(out.glob("*.mcap"))
    assert len(made) == len(sources) == 2
    for src_path, new_path in zip(sources, made):
        src, new = read_episode(src_path), read_episode(new_path)
        assert new.metadata["rerendered_from"] == str(src_path.resolve()) and "rerendered_from" not in src.metadata
        assert src.cameras == ["F", "FL", "FR"] and new.cameras == ["F", "FL30", "FR30"]
        assert new.metadata["rig"] == "three30"
        assert new.metadata["ticks"] == src.metadata["ticks"] and new.metadata["success"] == src.metadata["success"]
        assert new.metadata["command_sources"] == src.metadata["command_sources"] == ["scripted"]
        s_states, n_states = src.messages("/robot/state"), new.messages("/robot/state")
        assert [r.publish_time for r in n_states] == [r.publish_time for r in s_states]
        assert np.abs(np.array([r.msg.eef_pos for r in n_states]) - [r.msg.eef_pos for r in s_states]).max() < 1e-6
        assert [r.msg.action for r in new.messages("/robot/applied")] == [
            r.msg.action for r in src.messages("/robot/applied")
        ]
        for cam in new.cameras:
            assert len(new.messages(f"/camera/{cam}/image")) == len(n_states)
        # same scene, same tick, FL 30 degrees from F instead of 15: the pictures differ
        a = decode_jpeg(src.messages("/camera/FL/image")[5].msg.data).astype(int)
        b = decode_jpeg(new.messages("/camera/FL30/image")[5].msg.data).astype(int)
        assert a.shape == b.shape and np.abs(a - b).mean() > 5
    build_dataset(out, tmp_path / "ds", BuildParams(views=("F", "FL30", "FR30"), image_size=(32, 32)))
    assert DatasetStore(tmp_path / "ds").summary["pseudo_demos"] == 6
    # run again (as over a folder that gained episodes): what was rendered is kept, not an error
    # (before: each was 'SKIPPED: ... already exists', exit 1)
    mtimes = {p: p.stat().st_mtime_ns for p in made}
    again = viewscale("rerender", "--raw", str(raw), "--rig", "three30", "--out", str(out))
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert f"re-rendered 0 of 2 episodes through three30 (2 re-rendered before, kept) -> {out}" in again.stdout
    assert {p: p.stat().st_mtime_ns for p in made} == mtimes  # not written again
    other = viewscale("rerender", "--raw", str(raw), "--rig", "three30", "--out", str(out), "--size", "40")
    assert other.returncode == 1 and "re-rendered from another file or at another size" in other.stdout


def test_rerender_refuses_bad_arguments_before_writing_anything(sim_dataset, tmp_path, capsys):
    from services.cli import main

    raw = sim_dataset.parent / "raw"
    before = sorted(p.name for p in raw.iterdir())
    (tmp_path / "a-file").write_text("")
    cases = [
        # its output in the --raw folder: before, a second run re-rendered the re-renders (-three30-three30)
        (["--out", str(raw)], f"--out {raw} is a --raw folder"),
        (["--out", str(raw) + "/"], "is a --raw folder"),
        # inside it: read back the same way (before: taken)
        (
            ["--out", str(raw / "three30")],
            f"--out {raw / 'three30'} is inside the --raw folder {raw}: the re-rendered episodes would be read back "
            f"as recordings of {raw} (re-rendered again by the next rerender, built along with them); write them "
            f"beside it, e.g. --out {raw.resolve().parent / 'raw-three30'}",
        ),
        (["--out", str(tmp_path / "rr"), "--size", "0"], "--size must be 16..4096 px, got 0"),  # was a traceback
        (["--out", str(tmp_path / "a-file")], f"--out {tmp_path / 'a-file'}: not a directory"),
        (["--out", str(sim_dataset)], f"--out {sim_dataset} is a dataset: choose another folder"),
    ]
    for extra, says in cases:
        assert main(["rerender", "--raw", str(raw), "--rig", "three30", *extra]) == 2, extra
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err, (extra, err)
    assert sorted(p.name for p in raw.iterdir()) == before and not (tmp_path / "rr").exists()
    # a --raw with no episodes: it made --out first and left it there, empty
    assert main(["rerender", "--raw", str(tmp_path / "none"), "--rig", "three30", "--out", str(tmp_path / "rr")]) == 2
    assert "raw data path" in capsys.readouterr().err and not (tmp_path / "rr").exists()
    # episodes that are all skipped: nothing written, and no empty --out left (it was, before)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.mcap").write_bytes(b"not an mcap")
    assert main(["rerender", "--raw", str(tmp_path / "junk"), "--rig", "three30", "--out", str(tmp_path / "rr")]) == 1
    out = capsys.readouterr().out
    assert "re-rendered none of 1 episodes through three30: nothing written to" in out and "skipped a.mcap" in out
    assert not (tmp_path / "rr").exists()


def test_a_rerender_stopped_or_killed_mid_episode_is_finished_by_the_same_command(sim_dataset, tmp_path):
    """SIGTERM (a scheduler, `kill`) in the middle of an episode: before, the process died on the
    spot and left the episode's `.part`, and the same command then failed on it with `error: [Errno
    17] File exists`. Now a stop ends it with one line and no `.part`; the `.part` a SIGKILL leaves
    (nothing can clean up after that) is rendered again by the next run; and a second rerender on
    the same folder at once is refused, since it would render the same episodes beside the first."""
    raw = sim_dataset.parent / "raw"
    out = tmp_path / "rr"
    cmd = [sys.executable, "-m", "services.cli", "rerender", "--raw", str(raw), "--rig", "three30", "--out", str(out)]
    cmd += ["--size", "160"]
    for sig in (signal.SIGTERM, signal.SIGKILL):
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env()
        )
        deadline = time.monotonic() + 60
        while not list(out.glob("*.mcap.part")):  # an episode is being rendered
            assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
            time.sleep(0.01)
        if sig == signal.SIGTERM:
            proc.send_signal(signal.SIGSTOP)  # (held in that episode while the second one starts)
            busy = viewscale(*cmd[3:])  # the same command beside it, on the same folder
            proc.send_signal(signal.SIGCONT)
            assert busy.returncode == 2 and f"{out} is in use by another rerender (pid {proc.pid}" in busy.stderr
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        if sig == signal.SIGTERM:
            assert proc.returncode == 130 and "Traceback" not in err, err[-2000:]
            assert "interrupted (SIGTERM): " in err and "run the same command to render the rest" in err
            assert not list(out.glob("*.part"))
        else:
            assert len(list(out.glob("*.mcap.part"))) == 1  # what a killed run leaves
            again = viewscale(*cmd[3:])
            assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
            assert "left by a run that was stopped" in again.stderr
    assert not list(out.glob("*.part")) and len(list(out.glob("*.mcap"))) == 2
    for path in out.glob("*.mcap"):
        ep = read_episode(path)
        assert ep.metadata["ticks"] == len(ep.messages("/robot/state")) > 0
