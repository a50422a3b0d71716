"""Interleaved timing: calls alternate between the functions compared, and each keeps its fastest call."""

from __future__ import annotations

import pytest

from benchmarks import timing

pytestmark = pytest.mark.smoke


class FakeClock:
    """`time.perf_counter` stand-in that a timed function advances by its own duration."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_calls_alternate_and_each_function_keeps_its_fastest_call(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock)
    durations = {"a": iter([9.0, 3.0, 1.0, 2.0]), "b": iter([9.0, 5.0, 6.0, 4.0])}  # warm-up first
    calls = []

    def timed(name):
        def call():
            calls.append(name)
            clock.now += next(durations[name])
            return 0

        return call

    best = timing.best_times_interleaved([timed("a"), timed("b")], repeats=3)

    assert calls == ["a", "b"] + ["a", "b"] * 3
    assert best == [1.0, 4.0]
