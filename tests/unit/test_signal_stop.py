"""A stop signal sets the service's stop event wherever the main thread was.

Python runs a signal handler in the main thread between two bytecodes of whatever it was doing.
When that is inside ``stop.wait(...)``, the thread holds the event's lock, and a handler calling
``stop.set()`` there waited for that lock forever: the service never stopped. It happened in a
fresh-clone run of the collect test: a service gets its parent-death SIGTERM once for each of its
dead parent's threads, and the recorder, still running 30 s after its session was killed with
SIGKILL, was one of them. The child below puts the handler exactly there: it holds the event's
lock (``Event._cond``, CPython's own, as ``Event.wait`` does) while the signal comes in.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent(
    """
    import contextlib, logging, os, signal, sys, threading
    from services.core.runtime import stop_on_signals
    from services.trainer.cli import _stop_on_signals

    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    stop = threading.Event()
    if sys.argv[1] == "service":
        stop_on_signals(stop)
        scope = contextlib.nullcontext()
    else:
        scope = _stop_on_signals(stop, announce=True)
    with scope:
        with stop._cond:  # where the main thread is inside stop.wait()
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs at one of these bytecodes, the lock held
                pass
        print("stopped" if stop.wait(10) else "not stopped", flush=True)
    """
)


@pytest.mark.parametrize("handler", ["service", "training"])
def test_a_signal_that_comes_while_the_main_thread_holds_the_stop_events_lock_still_stops(handler):
    try:
        proc = subprocess.run(
            [sys.executable, "-c", CHILD, handler], cwd=ROOT, capture_output=True, text=True, timeout=30
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"the {handler} process hung in its signal handler: SIGTERM never set its stop event")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "stopped", proc.stdout + proc.stderr[-3000:]
    said = "runtime: received SIGTERM, stopping" if handler == "service" else "SIGTERM: stopping after this step"
    assert said in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-3000:]


def test_a_second_signal_right_after_the_first_interrupts_training_at_once():
    """Training's first signal stops after the step, a second one at once: also when the second comes
    before the first one's thread has set the event."""
    child = textwrap.dedent(
        """
        import os, signal, threading
        from services.trainer.cli import _stop_on_signals

        stop = threading.Event()
        try:
            with _stop_on_signals(stop, announce=True):
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(1000):
                    pass
            print("not interrupted", flush=True)
        except KeyboardInterrupt as exc:
            print("interrupted by", exc, flush=True)
        """
    )
    proc = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.stdout.strip() == "interrupted by SIGTERM", proc.stdout + proc.stderr[-3000:]
    assert proc.stderr.count("SIGTERM: stopping after this step") == 1, proc.stderr


def test_a_signal_when_no_thread_can_be_started_still_stops_without_a_traceback():
    """At interpreter shutdown Python 3.12 on refuses new threads (a parent-death SIGTERM of a burst
    that comes during atexit): the handler's RuntimeError cut the atexit callback short (the
    keyboard teleop's terminal restore is one). Faked here, on this Python, by the refusal itself."""
    child = textwrap.dedent(
        """
        import os, signal, sys, threading
        import services.core.runtime as runtime

        def refuse(*args):
            raise RuntimeError("can't create new thread at interpreter shutdown")

        stop = threading.Event()
        runtime.stop_on_signals(stop)
        runtime._thread.start_new_thread = refuse
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):
            pass
        print("stopped" if stop.is_set() else "not stopped", flush=True)
        """
    )
    proc = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and proc.stdout.strip() == "stopped", proc.stdout + proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr
