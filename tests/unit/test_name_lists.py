"""Lists of names in messages say how many they leave out."""

from __future__ import annotations

from services.core.text import first_few
from services.dataset.summary import FAILED, left_out_lines


def test_first_few_counts_what_it_leaves_out():
    assert first_few([]) == ""
    assert first_few(["a", "b", "c"]) == "a, b, c"
    assert first_few(["a", "b", "c", "d", "e"]) == "a, b, c and 2 more"
    assert first_few((f"e{i}" for i in range(7)), 5) == "e0, e1, e2, e3, e4 and 2 more"


def test_left_out_episodes_are_counted_past_the_fifth():
    """Before: '(e0, e1, e2, e3, e4, ...)', the count of the rest not said."""
    left = [{"episode": f"e{i}", "reason": FAILED} for i in range(8)]
    (line,) = left_out_lines(left)
    assert line == f"left out 8 episodes {FAILED} (e0, e1, e2, e3, e4 and 3 more): --include-failed builds them"
