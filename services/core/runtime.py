"""Process plumbing shared by every service: logging, signals, the ready line."""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import fcntl
import logging
import os
import platform
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from services.core.config import ConfigError, log_level_name

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"  # every service's lines, and the CLI's


def configure_logging(level: str = "INFO") -> None:
    """Called once from a service's main (never at import time). The service's level is set even
    where logging was configured before it (the ``viewscale`` CLI's ``--log-level``, WARNING by
    default): ``viewscale serve`` logs at its ``log_level`` setting, as ``python -m`` does."""
    lvl = getattr(logging, log_level_name(level))  # a name that is no level raises, never INFO in silence
    logging.basicConfig(level=lvl, format=LOG_FORMAT, stream=sys.stderr)
    logging.getLogger().setLevel(lvl)
    # torch's own INFO lines are not the service's (e.g. FakeTensor cache stats at exit, printed
    # when a Ctrl-C lands while torch imports): they show from DEBUG on
    logging.getLogger("torch").setLevel(lvl if lvl <= logging.DEBUG else max(lvl, logging.WARNING))


_SIGNALLED_WHILE_STARTING: list[str] = []


def remember_interrupts() -> None:
    """Called first in the command line's main. A Ctrl-C while a command starts raises
    KeyboardInterrupt, as Python's own handler does, and is also remembered: a library that
    swallows it (mpmath, which torch imports through sympy, wraps its ``import gmpy2`` in a bare
    ``except``) would otherwise lose it, and the command would start as if no one had asked it to
    stop. A command asks :func:`signalled_while_starting` once its own signal handling is in place.
    Where SIGINT is ignored (a background job of a script) or handled already, nothing changes.
    (Called again in one process, by a benchmark's second command, it forgets an earlier one's.)"""
    _SIGNALLED_WHILE_STARTING.clear()
    if threading.current_thread() is not threading.main_thread():
        return  # (signals are the main thread's)
    if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _remember):
        signal.signal(signal.SIGINT, _remember)


def _remember(signum, _frame):
    _SIGNALLED_WHILE_STARTING.append(signal.Signals(signum).name)
    raise KeyboardInterrupt


def signalled_while_starting() -> str | None:
    """The signal that came while the command started (see :func:`remember_interrupts`), or None."""
    return _SIGNALLED_WHILE_STARTING[0] if _SIGNALLED_WHILE_STARTING else None


def raise_interrupt(signum, _frame):
    """A signal handler that unwinds like Ctrl-C, naming the signal (``KeyboardInterrupt('SIGTERM')``)."""
    raise KeyboardInterrupt(signal.Signals(signum).name)


def interrupt_on_signals() -> None:
    """For a command that stops by unwinding (it keeps what it finished and says so): SIGTERM,
    SIGHUP and SIGINT (even where a parent shell ignores it) unwind like Ctrl-C; and a Ctrl-C that
    came while the command started, and that a library swallowed, unwinds now."""
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, raise_interrupt)
    if name := signalled_while_starting():
        raise KeyboardInterrupt(name)


def set_from_signal_handler(event: threading.Event, first: Callable[[], None] | None = None) -> None:
    """Call ``first`` and set ``event`` on a new thread: what a signal handler must do instead
    of ``event.set()``. Python runs a handler in the main thread between two bytecodes of whatever
    that thread was doing, possibly inside ``event.wait()`` while it holds the event's lock, which
    is not reentrant: ``event.set()`` there waits for that lock forever. A process signalled more
    than once is likely to get there sooner or later (a service gets its parent-death SIGTERM once
    for each of its dead parent's threads). Nothing the handler's thread may hold is taken here:
    ``_thread`` starts the thread without the ``threading`` module's locks."""

    def work() -> None:
        try:
            if first is not None:
                first()
        finally:
            event.set()

    try:
        _thread.start_new_thread(work, ())
    except RuntimeError:  # no thread to be had: at interpreter shutdown (Python 3.12 on: a signal
        # during atexit, from a parent-death burst) or out of threads. Set it here, as before: the
        # process is ending, and a main thread inside stop.wait() then is unlikely.
        event.set()


def stop_on_signals(stop: threading.Event) -> None:
    """SIGTERM, SIGINT and SIGHUP (a closed terminal) set ``stop`` so the service closes its files cleanly."""

    def handler(signum, _frame):
        name = signal.Signals(signum).name  # (the log line is written on the other thread too: the
        # handler may have come in the middle of a log line, and a buffered stream is not reentrant)
        set_from_signal_handler(stop, lambda: logging.getLogger("runtime").info("received %s, stopping", name))

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGHUP, handler)


def wait_for_stop(stop: threading.Event, poll_s: float = 0.2) -> None:
    """Block the main thread until ``stop`` is set, waking every ``poll_s``.

    Never ``stop.wait()`` with no timeout in a main thread: the kernel gives a process signal (a
    kill, or the parent-death SIGTERM of ``die_with_parent``) to any thread that does not block
    it, often one of zenoh's, and Python runs the handler only when the main thread next runs
    bytecode. A main thread asleep in an untimed wait never does, and the service never stops."""
    while not stop.wait(poll_s):
        pass


