"""Progress of a fixed-budget training call, estimated from the same program's previous call."""

import logging
import re
import threading
import time

import jax
import jax.numpy as jnp
import pytest
from pipeline_test_helpers import tiny_job

import kforge.pipeline.generation.estimated_progress as estimated
from kforge.pipeline.generation import resolve
from kforge.pipeline.generation.estimated_progress import estimated_progress
from kforge.pipeline.generation.level_batch import (
    KeyPurpose,
    _compiling_train_program,
    batch_level_indices,
    level_keys,
)

FAST_INTERVAL_SECONDS = 0.02
CALL_SECONDS = 0.3


@pytest.fixture(autouse=True)
def fast_estimates(monkeypatch):
    monkeypatch.setattr(estimated, "REPORT_INTERVAL_SECONDS", FAST_INTERVAL_SECONDS)
    monkeypatch.setattr(estimated, "_last_seconds", {})


def _call(program, reports: list, seconds: float = CALL_SECONDS) -> None:
    with estimated_progress(program, 10, lambda done, total: reports.append((done, total))):
        time.sleep(seconds)


def test_a_first_call_reports_its_start_and_end_and_a_later_one_estimates_between():
    first, second = [], []
    _call("program", first)
    assert first == [(0, 10), (10, 10)]  # nothing to estimate from
    _call("program", second)
    done = [updates for updates, _ in second]
    assert second[0] == (0, 10) and second[-1] == (10, 10) and {total for _, total in second} == {10}
    between = done[1:-1]
    assert between, "no estimate while the second call ran"
    assert between == sorted(between) and all(0 <= d <= 9 for d in between)
    assert max(between) >= 5  # most of the previous call's time passed before the block ended


def test_estimates_are_per_program_and_never_reach_the_total_while_a_longer_call_runs():
    _call("short", [])
    _call("long", [])
    reports = []
    _call("short", reports, seconds=3 * CALL_SECONDS)  # three times as long as its previous call
    assert [done for done, _ in reports[1:-1]][-1] == 9
    other = []
    _call("other", other)
    assert other == [(0, 10), (10, 10)]


def test_a_failing_listener_is_logged_and_the_call_goes_on(caplog):
    def broken(done, total):
        raise RuntimeError("listener broke")

    with caplog.at_level(logging.WARNING):
        with estimated_progress("program", 10, broken):
            finished = True
    assert finished and "progress listener failed" in caplog.text


def test_a_failed_call_reports_no_end_and_teaches_no_time():
    reports = []
    with pytest.raises(FloatingPointError):
        with estimated_progress("program", 10, lambda done, total: reports.append((done, total))):
            raise FloatingPointError("in the program")
    assert reports == [(0, 10)] and estimated._last_seconds == {}
    assert not [thread for thread in threading.enumerate() if thread.name == "estimated-progress"]


def _custom_call_targets(compiled) -> set[str]:
    return set(re.findall(r'custom_call_target="([^"]+)"', compiled.as_text()))


def test_the_fixed_budget_training_program_has_no_host_callback():
    """A program that calls back into Python is never stored in JAX's persistent compilation cache."""
    job = tiny_job("unused")
    indices = batch_level_indices(job, 0, 0)
    keys = level_keys(job.split.seed, indices, KeyPurpose.TRAIN)
    control = jax.jit(lambda x: (jax.debug.callback(print, x), x)[1]).lower(jnp.zeros(2)).compile()
    assert any("callback" in target for target in _custom_call_targets(control))  # what a host callback looks like
    compiled = _compiling_train_program(resolve(job), indices, keys).result()
    assert not any("callback" in target for target in _custom_call_targets(compiled))
