"""`viewscale serve` and `viewscale worker` refuse what they cannot run with one error line and an
exit code, never a traceback: a device this machine lacks, unreadable weights, workers that never
come up, an address they cannot listen on. Real processes, a tiny real checkpoint (and a copy of it
with its weights cut short)."""

from __future__ import annotations

import json
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from cli_process import user_env, viewscale, viewscale_each
from policy_processes import start_server, start_worker, stop
from polling import wait_for

from services.core.bus import free_tcp_port
from services.policy.checkpoint import (
    MODEL_FILE,
    CheckpointError,
    check_weights,
    inference_device,
    load_policy,
    read_weights,
)

ROOT = Path(__file__).resolve().parents[2]
NO_CUDA = not torch.cuda.is_available()


def no_traceback(stderr: str) -> None:
    for junk in ("Traceback", "Exception ignored", "never awaited"):
        assert junk not in stderr, stderr


@pytest.fixture(scope="module")
def cut_checkpoint(tiny_checkpoint, tmp_path_factory) -> Path:
    """A copy of the tiny run whose model.safetensors lost all but its first 100 bytes (a copy cut short)."""
    run = tmp_path_factory.mktemp("cut") / "run"
    shutil.copytree(tiny_checkpoint, run)
    [weights] = run.glob(f"checkpoints/*/{MODEL_FILE}")
    weights.write_bytes(weights.read_bytes()[:100])
    return run


@pytest.fixture(scope="module")
def unfitting_checkpoint(tiny_checkpoint, tmp_path_factory) -> Path:
    """A copy of the tiny run whose weights file is whole but lacks one of the model's tensors: it
    reads, and no model loads it."""
    from safetensors.torch import load_file, save_file

    run = tmp_path_factory.mktemp("unfitting") / "run"
    shutil.copytree(tiny_checkpoint, run)
    [weights] = run.glob(f"checkpoints/*/{MODEL_FILE}")
    state = load_file(str(weights))
    del state[sorted(state)[0]]
    save_file(state, str(weights))
    return run


def test_inference_device_names_what_is_wrong():
    assert inference_device("cpu") == torch.device("cpu")
    assert inference_device(torch.device("cpu"), "bf16") == torch.device("cpu")
    for bad in ("tpu", "cuda:x", "", "gpu0"):
        with pytest.raises(ValueError, match="not a device name"):
            inference_device(bad)
    if NO_CUDA:
        for name in ("cuda", "cuda:1"):
            with pytest.raises(ValueError, match=f"device {name}: no CUDA device is visible"):
                inference_device(name)
    else:
        n = torch.cuda.device_count()
        with pytest.raises(ValueError, match=f"this machine has {n} CUDA device"):
            inference_device(f"cuda:{n}")


def test_weights_cut_short_are_a_checkpoint_error_naming_the_file(tiny_checkpoint, cut_checkpoint, tmp_path):
    [weights] = cut_checkpoint.glob(f"checkpoints/*/{MODEL_FILE}")
    with pytest.raises(CheckpointError, match=f"{weights} cannot be read"):
        read_weights(weights)
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_policy(cut_checkpoint)
    with pytest.raises(CheckpointError, match="cannot be read"):
        read_weights(weights.with_name("missing.safetensors"))
    [good] = tiny_checkpoint.glob(f"checkpoints/*/{MODEL_FILE}")
    assert read_weights(good)  # the original still reads: the copy was cut, not the source
    # the check a server makes without reading the tensors: a cut in the header or in the tensors
    check_weights(tiny_checkpoint)
    with pytest.raises(CheckpointError, match=f"{weights} cannot be read"):
        check_weights(cut_checkpoint)
    late = tmp_path / "run"
    shutil.copytree(tiny_checkpoint, late)
    [file] = late.glob(f"checkpoints/*/{MODEL_FILE}")
    file.write_bytes(file.read_bytes()[:-10])  # the header whole, the last tensor short
    with pytest.raises(CheckpointError, match="cannot be read .*not fully covered"):
        check_weights(late)


@pytest.mark.parametrize(
    "command, device", [("worker", "tpu"), ("serve", "cuda" if NO_CUDA else f"cuda:{torch.cuda.device_count()}")]
)
def test_a_device_this_machine_lacks_is_one_line_before_listening(tiny_checkpoint, command, device):
    proc = viewscale(command, "--checkpoint", str(tiny_checkpoint), "--listen", "127.0.0.1:0", "--device", device)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]  # one line
    assert proc.stderr.startswith(f"error: device {device!r}" if device == "tpu" else f"error: device {device}:")
    assert "listening" not in proc.stdout  # refused before it bound a port


