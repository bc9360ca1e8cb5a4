"""`viewscale collect` as a user runs it: real services as subprocesses, real MCAP files."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_process import user_env, viewscale_each

from services.core.rig import Camera, load_rig
from services.recorder.reader import read_episode

ROOT = Path(__file__).resolve().parents[2]


def run_collect(out: Path, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "services.cli", "collect", "--out", str(out), *args]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=user_env())


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("raw")
    proc = run_collect(out, "--task", "lift", "--episodes", "2", "--rig", "five15", "--fast")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out, proc.stdout


def test_progress_and_summary_are_shown(recorded):
    out, stdout = recorded
    assert "[1/2] lift seed" in stdout and "[2/2] lift seed" in stdout
    assert "recorded 2 episodes" in stdout
    assert (out / "logs" / "sim.log").exists()


def test_every_camera_has_one_frame_per_tick_with_monotonic_times(recorded):
    out, _ = recorded
    files = sorted(out.glob("*.mcap"))
    assert len(files) == 2
    for path in files:
        ep = read_episode(path)
        ticks = ep.metadata["ticks"]
        assert ep.metadata["success"] is True and ep.metadata["rig"] == "five15"
        assert ep.metadata["lockstep"] is True and ep.flags == []  # --fast: lockstep, never rate-flagged
        assert ep.metadata["command_sources"] == ["scripted"]  # the expert drove it
        assert ticks > 10
        states = ep.messages("/robot/state")
        applied = ep.messages("/robot/applied")
        assert [r.msg.tick for r in states] == list(range(ticks))
        assert [r.msg.tick for r in applied] == list(range(ticks))
        assert ep.cameras == sorted(load_rig("five15").names)
        for name in ep.cameras:
            frames = ep.messages(f"/camera/{name}/image")
            assert len(frames) == ticks, name
            # sim frames share the capture time of their tick's state
            assert [r.publish_time for r in frames] == [r.publish_time for r in states]
            assert ep.metadata["frames"][name] == ticks
            assert ep.messages(f"/camera/{name}/calibration") and ep.messages(f"/camera/{name}/pose")
        for topic, records in ep.topics.items():
            pub = [r.publish_time for r in records]
            log = [r.log_time for r in records]
            assert pub == sorted(pub), topic
            assert log == sorted(log), topic
            assert [r.sequence for r in records] == sorted(set(r.sequence for r in records)), topic
        assert sum(ep.metadata["drops"].values()) == 0
        assert not any(r.msg.stale for r in applied)


def test_recorded_calibration_is_the_rig(recorded):
    out, _ = recorded
    ep = read_episode(sorted(out.glob("*.mcap"))[0])
    rig = load_rig("five15")
    for name, cam in rig.cameras.items():
        calib = ep.messages(f"/camera/{name}/calibration")[0].msg
        pose = ep.messages(f"/camera/{name}/pose")[0].msg
        back, K = Camera.from_msgs(calib, pose)
        assert np.allclose(back.R_wc, cam.R_wc, atol=1e-9) and np.allclose(back.position, cam.position)
        assert np.allclose(K, cam.K(84, 84))


def test_open_loop_replay_reproduces_the_eef_trajectory(recorded):
    """Applied actions from the recording, replayed in a fresh world from the same seed."""
    from sim.world import SimWorld

    out, _ = recorded
    path = sorted(out.glob("*.mcap"))[-1]  # the second episode: the sim had run one before it
    ep = read_episode(path)
    states = [r.msg for r in ep.messages("/robot/state")]
    actions = [r.msg.action for r in ep.messages("/robot/applied")]
    with SimWorld(ep.metadata["task"], load_rig("front")) as world:
        world.reset(int(ep.metadata["seed"]))
        replayed = []
        for _state, action in zip(states, actions):
            replayed.append(world.robot().eef_pos.copy())
            world.step(np.array(action.dp), np.array(action.drot), action.gripper)
        assert world.success()
    recorded_pos = np.array([s.eef_pos for s in states])
    assert np.abs(np.array(replayed) - recorded_pos).max() < 1e-6


def test_bad_arguments_fail_fast_with_one_line(tmp_path):
    proc = run_collect(tmp_path, "--rig", "six15", timeout=60)
    assert proc.returncode == 2
    assert "error: unknown rig 'six15'" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_collect(tmp_path, "--task", "stack", timeout=60)
    assert proc.returncode == 2 and "unknown task 'stack'" in proc.stderr
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    cases = [
        (["--episodes", "-1"], "--episodes must be at least 1"),
        (["--episodes", "0"], "--episodes must be at least 1"),
        (["--size", "0"], "--size must be 16..4096"),
        (["--set", "nonexistent.field=1"], "no service 'nonexistent'"),
        (["--set", "sim.nonexistent=1"], "nonexistent: no such setting"),
        (["--set", "recorder.queue_size=0"], "queue_size"),
        (["--seed", "99990"], "--seed: collection seeds stay below 100000"),
        # (before: the sim's ValueError traceback 2 s in, or a hang for 1e-9)
        (["--hz", "1000"], "--hz must be 1..500 (the sim's physics steps every 2 ms), got 1000"),
        (["--hz", "inf"], "--hz must be 1..500"),
        (["--hz", "1e-9"], "--hz must be 1..500"),
        (["--set", "sim.control_hz=600"], "control_hz: Input should be less than or equal to 500"),
    ]
    procs = viewscale_each([["collect", "--out", str(tmp_path / "out"), *args] for args, _ in cases], timeout=60)
    for (args, text), proc in zip(cases, procs):
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and text in lines[0], args
        assert "starting sim" not in proc.stdout  # refused before any service starts
        assert not (tmp_path / "out").exists()
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli", "collect", "--out", str(blocker / "sub")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    says = f"error: --out {blocker / 'sub'}: not a directory ({blocker} is a file)"
    assert proc.returncode == 2 and proc.stderr.strip() == says
    # another command's output: the episodes would go in among its files (before: exit 0, they did)
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "manifest.json").write_text("{}")
    proc = run_collect(ds, timeout=60)
    assert (
        proc.returncode == 2
        and proc.stderr.strip() == f"error: --out {ds} is a dataset: choose another folder (a new one is made)"
    )
    assert sorted(p.name for p in ds.iterdir()) == ["manifest.json"]


def test_a_sim_that_cannot_render_fails_its_start_saying_why_and_what_to_do(tmp_path):
    """No OpenGL to render with (here GLFW with no display, as on a headless machine without EGL):
    the sim renders a frame before it says ready, and exits with one error line naming the backend
    and the ones that render headless. Before, it said ready, its first tick raised, and the session
    reported only `no reply on vs/sim/control within 20.0s (is the service running?)`."""
    env = {k: v for k, v in user_env(MUJOCO_GL="glx").items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    cmd = [sys.executable, "-m", "services.cli", "collect", "--out", str(tmp_path), "--rig", "front", "--fast"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode != 0, proc.stdout
    assert "sim exited with code 2 before it was ready" in proc.stderr, proc.stderr[-3000:]
    assert "error: cannot render with MUJOCO_GL=glx: " in proc.stderr and "MUJOCO_GL=egl (libEGL" in proc.stderr
    assert "Traceback" not in proc.stderr and not list(tmp_path.glob("*.mcap*"))


def test_sigterm_mid_session_keeps_the_partial_episode_and_stops_every_service(tmp_path):
    import signal

    import psutil

    # Lockstep, so that a loaded machine cannot make the recorded episodes stale: what is under
    # test is the signal, not real-time pacing.
    cmd = [
        sys.executable,
        "-m",
        "services.cli",
        "collect",
        "--task",
        "can",
        "--episodes",
        "20",
        "--rig",
        "three15",
        "--out",
        str(tmp_path),
        "--fast",
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    children: list[psutil.Process] = []
    for line in proc.stdout:  # wait until the first episode is recorded: the second is under way
        children = children or psutil.Process(proc.pid).children()
        if line.startswith("[1/20]"):
            break
    else:
        raise AssertionError(f"no episode recorded: {proc.stderr.read()}")
    assert {c.cmdline()[2] for c in children} >= {"sim", "services.teleop", "services.recorder"}
    log = tmp_path / "logs" / "recorder.log"
    deadline = time.monotonic() + 60
    while log.read_text().count(" started: ") < 2:  # the second episode is being recorded
        assert time.monotonic() < deadline, log.read_text()[-2000:]
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted (SIGTERM)" in err and "Traceback" not in err, err
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"services left running: {[c.cmdline() for c in alive]}"
    assert not list(tmp_path.glob("*.part")), "an episode was left unclosed"
    episodes = [read_episode(f) for f in sorted(tmp_path.glob("*.mcap"))]
    assert f"services stopped; {len(episodes)} episodes in {tmp_path}" in err, err
    done = [e for e in episodes if e.metadata["success"]]
    cut = [e for e in episodes if not e.metadata["success"]]
    assert len(done) >= 1 and all(not e.flags for e in done)
    # the episode under way when the signal came is kept, closed and flagged, never silently lost
    assert len(cut) == 1 and cut[0].flags, [(e.path.name, e.metadata["success"], e.flags) for e in episodes]
    assert cut[0].flags[0].startswith("interrupted: "), cut[0].flags  # says why, whatever the pacing


def _start_collect(tmp_path):
    import psutil

    cmd = [
        sys.executable,
        "-m",
        "services.cli",
        "collect",
        "--task",
        "can",
        "--episodes",
        "20",
        "--rig",
        "three15",
        "--out",
        str(tmp_path),
        "--fast",
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("[1/20]"):
            break
    else:
        raise AssertionError(f"no episode recorded: {proc.stderr.read()}")
    children = psutil.Process(proc.pid).children()
    log = tmp_path / "logs" / "recorder.log"
    deadline = time.monotonic() + 60
    while log.read_text().count(" started: ") < 2:  # the second episode is being recorded
        assert time.monotonic() < deadline, log.read_text()[-2000:]
        time.sleep(0.05)
    return proc, children


def _log_tails(tmp_path, procs) -> str:
    """The last lines of each of ``procs``' service logs: what a failure needs to be understood."""
    out = []
    for p in procs:
        name = p.cmdline()[2].removeprefix("services.")
        log = tmp_path / "logs" / f"{name}.log"
        out.append(f"--- {log}:\n" + ("\n".join(log.read_text().splitlines()[-15:]) if log.exists() else "(none)"))
    return "\n".join(out)


