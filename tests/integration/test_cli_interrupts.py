"""A Ctrl-C while a command starts stops it, even where a library swallows the KeyboardInterrupt.

mpmath (which torch imports through sympy) wraps its ``import gmpy2`` in a bare ``except``: a Ctrl-C
landing there was lost, and ``viewscale serve`` went on to serve (CI saw it not exit within 30 s of
a Ctrl-C). Here the Ctrl-C is raised, and swallowed, at a chosen import of a command's start, the
way such a library does it, so each command's check is tested at a known moment, not by timing.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from cli_process import ROOT, user_env

# As a terminal starts it (SIGINT raises KeyboardInterrupt); at the first lookup of the module
# named by argv[1], a SIGINT is raised and swallowed, as by a bare except around an import.
SWALLOWED_AT = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
at = sys.argv.pop(1)

class Swallow:
    done = False

    def find_spec(self, name, path=None, target=None):
        if name == at and not Swallow.done:
            Swallow.done = True
            try:
                signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                print("swallowed", flush=True)
        return None

sys.meta_path.insert(0, Swallow())
from services.cli import main
sys.exit(main())
"""


def run_swallowed(at: str, *args: str) -> subprocess.CompletedProcess:
    proc = subprocess.Popen(
        [sys.executable, "-c", SWALLOWED_AT, at, *args],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=user_env(),
    )  # fmt: skip
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"still running 60 s after a Ctrl-C that was swallowed at {at}:\n{out[-800:]}\n{err[-800:]}")
    assert out.startswith("swallowed\n"), (out, err)  # (the Ctrl-C came where it is meant to)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_a_ctrl_c_a_library_swallowed_while_the_parser_was_built_stops_any_command(sim_dataset):
    """(a command with no signal handling of its own: it ran to its end)"""
    proc = run_swallowed("services.policy.cli", "dataset", "info", str(sim_dataset))
    assert proc.returncode == 130 and proc.stderr.strip() == "viewscale dataset: interrupted", proc.stderr
    assert proc.stdout == "swallowed\n"


def test_serve_stops_on_a_ctrl_c_a_library_swallowed_while_it_started(tiny_checkpoint):
    proc = run_swallowed(
        "torch", "serve", "--checkpoint", str(tiny_checkpoint), "--listen", "127.0.0.1:0", "--in-process"
    )
    assert proc.returncode == 130 and proc.stderr.strip() == "viewscale serve: interrupted", proc.stderr
    assert "listening" not in proc.stdout


def test_collect_stops_on_a_ctrl_c_a_library_swallowed_while_it_started(tmp_path):
    out = tmp_path / "raw"
    proc = run_swallowed("services.session.collect", "collect", "--task", "lift", "--episodes", "1", "--out", str(out))
    assert proc.returncode == 130, proc.stderr
    # nothing was started: it says so (before: "episodes recorded so far are in" a folder never made)
    assert proc.stderr.strip() == "interrupted (SIGINT): services stopped; no episodes recorded", proc.stderr
    assert not list(out.glob("*.mcap"))


def test_train_stops_on_a_ctrl_c_a_library_swallowed_while_it_started(sim_dataset, tmp_path):
    proc = run_swallowed(
        "services.trainer.train", "train", "--data", str(sim_dataset), "--preset", "tiny", "--steps", "5",
        "--out", str(tmp_path / "run"), "--device", "cpu",
    )  # fmt: skip
    assert proc.returncode == 130, proc.stderr
    assert "stopped before the first step: nothing to save" in proc.stderr, proc.stderr
