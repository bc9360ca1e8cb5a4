"""Signals to a service process as the kernel may deliver them."""

from __future__ import annotations

import ctypes
import os
import signal
from pathlib import Path


def signal_another_thread(pid: int, sig: int = signal.SIGTERM) -> int:
    """Send ``sig`` to one thread of ``pid`` that is not its main thread (Linux ``tgkill``) and
    return that thread's id. The kernel hands a process signal -- a kill, or the parent-death
    SIGTERM -- to any thread that does not block it, often one of zenoh's; this makes that case
    happen every time instead of now and then."""
    tid = next(int(t.name) for t in sorted(Path(f"/proc/{pid}/task").iterdir()) if int(t.name) != pid)
    if ctypes.CDLL(None, use_errno=True).tgkill(pid, tid, sig) != 0:
        raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
    return tid
