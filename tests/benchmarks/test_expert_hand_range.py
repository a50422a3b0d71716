"""benchmarks/experts.py --hand-first / --hand-count: which hand-designed levels a part measures."""

from __future__ import annotations

import pytest

from benchmarks.experts import hand_range

HAND_LEVELS = 10
"""Levels in the hand-designed s set."""


class _Refused(Exception):
    pass


def _refuse(message: str) -> None:
    raise _Refused(message)


def test_default_count_is_the_rest_of_the_set():
    assert hand_range(0, None, HAND_LEVELS, _refuse) == (0, HAND_LEVELS)
    assert hand_range(7, None, HAND_LEVELS, _refuse) == (7, 3)


def test_parts_cover_the_set_without_overlap():
    first_half = hand_range(0, 5, HAND_LEVELS, _refuse)
    second_half = hand_range(5, None, HAND_LEVELS, _refuse)
    covered = [i for first, count in (first_half, second_half) for i in range(first, first + count)]
    assert covered == list(range(HAND_LEVELS))


@pytest.mark.parametrize(("first", "count"), [(-1, 2), (0, 0), (8, 3), (10, None)])
def test_a_range_outside_the_set_is_refused_with_its_bounds(first, count):
    with pytest.raises(_Refused, match=r"levels 0\.\.9"):
        hand_range(first, count, HAND_LEVELS, _refuse)