def host_description(gpu: str | None = None) -> str:
    """``node (CPU model, N cores[, gpu])``: where something ran. The same seed trained on another
    CPU model gives other weights (its float kernels round differently), so results record it."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()} ({cpu}, {os.cpu_count()} cores{'' if gpu is None else ', ' + gpu})"


def announce_ready(service: str, address: str) -> None:
    """Print the one line tests and compose wait on: ``ready <service> <address>``."""
    print(f"ready {service} {address}", flush=True)
    logging.getLogger(service).info("ready at %s", address)


def serve(name: str, bus_config, build, address: str) -> int:
    """The body of every service's ``main``: open the bus, build the service (a context manager
    taking the bus), print the ready line, run until SIGTERM/SIGINT, close everything."""
    from services.core.bus import Bus  # here, not at import: runtime stays free of zenoh

    die_with_parent()
    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(bus_config) as bus, build(bus) as service:
        announce_ready(name, address)
        service.run(stop)
    return 0


# What two services on one bus would both do: the reason the second one is refused.
DOUBLED = {
    frozenset({"recorder"}): "record every episode, each into its own folder",
    frozenset({"robot"}): "publish robot/state and drive an arm",
    frozenset({"sim"}): "publish robot/state and camera frames",
    frozenset({"robot", "sim"}): "publish robot/state",
    frozenset({"camera", "sim"}): "publish camera frames",
    frozenset({"camera"}): "publish the same camera's frames",
    frozenset({"teleop"}): "send a command every tick",
    frozenset({"trainer"}): "take every TRAIN request",
}


RIVAL_SETTLE_S = 1.0


def refuse_rivals(bus, me: str, rivals: set[str]) -> None:
    """ConfigError when a service in ``rivals`` (liveliness names) is on ``bus`` already: a sim
    started on a lab's session would publish its arm's state and frames in among the real ones, a
    second recorder record every episode again. Checked before ``me`` publishes or announces.

    A rival that has just stopped (a session started again at once) may still be seen for a moment:
    its token's withdrawal reaches the router after it. Only one still there a second later counts."""
    found = sorted(rivals & bus.alive(timeout=2.0))
    if found:
        time.sleep(RIVAL_SETTLE_S)
        found = sorted(rivals & bus.alive(timeout=2.0))
    if found:
        rival = found[0]
        kind = rival.split("/", 1)[0]  # (camera/F: a camera service's token for its camera F)
        who = f"another {me}" if kind == me else f"a {kind} service"
        raise ConfigError(
            f"{who} is on this bus (namespace {bus.cfg.namespace!r}): both would "
            f"{DOUBLED.get(frozenset({me, kind}), 'run')}; stop it, or give this session its own bus.namespace"
        )


PARENT_ENV = "VIEWSCALE_PARENT_PID"


def child_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """The environment for a child process that must not outlive this one (see ``die_with_parent``)."""
    return dict(os.environ if env is None else env, **{PARENT_ENV: str(os.getpid())})


def die_with_parent() -> None:
    """Called first in a main: when started through ``child_env``, get SIGTERM when the parent dies,
    however it dies (kill -9 included), so no service outlives its session and every file is
    closed. Linux only (prctl); elsewhere, and for processes started by hand, nothing changes."""
    parent = os.environ.pop(PARENT_ENV, None)  # grandchildren get their own, or none
    if not parent or not sys.platform.startswith("linux"):
        return
    pr_set_pdeathsig = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != int(parent):  # the parent died before prctl: nobody would send the signal
        os.kill(os.getpid(), signal.SIGTERM)


class OutputError(ValueError):
    """An output directory that cannot be made or written; the message names the argument."""


def writable_dir(path: str | os.PathLike, argument: str) -> Path:
    """Make ``path`` (and its parents) and check it can be written, before any work starts."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):  # it, or a folder on its way, is a file
        file = next((q for q in [p, *p.parents] if q.exists() and not q.is_dir()), p)
        raise OutputError(f"{argument} {p}: not a directory" + (f" ({file} is a file)" if file != p else "")) from None
    except OSError as exc:
        raise OutputError(f"{argument} {p}: {exc.strerror or exc}") from None
    if not p.is_dir() or not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"{argument} {p}: not a writable directory")
    return p


# What marks a folder as one command's output: its kind, and names any one of which it holds. The
# names are the writers' own (services.dataset.store, services.trainer.train, services.policy.
# checkpoint, services.session.evaluate; tests/unit/test_output_dirs.py holds them to those).
DATASET = "a dataset"
EVALUATION = "an evaluation"
OUTPUT_KINDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (DATASET, ("manifest.json", "meta.json")),
    ("a training run", ("config.json", "checkpoints", "log.jsonl")),
    ("a checkpoint", ("model.safetensors", "policy.json")),
    (EVALUATION, ("report.json", "rollouts")),
)
RECORDINGS = "a folder of recorded episodes"  # one holding episode files (*.mcap)


def output_kind(path: str | os.PathLike) -> str | None:
    """Which command's output ``path`` is, by what it holds; None for a missing, empty or other folder."""
    p = Path(path)
    if not p.is_dir():
        return None
    for kind, names in OUTPUT_KINDS:
        if any((p / name).exists() for name in names):
            return kind
    return RECORDINGS if any(p.glob("*.mcap")) else None