@pytest.mark.parametrize(
    "command", [["worker"], ["serve", "--in-process"], ["serve", "--workers", "1", "--set", "worker_ready_s=10"]]
)
def test_weights_cut_short_stop_the_process_with_one_error_line(cut_checkpoint, command):
    proc = viewscale(*command, "--checkpoint", str(cut_checkpoint), "--listen", "127.0.0.1:0")
    assert proc.returncode == 1, proc.stderr
    no_traceback(proc.stderr)
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and f"{MODEL_FILE} cannot be read" in errors[0], proc.stderr
    # a server with workers says so before it starts them (before: they were started, failed to
    # load the weights and were started again until worker_ready_s ran out, 120 s by default)
    if command[0] == "serve":
        assert "local worker" not in proc.stderr and "listening" not in proc.stdout, proc.stderr


def _garble(policy_json: Path) -> None:
    policy_json.write_text("{")  # a copy cut short


def _edit_model(policy_json: Path) -> None:
    info = json.loads(policy_json.read_text())
    info["model"]["n_groups"] = 0  # edited by hand, or a version whose bounds differ
    policy_json.write_text(json.dumps(info))


@pytest.mark.parametrize(
    ("damage", "says"),
    [
        (_garble, "policy.json cannot be read (Expecting property name"),
        (Path.unlink, "policy.json cannot be read ([Errno 2] No such file or directory"),
        (_edit_model, "policy.json holds a model config this version cannot build (n_groups: Input should be"),
    ],
)
def test_a_damaged_policy_json_is_one_line_naming_it(tiny_checkpoint, tmp_path, damage, says):
    """(before: the server's error said only the JSON parser's words, and a model config that this
    version's bounds refuse was pydantic's traceback)"""
    run = tmp_path / "run"
    shutil.copytree(tiny_checkpoint, run)
    [policy_json] = run.glob("checkpoints/*/policy.json")
    damage(policy_json)
    # the checkpoint folder itself (a run whose latest lacks its policy.json says the latest is incomplete)
    listen = ["--checkpoint", str(policy_json.parent), "--listen", "127.0.0.1:0"]
    for proc in viewscale_each([["worker", *listen], ["serve", "--workers", "1", *listen]]):
        err = proc.stderr.strip()
        assert proc.returncode == 2 and err.startswith(f"error: {policy_json.parent}/{says}"), err
        assert len(err.splitlines()) == 1 and "local worker" not in err, err


def test_local_workers_that_cannot_load_the_model_end_the_server_with_their_error(unfitting_checkpoint):
    """Weights that read but fit no model: each local worker exits while it loads them. Without
    --log-dir the workers' stderr still reaches the server, whose one error line quotes why, at
    once: restarted, they would fail the same way (before: they were restarted until
    worker_ready_s ran out, 120 s by default, and the error said only that no worker was ready)."""
    start = time.monotonic()
    proc = viewscale(
        "serve", "--checkpoint", str(unfitting_checkpoint), "--listen", "127.0.0.1:0", "--workers", "2"
    )  # fmt: skip
    took = time.monotonic() - start
    assert proc.returncode == 1, proc.stderr
    no_traceback(proc.stderr)
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1, proc.stderr
    assert errors[0].startswith("error: no local worker could load the model; local worker 0 exited with code 1: ")
    assert "does not fit this model: 1 missing" in errors[0], proc.stderr
    assert took < 60, (took, proc.stderr)  # (worker_ready_s: 120)