def test_killing_collect_with_sigkill_takes_every_service_with_it_and_closes_the_episode(tmp_path):
    import psutil

    proc, children = _start_collect(tmp_path)
    assert {c.cmdline()[2] for c in children} >= {"sim", "services.teleop", "services.recorder"}
    proc.kill()  # kill -9: no handler runs in the parent
    proc.wait(timeout=30)
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"services left running: {[c.cmdline() for c in alive]}\n{_log_tails(tmp_path, alive)}"
    assert not list(tmp_path.glob("*.part")), "an episode was left unclosed"  # the recorder closed it on SIGTERM
    cut = [read_episode(f) for f in tmp_path.glob("*.mcap") if not read_episode(f).metadata["success"]]
    assert len(cut) == 1 and any(f.startswith("interrupted") for f in cut[0].flags)


def test_sighup_to_collect_stops_like_sigterm(tmp_path):
    import psutil

    proc, children = _start_collect(tmp_path)
    proc.send_signal(signal.SIGHUP)  # the terminal was closed
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted (SIGHUP)" in err, err
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive and not list(tmp_path.glob("*.part"))


def test_a_service_that_exits_mid_session_is_named_with_its_last_log_lines(tmp_path):
    """The sim stopped mid-episode (here SIGTERM: it closes its bus, a while after its queryable is
    gone): collect names it, its exit code and its log's last lines, and keeps the cut episode.
    Before, the sim was still exiting when collect looked, and it said only `service(s) lost
    mid-episode: sim`."""
    import psutil

    proc, children = _start_collect(tmp_path)
    sim = next(c for c in children if c.cmdline()[2] == "sim")
    sim.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, err
    assert "error: sim exited with code 0; last log lines:" in err and "received SIGTERM" in err, err[-3000:]
    assert "kept as failed" in out  # the cut episode, as before
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive and not list(tmp_path.glob("*.part"))


