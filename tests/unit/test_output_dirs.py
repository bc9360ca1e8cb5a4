"""``writable_dir``, the check every command's output folder (--out, --root, --log-dir) goes through
before any work starts: made with its parents, or one message naming what is in the way."""

from __future__ import annotations

import pytest

from services.core.runtime import OutputError, writable_dir


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