def test_workers_that_never_answer_end_the_server_cleanly(tiny_checkpoint):
    closed = f"127.0.0.1:{free_tcp_port()}"  # nothing listens there
    proc = viewscale(
        "serve", "--checkpoint", str(tiny_checkpoint), "--listen", "127.0.0.1:0", "--worker", closed,
        "--set", "worker_ready_s=1",
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert "listening policy " in proc.stdout  # it had started its gRPC server: that is what it stops
    no_traceback(proc.stderr)
    assert f"error: 0 of 1 workers ready after 1s: {closed}" in proc.stderr


def test_a_port_another_server_holds_is_refused_not_shared(tiny_checkpoint):
    """grpc binds with SO_REUSEPORT unless told not to: a second server on a worker's port would
    start, and the kernel would hand each new connection to either. Here it is refused."""
    holder, address = start_worker(tiny_checkpoint)
    try:
        for command in (["serve", "--in-process"], ["worker"]):
            proc = viewscale(*command, "--checkpoint", str(tiny_checkpoint), "--listen", address)
            assert proc.returncode == 1, proc.stdout + proc.stderr
            assert f"error: cannot listen on {address}: another process holds the port" in proc.stderr
            assert "add_port" not in proc.stderr  # (grpc's own line came first, before)
            assert "ready " not in proc.stdout
            no_traceback(proc.stderr)
    finally:
        stop(holder)


@pytest.mark.parametrize(
    "listen, code, says",
    [
        ("192.0.2.1:0", 1, "cannot listen on 192.0.2.1:0: 192.0.2.1 is not an address of this machine"),
        ("127.0.0.1:99999", 2, "listen: '127.0.0.1:99999' is not host:port with a port of 0-65535"),
        # (before: exit 1, after grpc's own "add_port.cc ... Failed to add port" line)
        (
            "no-such-host.invalid:7001",
            2,
            "cannot listen on no-such-host.invalid:7001: 'no-such-host.invalid' is not a name or address",
        ),
    ],
)
def test_an_address_it_cannot_listen_on_is_one_line(tiny_checkpoint, listen, code, says, tmp_path):
    for command in (["worker"], ["serve", "--workers", "1", "--log-dir", str(tmp_path)]):
        proc = viewscale(*command, "--checkpoint", str(tiny_checkpoint), "--listen", listen)
        assert proc.returncode == code, proc.stderr
        assert says in proc.stderr
        assert proc.stderr.strip().splitlines() == [proc.stderr.strip()], proc.stderr  # that line alone
        assert proc.stderr.startswith("error: ") and "ready " not in proc.stdout
    # said before any worker starts (before: once a worker had started and the model loaded, 6 s)
    assert not list(tmp_path.iterdir())


def test_listen_addresses_are_checked_and_a_failed_bind_says_why():
    from pydantic import ValidationError

    from services.policy.config import WorkerConfig
    from services.policy.transport import bind_problem, unlistenable

    for ok in ("127.0.0.1:0", "0.0.0.0:7001", "[::1]:50051", "policy-worker:7001"):
        assert WorkerConfig(checkpoint="c", listen=ok).listen == ok
    for bad in ("7001", 7001, ":7001", "127.0.0.1:65536", "127.0.0.1:x", "host"):
        with pytest.raises(ValidationError, match="is not host:port with a port of 0-65535"):
            WorkerConfig(checkpoint="c", listen=bad)
    for why in (unlistenable, bind_problem):
        assert why("no-such-host.invalid:0") == "'no-such-host.invalid' is not a name or address this machine resolves"
        assert why("127.0.0.1:x").startswith("not host:port")
    assert bind_problem("192.0.2.1:0").startswith("192.0.2.1 is not an address of this machine")
    assert unlistenable("192.0.2.1:0") is None  # (it resolves: whether it binds is the bind's to say)
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        assert bind_problem(f"127.0.0.1:{held.getsockname()[1]}") == "another process holds the port"
    assert bind_problem("127.0.0.1:0") is None


def test_a_tls_file_that_is_not_there_is_a_config_error(tiny_checkpoint):
    proc = viewscale(
        "serve", "--checkpoint", str(tiny_checkpoint), "--set", "tls.cert=/nonexistent/cert.pem",
        "--set", "tls.key=/nonexistent/key.pem",
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "tls.cert /nonexistent/cert.pem: no such file" in proc.stderr
    no_traceback(proc.stderr)


@pytest.mark.parametrize(
    "args, says",
    [
        (
            ["--views", "F,FL", "--gamma", "F=-1,FL=2"],
            "--gamma F=-1.0,FL=2.0: the weight of F must be finite and non-negative, got -1.0",
        ),
        (["--gamma", "F=x"], "--gamma must look like F=0.5,FL=0.25, got 'F=x'"),
    ],
)
def test_eval_refuses_weights_the_server_would_refuse_before_starting_anything(tiny_checkpoint, tmp_path, args, says):
    out = tmp_path / "eval"
    proc = viewscale("eval", "--checkpoint", str(tiny_checkpoint), "--episodes", "1", "--out", str(out), *args)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"error: {says}"
    assert not out.exists()  # nothing started, nothing written


def test_eval_checks_weights_as_the_server_does():
    from services.session.evaluate import EvalError, EvalSpec, _check_gamma

    _check_gamma(EvalSpec(task="lift", gamma={"F": 0.0, "FL": 2.0}), ["F", "FL"])  # one may be zero
    _check_gamma(EvalSpec(task="lift", gamma={"F": 0.0}), ["F", "FL"])  # FL keeps the server's default
    for gamma, views, says in [
        ({"F": 0.5, "XX": 0.5}, ["F"], "--gamma names XX: not among the composed views F (--views)"),
        ({"F": 0.0, "FL": 0.0}, ["F", "FL"], "--gamma F=0.0,FL=0.0: the weights of F, FL sum to zero"),
        ({"F": float("nan")}, ["F"], "--gamma F=nan: the weight of F must be finite and non-negative, got nan"),
    ]:
        with pytest.raises(EvalError, match=re.escape(says)):
            _check_gamma(EvalSpec(task="lift", gamma=gamma), views)
    with pytest.raises(EvalError, match="not with --expert"):
        _check_gamma(EvalSpec(task="lift", expert=True, gamma={"F": 1.0}), ["F"])


def test_eval_whose_every_request_fails_exits_1_with_the_first_refusal(tiny_checkpoint, tmp_path):
    """The server's only worker killed: every GetAction is refused. That is not a policy scoring
    0 %: eval exits 1 quoting the first refusal, and the report says so."""
    worker, worker_address = start_worker(tiny_checkpoint)
    server, address = start_server(tiny_checkpoint, "--worker", worker_address)
    try:
        worker.kill()
        worker.wait()
        out = tmp_path / "eval"
        proc = viewscale(
            "eval", "--server", address, "--task", "lift", "--episodes", "1", "--max-ticks", "12", "--out", str(out),
            timeout=300,
        )  # fmt: skip
        assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
        s = json.loads((out / "report.json").read_text())["summary"]
        n = s["requests"]
        assert n > 0 and s["failed_requests"] == n and "UNAVAILABLE" in s["first_error"]
        assert f"error: {n} of {n} GetAction requests failed" in proc.stderr and s["first_error"] in proc.stderr
        report = (out / "report.md").read_text()
        assert f"no answer to any of {n} requests" in report and f"first failed request: {s['first_error']}" in report
    finally:
        stop(server)
        stop(worker)


def test_a_log_dir_that_is_a_file_is_one_line_before_any_worker_starts(tiny_checkpoint, tmp_path):
    note = tmp_path / "note.txt"
    note.write_text("keep me\n")
    proc = viewscale("serve", "--checkpoint", str(tiny_checkpoint), "--workers", "1", "--log-dir", str(note))
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"error: --log-dir {note}: not a directory"
    assert "listening" not in proc.stdout and note.read_text() == "keep me\n"


def test_a_stop_while_waiting_for_workers_ends_the_server_at_once_and_the_wait_says_why(tiny_checkpoint, tmp_path):
    """Waiting for workers (up to worker_ready_s, 120 s by default), the server says which are not
    ready and why, and a SIGTERM (docker stop, systemd) or Ctrl-C ends it then, not when the wait
    runs out: before, it went on waiting the whole 120 s."""
    closed = f"127.0.0.1:{free_tcp_port()}"  # nothing listens there
    err = tmp_path / "serve.err"
    with open(err, "w") as f:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--checkpoint", str(tiny_checkpoint),
             "--listen", "127.0.0.1:0", "--worker", closed],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=f, env=user_env(),
        )  # fmt: skip
    try:
        said = wait_for(lambda: "0 of 1 workers ready after 5 s" in err.read_text(), 60, "the wait's first report")
        assert said and f"waiting up to 120 s, worker_ready_s): {closed}: " in err.read_text()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0  # (it checks again within 0.1 s; a health check takes at most 2 s)
    finally:
        proc.kill()
        proc.wait()
    text = err.read_text()
    assert "stopped before any worker was ready" in text
    no_traceback(text)
    assert not [ln for ln in text.splitlines() if ln.startswith("error:")]  # a stop is not the wait running out


