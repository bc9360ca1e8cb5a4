"""``viewscale`` run as a process, as a user's shell runs it (importable from every test folder:
tests/ holds the conftest)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def user_env(**extra: str) -> dict[str, str]:
    """This environment without what `make test` adds for the suite (MUJOCO_GL): each command that
    renders sets its own default, and a test that leaned on the suite's would hide a command that
    does not (it hid `viewscale check`'s)."""
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    return {**env, **extra}


def viewscale(*args: str, timeout: float = 600, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """``cwd``: the folder it runs in (a user's own, to try relative paths; default the source tree)."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=user_env(),
    )


def viewscale_each(commands: list[list[str]], timeout: float = 120) -> list[subprocess.CompletedProcess]:
    """``viewscale(*command)`` for each command, four at a time (each is mostly a second of Python
    imports): the results in the commands' order."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(4) as pool:
        return list(pool.map(lambda command: viewscale(*command, timeout=timeout), commands))
