"""The training service on a real Zenoh session: a TRAIN query and a job file each train the
tiny policy on a recorded sim dataset while progress arrives on trainer/progress; and
``python -m services.trainer`` starts, announces itself and stops on SIGTERM."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from signals import signal_another_thread

from services.core.runtime import exclusive
from services.core.topics import TRAIN_PROGRESS, TRAIN_REQUEST
from services.pb import trainer_pb2 as S
from services.policy.checkpoint import load_policy
from services.trainer.config import TrainerServiceConfig
from services.trainer.service import SERVICE_NAME, TrainerService

torch.set_num_threads(1)

JOB_SETTINGS = ["num_workers=0", "batch_size=4", "log_every=1", "val_every=0", "checkpoint_every=0"]


def _progress(bus) -> queue.Queue[S.TrainProgress]:
    q: queue.Queue = queue.Queue()
    bus.subscribe(TRAIN_PROGRESS, lambda msg, rx: q.put(msg))
    return q


def _until(q: queue.Queue, job_id: str, states: set[int], timeout: float = 120.0) -> list:
    """Progress messages of ``job_id`` up to the first in ``states``."""
    seen, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            msg = q.get(timeout=0.5)
        except queue.Empty:
            continue
        if msg.job_id != job_id:
            continue
        seen.append(msg)
        if msg.state in states:
            return seen
    raise AssertionError(f"job {job_id} did not reach {states} in {timeout:.0f}s: {[m.state for m in seen]}")


def test_query_trains_and_publishes_progress(sim_dataset, tmp_path, make_bus):
    cfg = TrainerServiceConfig(bus=make_bus().cfg, progress_every_s=0.0, defaults=JOB_SETTINGS)
    with make_bus() as service_bus, TrainerService(cfg, service_bus):
        client = make_bus()
        client.wait_alive([SERVICE_NAME], timeout=10)
        progress = _progress(client)
        req = S.TrainRequest(
            command=S.TRAIN_COMMAND_TRAIN,
            job_id="lift-tiny",
            data=str(sim_dataset),
            out=str(tmp_path / "run"),
            preset="tiny",
            steps=3,
        )
        reply = S.TrainReply.FromString(client.query(TRAIN_REQUEST, req.SerializeToString(), timeout=10))
        assert reply.ok and reply.job_id == "lift-tiny"
        msgs = _until(progress, "lift-tiny", {S.TRAIN_STATE_DONE, S.TRAIN_STATE_FAILED})
        assert msgs[-1].state == S.TRAIN_STATE_DONE, msgs[-1].error
        running = [m for m in msgs if m.state == S.TRAIN_STATE_RUNNING and m.step > 0]
        assert [m.step for m in running] == [1, 2, 3]
        assert all(m.steps == 3 and m.loss > 0 and m.it_s > 0 and m.eta_s >= 0 for m in running)
        assert running[-1].lr > running[0].lr  # warming up
        assert msgs[-1].step == 3 and Path(msgs[-1].checkpoint).is_dir()
        assert load_policy(tmp_path / "run").info["step"] == 3

        # a bad request is answered with the reason, and nothing is queued
        bad = S.TrainRequest(data=str(sim_dataset), out=str(tmp_path / "bad"), overrides=["optim.lr=fast"])
        reply = S.TrainReply.FromString(client.query(TRAIN_REQUEST, bad.SerializeToString(), timeout=10))
        assert not reply.ok and "lr" in reply.error
        # a wrong data folder is refused in the reply (before: queued, then failed when its turn came)
        bad = S.TrainRequest(data=str(tmp_path / "nowhere"), out=str(tmp_path / "bad"))
        reply = S.TrainReply.FromString(client.query(TRAIN_REQUEST, bad.SerializeToString(), timeout=10))
        assert not reply.ok and reply.error == f"dataset {tmp_path / 'nowhere'} does not exist"
        status = S.TrainReply.FromString(
            client.query(TRAIN_REQUEST, S.TrainRequest(command=S.TRAIN_COMMAND_STATUS).SerializeToString(), timeout=10)
        )
        assert status.ok and status.running == "" and list(status.queued) == []

        # a run another training holds (`viewscale train` in a terminal: its lock) is not written into
        # (before: both trained in it)
        log_before = (tmp_path / "run" / "log.jsonl").read_bytes()
        with exclusive(tmp_path / "run", "training"):
            req = S.TrainRequest(job_id="clash", data=str(sim_dataset), out=str(tmp_path / "run"), steps=5)
            assert S.TrainReply.FromString(client.query(TRAIN_REQUEST, req.SerializeToString(), timeout=10)).ok
            msgs = _until(progress, "clash", {S.TRAIN_STATE_DONE, S.TRAIN_STATE_FAILED})
        assert msgs[-1].state == S.TRAIN_STATE_FAILED
        assert msgs[-1].error.startswith(f"{tmp_path / 'run'} is in use by another training (pid {os.getpid()}")
        assert (tmp_path / "run" / "log.jsonl").read_bytes() == log_before
        assert load_policy(tmp_path / "run").info["step"] == 3


def test_job_file_is_taken_trained_and_marked(sim_dataset, tmp_path, make_bus, caplog):
    jobs = tmp_path / "jobs"
    jobs.mkdir()
    cfg = TrainerServiceConfig(bus=make_bus().cfg, jobs_dir=str(jobs), poll_s=0.1, defaults=JOB_SETTINGS)
    with make_bus() as service_bus, TrainerService(cfg, service_bus):
        client = make_bus()
        client.wait_alive([SERVICE_NAME], timeout=10)
        progress = _progress(client)
        # a file being written, with a pause mid-way: taken whole, once it stopped changing for
        # settle_s (before: taken at the next scan, half-written: 'not valid YAML')
        with open(jobs / "slow.yaml", "w") as f:
            f.write("data: /nonexistent\nsteps: [1,\n")
            f.flush()
            time.sleep(0.5)
            f.write(" 2]\nsetting: that does not exist\n")
        (jobs / "bad.yaml").write_text("data: /nonexistent\nout: x\nsteps: nope\n")
        (jobs / "list.json").write_text("[1, 2]")
        (jobs / "broken.yaml").write_text("steps: [oops\n")
        (jobs / "after-collect.yaml").write_text(
            f"data: {sim_dataset}\nout: {tmp_path / 'run'}\npreset: tiny\nsteps: 2\nviews: [F]\n"
        )
        msgs = _until(progress, "after-collect", {S.TRAIN_STATE_DONE, S.TRAIN_STATE_FAILED})
        assert msgs[-1].state == S.TRAIN_STATE_DONE, msgs[-1].error
        deadline = time.monotonic() + 10
        while not (jobs / "after-collect.yaml.done").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
    assert (jobs / "after-collect.yaml.done").exists() and not (jobs / "after-collect.yaml").exists()
    assert '"outcome": "done"' in (jobs / "after-collect.result.json").read_text()
    assert (jobs / "bad.yaml.failed").exists()
    assert "steps" in (jobs / "bad.result.json").read_text()
    slow = json.loads((jobs / "slow.result.json").read_text())["error"]
    assert "setting: no such setting" in slow and "not valid YAML" not in slow, slow
    listed = json.loads((jobs / "list.result.json").read_text())["error"]
    assert listed == f"job file {jobs / 'list.json'} must hold an object at the top level"
    # each refusal is in the service's log, naming the file as it was dropped (before: not logged,
    # and a YAML error named '<name>.running')
    refused = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    broken = json.loads((jobs / "broken.result.json").read_text())["error"]
    assert broken.startswith(f"job file {jobs / 'broken.yaml'} is not valid YAML: "), broken
    for name in ("slow.yaml", "bad.yaml", "list.json", "broken.yaml"):
        assert any(m.startswith(f"job file {jobs / name}") and f"(now {name}.failed)" in m for m in refused), refused
    assert not any(".running" in m for m in refused)
    assert load_policy(tmp_path / "run").info["views"] == ["F"]


def test_cancel_stops_a_running_job_at_a_checkpoint(sim_dataset, tmp_path, make_bus):
    cfg = TrainerServiceConfig(bus=make_bus().cfg, progress_every_s=0.0, defaults=JOB_SETTINGS)
    with make_bus() as service_bus, TrainerService(cfg, service_bus):
        client = make_bus()
        client.wait_alive([SERVICE_NAME], timeout=10)
        progress = _progress(client)
        req = S.TrainRequest(job_id="long", data=str(sim_dataset), out=str(tmp_path / "run"), steps=100000)
        assert S.TrainReply.FromString(client.query(TRAIN_REQUEST, req.SerializeToString(), timeout=10)).ok
        _until(progress, "long", {S.TRAIN_STATE_RUNNING})
        while progress.get(timeout=60).step < 2:  # a couple of steps in
            pass
        cancel = S.TrainRequest(command=S.TRAIN_COMMAND_CANCEL, job_id="long")
        assert S.TrainReply.FromString(client.query(TRAIN_REQUEST, cancel.SerializeToString(), timeout=10)).ok
        msgs = _until(progress, "long", {S.TRAIN_STATE_STOPPED, S.TRAIN_STATE_DONE, S.TRAIN_STATE_FAILED})
        assert msgs[-1].state == S.TRAIN_STATE_STOPPED
        assert 2 <= msgs[-1].step < 100000 and Path(msgs[-1].checkpoint).is_dir()


@pytest.mark.parametrize("thread", ["main", "another"])
def test_module_starts_announces_and_stops_on_sigterm(zenoh_endpoint, make_bus, tmp_path, thread):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [
        sys.executable,
        "-m",
        "services.trainer",
        "--set",
        "bus.mode=client",
        "--set",
        f"bus.connect=[{zenoh_endpoint}]",
        "--set",
        f"jobs_dir={tmp_path / 'jobs'}",
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=Path(__file__).resolve().parents[2]
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith("ready trainer vs/trainer/request"), proc.stderr.read()
        make_bus().wait_alive([SERVICE_NAME], timeout=10)
        if thread == "main":
            proc.send_signal(signal.SIGTERM)
        else:  # as the kernel may deliver it: to one of zenoh's threads
            signal_another_thread(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