# Python as a terminal starts it: SIGINT raises KeyboardInterrupt (a parent that ignores SIGINT,
# as a background job of a script does, would hand that on to the child). It says "started" once
# its handler is in place and services.cli is imported (main's handling begins there): a SIGINT
# before that, while the interpreter itself starts or the standard library of services.cli imports
# (some 30 ms here; a loaded machine can take longer than 0.2 s), would end in a traceback.
AS_FROM_A_TERMINAL = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from services.cli import main; print('started', flush=True); sys.exit(main())"
)


@pytest.mark.parametrize("after_s", [0.2, 0.6])
def test_ctrl_c_while_the_command_line_starts_is_one_line_not_a_traceback(tiny_checkpoint, after_s):
    """The first second of every command goes to building the parser (it imports each command's
    module), then serve imports torch: a Ctrl-C there printed a KeyboardInterrupt traceback from
    deep in scipy's imports and exited -2."""
    proc = subprocess.Popen(
        [sys.executable, "-c", AS_FROM_A_TERMINAL, "serve", "--checkpoint", str(tiny_checkpoint),
         "--listen", "127.0.0.1:0", "--in-process"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env(),
    )  # fmt: skip
    assert proc.stdout.readline() == "started\n"
    time.sleep(after_s)  # the moment of the Ctrl-C is what is tested (the parser takes about a second)
    proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:  # (what it printed says where it was: test_cli_interrupts.py)
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"still running 30 s after the Ctrl-C:\n{out[-800:]}\n{err[-800:]}")
    assert "listening" not in out  # (it was still starting)
    assert proc.returncode == 130, err
    assert err.strip() in ("viewscale: interrupted", "viewscale serve: interrupted"), err


