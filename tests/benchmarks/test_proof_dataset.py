"""The proof dataset report's stretches: parsed from the generation's log, level batches counted in the stretch that
committed them."""

import datetime

from benchmarks.proof_dataset import read_stretches, stretch_figures

LOG = """stretch start 2026-01-01T10:00:00Z levels=512 commit=abc
stretch end 2026-01-01T11:00:00Z rc=0
noise that is not a stretch line
stretch start 2026-01-01T12:00:00Z levels=1024 commit=abc
stretch end 2026-01-01T12:30:00Z rc=130
stretch start 2026-01-01T13:00:00Z levels=1024 commit=def
"""


def _at(text: str) -> float:
    return datetime.datetime.fromisoformat(text).replace(tzinfo=datetime.UTC).timestamp()


def test_stretches_are_read_with_their_fields_and_an_open_last_one():
    stretches = read_stretches(LOG)
    assert [(s["start"], s["end"], s.get("rc")) for s in stretches] == [
        ("2026-01-01T10:00:00Z", "2026-01-01T11:00:00Z", "0"),
        ("2026-01-01T12:00:00Z", "2026-01-01T12:30:00Z", "130"),
        ("2026-01-01T13:00:00Z", None, None),
    ]
    assert stretches[1]["levels"] == "1024" and stretches[2]["commit"] == "def"


def test_batches_count_in_the_stretch_that_committed_them_and_the_rate_is_per_hour():
    commits = [
        (_at("2026-01-01T10:10:00"), 2),
        (_at("2026-01-01T10:50:00"), 3),
        (_at("2026-01-01T11:30:00"), 7),  # between stretches: in none
        (_at("2026-01-01T12:15:00"), 4),
        (_at("2026-01-01T13:20:00"), 1),
    ]
    rows = stretch_figures(read_stretches(LOG), commits, now=_at("2026-01-01T13:30:00"))
    assert [(r["level_batches"], r["kept_levels"]) for r in rows] == [(2, 5), (1, 4), (1, 1)]
    assert [r["wall_seconds"] for r in rows] == [3600.0, 1800.0, 1800.0]
    assert [r["kept_levels_per_hour"] for r in rows] == [5.0, 8.0, 2.0]