def test_collecting_again_into_a_folder_continues_after_the_seeds_it_holds(recorded, tmp_path):
    """A seed is a scene, and the scripted expert is deterministic: before, a second `collect` into
    the same folder started at seed 0 again and recorded the same episodes a second time (the
    dataset then held duplicates, and a held-out episode could be a training episode's twin)."""
    import shutil

    first, _ = recorded  # lift seeds 0 and 1
    out = tmp_path / "raw"
    out.mkdir()
    for f in first.glob("*.mcap"):
        shutil.copy(f, out)
    proc = run_collect(out, "--task", "lift", "--episodes", "1", "--rig", "five15", "--fast")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert f"{out} holds 2 lift episodes (seeds 0..1): continuing from seed 2" in proc.stdout
    assert "[1/1] lift seed 2: success" in proc.stdout
    seeds = sorted(read_episode(f, topics=()).metadata["seed"] for f in out.glob("*.mcap"))
    assert seeds == [0, 1, 2]
    # a seed asked for is taken, and what it repeats is said
    again = run_collect(out, "--task", "lift", "--episodes", "1", "--rig", "five15", "--fast", "--seed", "1")
    assert again.returncode == 0 and "[1/1] lift seed 1: success" in again.stdout
    assert f"note: {out} holds lift episodes of seeds 0..2: from --seed 1, the seeds recorded there" in again.stdout