@pytest.mark.parametrize(
    "args, says",
    [
        (["--views", ","], "error: --views names no camera (leave it out for the training views)"),
        (["--views", "F,FL,F"], "error: invalid ServerConfig config: views: names F more than once"),
    ],
)
def test_a_view_list_naming_nothing_or_a_camera_twice_is_one_line(tiny_checkpoint, args, says):
    """`--views ,` fell back to the training views without a word; `F,FL,F` composed F twice."""
    proc = viewscale("serve", "--checkpoint", str(tiny_checkpoint), "--listen", "127.0.0.1:0", *args)
    assert proc.returncode == 2 and proc.stderr.startswith(says), proc.stderr
    assert proc.stderr.count("\n") == 1 and "listening" not in proc.stdout


def test_in_process_says_which_workers_it_leaves_unused(tiny_checkpoint):
    """--in-process wins over workers from a config file or flags: said, not silent (the device
    error after it keeps the test from starting a server)."""
    proc = viewscale(
        "serve", "--checkpoint", str(tiny_checkpoint), "--in-process", "--workers", "2",
        "--worker", "127.0.0.1:7001", "--device", "tpu",
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    warning, error = proc.stderr.strip().splitlines()
    assert warning == "warning: --in-process computes every view here; not used: 2 local workers, worker 127.0.0.1:7001"
    assert error.startswith("error: device 'tpu'")


def test_the_client_says_why_it_cannot_connect():
    """Its connect waits for the channel, so the last error was only DEADLINE_EXCEEDED; it now
    asks once more without waiting and quotes the connection's own error. A port beyond 65535,
    which gRPC would take modulo 65536 (99999 -> 34463), is refused before any connection."""
    from services.policy.client import PolicyClient, PolicyError

    closed = f"127.0.0.1:{free_tcp_port()}"
    with pytest.raises(PolicyError, match=f"no policy server at {closed} after 1s .*Connection refused"):
        PolicyClient(closed, connect_timeout_s=1.0)
    with pytest.raises(PolicyError, match="127.0.0.1:99999: port 99999 is beyond 65535"):
        PolicyClient("127.0.0.1:99999", connect_timeout_s=1.0)
    # (a URL: before, a second's wait and then gRPC's "Misformatted domain name")
    t0 = time.monotonic()
    with pytest.raises(PolicyError, match="^http://127.0.0.1:50051: http:// is not a gRPC address: give host:port"):
        PolicyClient("http://127.0.0.1:50051", connect_timeout_s=5.0)
    assert time.monotonic() - t0 < 4.0  # said at once, not after the connect timeout


URL = "http://127.0.0.1:50051"  # (what a browser would take)
BAD_WORKER_ADDRESSES = [
    ("dns:///policy-worker:99999", "port 99999 is beyond 65535"),  # (it went to port 34463)
    ("http://10.0.0.5:7001", "http:// is not a gRPC address: give host:port (e.g. 10.0.0.5:7001)"),
    ("10.0.0.5", "10.0.0.5 has no port (gRPC would use 443): give host:port"),
    ("10.0.0.5:70o1", "port '70o1' is not a number"),
    ("fe80::1:7001", "host 'fe80::1' has a ':' in it (an IPv6 address goes in brackets: [::1]:7001)"),
]


def test_an_address_grpc_cannot_use_is_refused_before_anything_starts(tiny_checkpoint, tmp_path):
    """Before, each worker address but the first was taken, and the server waited its whole
    worker_ready_s (120 s) for a worker gRPC could never reach (here, bounded to 10 s); `eval
    --server` with a URL waited its 15 s, then quoted gRPC's "Misformatted domain name"."""
    procs = viewscale_each(
        [
            ["serve", "--checkpoint", str(tiny_checkpoint), "--listen", "127.0.0.1:0", "--worker", address]
            + ["--set", "worker_ready_s=10"]
            for address, _ in BAD_WORKER_ADDRESSES
        ]
        + [["eval", "--server", URL, "--out", str(tmp_path / "eval")]]
    )
    for (address, says), proc in zip(BAD_WORKER_ADDRESSES, procs, strict=False):
        assert proc.returncode == 2 and "ready policy" not in proc.stdout, (address, proc.stderr)
        assert f"worker: {address}: {says}" in proc.stderr and proc.stderr.count("\n") == 1, (address, proc.stderr)
    said = f"error: --server: {URL}: http:// is not a gRPC address: give host:port (e.g. 127.0.0.1:50051)"
    assert procs[-1].returncode == 2 and procs[-1].stderr.strip() == said, procs[-1].stderr
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize("how", ["env", "set", "yaml"])
def test_an_empty_token_is_refused_not_taken_for_none(tiny_checkpoint, tmp_path, how):
    """An empty value reads as no value: VIEWSCALE_TOKEN=$TOKEN with TOKEN unset, or `--set token=`,
    started the worker (or server) with no token check at all, without a word."""
    args, env = ["worker", "--checkpoint", str(tiny_checkpoint)], user_env()
    if how == "env":
        env["VIEWSCALE_TOKEN"] = ""
    elif how == "set":
        args += ["--set", "token="]
    else:
        (tmp_path / "w.yaml").write_text('worker:\n  token: ""\n')
        args += ["--config", str(tmp_path / "w.yaml")]
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli", *args], cwd=ROOT, capture_output=True, text=True, env=env, timeout=60
    )
    assert proc.returncode == 2 and "listening" not in proc.stdout, proc.stderr
    [line] = proc.stderr.strip().splitlines()
    assert line.startswith("error: ") and "empty" in line and "token" in line.lower(), line