def refuse_other_output(path: str | os.PathLike, argument: str, own: str) -> None:
    """OutputError when ``path`` is another command's output: what this one writes would go in among
    its files (the command's own kind, ``own``, is where it writes more)."""
    kind = output_kind(path)
    if kind is not None and kind != own:
        raise OutputError(f"{argument} {path} is {kind}: choose another folder (a new one is made)")


@contextlib.contextmanager
def output_dir(path: str | os.PathLike, argument: str, keep_empty: bool = True) -> Iterator[Path]:
    """``writable_dir`` for a command's output, taken back when the command fails: where ``path``
    did not exist, the empty folders the block left in it, ``path`` itself and the parents made
    for it are removed again if the block raises (or, ``keep_empty`` False, whenever the block
    leaves them empty). A file, or a folder holding one, is never removed."""
    p = Path(path).absolute()
    made = [q for q in [p, *p.parents] if not q.exists()]  # leaf first
    writable_dir(path, argument)
    try:
        yield Path(path)
    except BaseException:
        _take_back(made)
        raise
    if not keep_empty:
        _take_back(made)


def _take_back(made: list[Path]) -> None:
    """Remove the empty folders in and above a new output folder (``made``: it and its new parents)."""
    if not made:  # the folder was there before: nothing in it is the command's to remove
        return
    for root, _dirs, _files in os.walk(made[0], topdown=False):  # every folder in it is the command's
        with contextlib.suppress(OSError):
            Path(root).rmdir()  # (fails for a folder that still holds something)
    for q in made[1:]:
        try:
            q.rmdir()
        except OSError:
            break


LOCK_FILE = ".viewscale.lock"  # held in an output folder while a command writes there
READ_BY = "read by"  # what a reader writes in the lock file: ``read by a training (pid ...)``


class _Held(Exception):
    """The lock is held by another process; ``holder`` is what it wrote in the lock file."""

    def __init__(self, holder: str):
        super().__init__(holder)
        self.holder = holder


def _locked(lock: Path, mode: int) -> IO[str]:
    """``lock`` opened (made if missing) and locked with ``mode`` (``LOCK_EX`` or ``LOCK_SH``)
    without waiting; _Held when another process holds it, OSError when it cannot be made or
    locked. A lock file its holder removed while we opened it is opened again (its new one)."""
    while True:
        fh = open(lock, "a+")
        try:
            fcntl.flock(fh, mode | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip()
            fh.close()
            raise _Held(holder) from None
        except OSError:
            fh.close()
            raise
        try:
            same = os.stat(lock).st_ino == os.fstat(fh.fileno()).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fh
        fh.close()


@contextlib.contextmanager
def exclusive(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Hold the lock of output folder ``path`` while a command writes in it. A second command on the
    same folder (another terminal, a run thought dead) is refused at once with an OutputError naming
    the process that holds it, instead of both writing there. The OS drops the lock of a process
    that dies, killed or not; the lock file goes when the lock is given up."""
    lock = Path(path) / LOCK_FILE
    try:
        fh = _locked(lock, fcntl.LOCK_EX)  # held until the block ends
    except _Held as held:
        if held.holder.startswith(READ_BY):  # (a training reading the dataset this build would replace)
            raise OutputError(f"{path} is {held.holder}: wait for it to end, or choose another folder") from None
        raise OutputError(
            f"{path} is in use by another {what}"
            + (f" ({held.holder})" if held.holder else "")
            + ": wait for it to end, or choose another folder"
        ) from None
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        yield
    finally:
        with contextlib.suppress(OSError):
            lock.unlink()
        fh.close()


@contextlib.contextmanager
def reading(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Hold the lock of folder ``path`` shared while a command reads it (a training its dataset): a
    command that would write there (``exclusive``: a dataset build over it) is refused meanwhile,
    naming the reader, instead of replacing files under it. Readers share the lock; one that finds
    the folder being written is refused, naming the writer. A folder where no lock file can be made
    (a dataset on a read-only mount) is read without one."""
    lock = Path(path) / LOCK_FILE
    try:
        fh = _locked(lock, fcntl.LOCK_SH)
    except _Held as held:
        raise OutputError(
            f"{path} is being written" + (f" ({held.holder})" if held.holder else "") + ": wait for it to end"
        ) from None
    except OSError:  # read-only, not ours to write, or a file system without locks (ENOLCK): read without one
        yield
        return
    try:
        try:  # (several readers: the last one to start is named)
            fh.truncate(0)
            fh.write(f"{READ_BY} a {what} (pid {os.getpid()} on {socket.gethostname()})\n")
            fh.flush()
        except OSError:  # a full disk: the lock holds without its note
            pass
        yield
    finally:
        try:  # the last reader removes the lock file (one that gets the lock to itself)
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            lock.unlink()
        except OSError:  # (BlockingIOError: another reader holds it still)
            pass
        fh.close()
