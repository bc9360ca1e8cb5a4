"""``writable_dir``, the check every command's output folder (--out, --root, --log-dir) goes through
before any work starts: made with its parents, or one message naming what is in the way."""

from __future__ import annotations

import pytest

from services.core.runtime import OutputError, output_dir, writable_dir


def test_makes_the_folder_and_its_parents(tmp_path):
    out = writable_dir(tmp_path / "a" / "b", "--out")
    assert out.is_dir() and out == tmp_path / "a" / "b"
    assert writable_dir(out, "--out") == out  # an existing folder is fine


def test_a_file_in_the_way_is_named_and_left_as_it_was(tmp_path):
    note = tmp_path / "note.txt"
    note.write_text("keep me\n")
    with pytest.raises(OutputError, match=f"^--out {note}: not a directory$"):
        writable_dir(note, "--out")
    with pytest.raises(OutputError, match=rf"^--root {note / 'x' / 'y'}: not a directory \({note} is a file\)$"):
        writable_dir(note / "x" / "y", "--root")
    assert note.read_text() == "keep me\n" and sorted(tmp_path.iterdir()) == [note]


class Failed(Exception):
    pass


def test_output_dir_takes_back_what_it_made_when_the_command_fails(tmp_path):
    # a new folder (and its new parents), with the empty subfolders the command made: all gone
    with pytest.raises(Failed), output_dir(tmp_path / "a" / "b", "--out") as out:
        (out / "episodes" / "x").mkdir(parents=True)
        raise Failed
    assert list(tmp_path.iterdir()) == []
    # a folder that was there is kept, even empty, and so is everything of the user's in it
    (tmp_path / "mine").mkdir()
    with pytest.raises(Failed), output_dir(tmp_path / "mine", "--out") as out:
        (out / "made").mkdir()
        raise Failed
    assert (tmp_path / "mine" / "made").is_dir()
    # a file written before the failure keeps its folder and the folders above it
    with pytest.raises(KeyboardInterrupt), output_dir(tmp_path / "new" / "run", "--out") as out:
        (out / "ckpt").mkdir()
        (out / "ckpt" / "weights").write_text("step 3\n")
        (out / "empty").mkdir()
        raise KeyboardInterrupt
    assert (tmp_path / "new" / "run" / "ckpt" / "weights").read_text() == "step 3\n"
    assert not (tmp_path / "new" / "run" / "empty").exists()
    # and a command that succeeds keeps its (empty) output
    with output_dir(tmp_path / "ok", "--out"):
        pass
    assert (tmp_path / "ok").is_dir()


HOLD = """
import sys, time
from services.core.runtime import exclusive
with exclusive(sys.argv[1], "training"):
    print("held", flush=True)
    time.sleep(120)
"""


def _holder(folder):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], cwd=root, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline() == "held\n"
    return proc


def test_exclusive_refuses_a_second_writer_and_frees_the_folder_when_the_first_dies(tmp_path):
    import signal

    from services.core.runtime import LOCK_FILE, exclusive

    proc = _holder(tmp_path)
    try:
        with pytest.raises(OutputError, match=rf"^{tmp_path} is in use by another training \(pid {proc.pid} on "):
            with exclusive(tmp_path, "training"):
                pass
    finally:
        proc.send_signal(signal.SIGKILL)  # killed: the OS drops its lock, the file stays behind
        proc.wait()
    assert (tmp_path / LOCK_FILE).exists()
    with exclusive(tmp_path, "training"):
        assert (tmp_path / LOCK_FILE).read_text().startswith("pid ")
    assert not (tmp_path / LOCK_FILE).exists()  # given up: gone


def test_another_commands_output_is_told_by_the_names_its_writer_gives():
    """OUTPUT_KINDS spells the names out (the bottom layer imports none of the writers): they must
    stay the writers' own."""
    from services.core.runtime import EVALUATION, OUTPUT_KINDS
    from services.dataset.store import MANIFEST, META
    from services.policy.checkpoint import MODEL_FILE, POLICY_FILE
    from services.trainer.train import RUN_FILES

    kinds = dict(OUTPUT_KINDS)
    assert kinds["a dataset"] == (MANIFEST, META)
    assert kinds["a training run"] == RUN_FILES
    assert kinds["a checkpoint"] == (MODEL_FILE, POLICY_FILE)
    assert kinds[EVALUATION] == ("report.json", "rollouts")  # services/session/evaluate.py writes these


@pytest.mark.parametrize(
    ("holds", "kind"),
    [
        ([], None),
        (["notes.txt"], None),
        (["ep.mcap", "logs/"], "a folder of recorded episodes"),
        (["manifest.json", "episodes/"], "a dataset"),
        (["config.json", "log.jsonl"], "a training run"),
        (["checkpoints/"], "a training run"),
        (["model.safetensors", "policy.json"], "a checkpoint"),
        (["rollouts/", "logs/"], "an evaluation"),
    ],
)
def test_output_kind_and_refusing_another_commands_folder(tmp_path, holds, kind):
    from services.core.runtime import RECORDINGS, output_kind, refuse_other_output

    out = tmp_path / "out"
    out.mkdir()
    for name in holds:
        (out / name.rstrip("/")).mkdir() if name.endswith("/") else (out / name).write_text("kept")
    before = sorted(p.name for p in out.iterdir())
    assert output_kind(out) == kind and output_kind(tmp_path / "missing") is None
    if kind in (None, RECORDINGS):
        refuse_other_output(out, "--out", RECORDINGS)  # where collect and rerender write more episodes
    else:
        with pytest.raises(OutputError, match=rf"^--out {out} is {kind}: choose another folder"):
            refuse_other_output(out, "--out", RECORDINGS)
    assert sorted(p.name for p in out.iterdir()) == before


def test_a_folder_being_read_is_refused_to_a_writer_and_shared_by_readers(tmp_path):
    """A training reads its dataset's frames as it goes: a dataset build over it (exclusive) is
    refused, naming the reader (before: it replaced the files under the running training)."""
    import os

    from services.core.runtime import LOCK_FILE, exclusive, reading

    with reading(tmp_path, "training"):
        with reading(tmp_path, "training"):  # readers share it
            with pytest.raises(
                OutputError, match=rf"^{tmp_path} is read by a training \(pid {os.getpid()} on .*\): wait"
            ):
                with exclusive(tmp_path, "dataset build"):
                    pass
        with pytest.raises(OutputError, match="is read by a training"):  # one reader still holds it
            with exclusive(tmp_path, "dataset build"):
                pass
    assert not (tmp_path / LOCK_FILE).exists()  # the last reader tidies up
    with exclusive(tmp_path, "dataset build"):
        with pytest.raises(OutputError, match=rf"^{tmp_path} is being written \(pid {os.getpid()} on .*\): wait"):
            with reading(tmp_path, "training"):
                pass
    with exclusive(tmp_path, "dataset build"):  # free again
        pass


def test_a_read_only_folder_is_read_without_a_lock(tmp_path):
    import os

    from services.core.runtime import LOCK_FILE, reading

    folder = tmp_path / "mounted"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):  # (root may write anywhere: then make the lock a folder)
            (folder / LOCK_FILE).mkdir()
        with reading(folder, "training"):
            pass
    finally:
        folder.chmod(0o755)