@pytest.mark.parametrize(
    "kw, says",
    [
        (dict(timeout_s=0), "timeout_s must be positive, got 0"),
        (dict(connect_timeout_s=-1), "connect_timeout_s must be positive, got -1"),
        (dict(jpeg_quality=101), "jpeg_quality must be 0 (raw RGB) to 100, got 101"),
        (dict(max_message_mb=0), "max_message_mb must be at least 1, got 0"),
    ],
)
def test_the_client_refuses_settings_out_of_range_before_connecting(kw, says):
    """(all were taken before; a call's timeout of 0 is a deadline already passed)"""
    from services.policy.client import PolicyClient

    with pytest.raises(ValueError, match=re.escape(says)):
        PolicyClient(f"127.0.0.1:{free_tcp_port()}", **kw)


def test_a_policy_teleop_it_cannot_use_is_one_line(tiny_checkpoint):
    """`teleop: {driver: {type: policy, ...}}` (README step 7): a view the server lacks, or no server
    there, stops the teleop service with one error line, as a camera or arm it cannot open (before:
    a ValueError or PolicyError traceback)."""
    server, address = start_server(tiny_checkpoint, "--in-process")
    try:
        cases = [
            (address, "[F, XX]", f"views XX: the policy server at {address} knows no such camera"),
            (f"127.0.0.1:{free_tcp_port()}", "[F]", "no policy server at 127.0.0.1:"),
            (f"grpc://{address}", "[F]", f"grpc://{address}: grpc:// is not a gRPC address: give host:port"),
        ]
        for at, views, says in cases:
            proc = subprocess.run(
                [sys.executable, "-m", "services.teleop", "--set"]
                + [f"driver={{type: policy, server: '{at}', views: {views}, connect_timeout_s: 1}}"],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert proc.returncode == 2, proc.stderr
            assert proc.stderr.startswith("error: teleop driver policy: ") and says in proc.stderr, proc.stderr
            no_traceback(proc.stderr)
    finally:
        stop(server)
