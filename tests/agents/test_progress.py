"""Progress reports from a training program: when they come, to whom, and that they change nothing."""

import jax
import jax.numpy as jnp
import numpy as np
from agents_test_helpers import ENV_PARAMS, STATIC, TRAIN_CONFIG, keys, mirrored_level, stack, thruster_level

from agents import train_levels, training_progress
from agents.progress import report_updates


def test_a_tracked_batch_reports_each_segment_and_trains_exactly_as_untracked(trained_mixed):
    reports = []
    with training_progress(lambda done, total: reports.append((done, total))) as token:
        tracked = jax.block_until_ready(
            train_levels(
                stack(thruster_level(), mirrored_level()), keys(0, 1), TRAIN_CONFIG, ENV_PARAMS, STATIC, progress=token
            )
        )
    # TRAIN_CONFIG: 24 updates, evaluated every 6: one report per level batch at the start of each segment.
    assert reports == [(0, 24), (6, 24), (12, 24), (18, 24)]
    jax.tree.map(np.testing.assert_array_equal, jax.device_get(tracked), jax.device_get(trained_mixed))


@jax.jit
def _report(token, done):
    report_updates(token, done, 10)
    return done


def test_reports_reach_only_their_own_listener_and_stop_when_its_block_ends():
    first, second = [], []
    with training_progress(lambda *report: first.append(report)) as first_token:
        with training_progress(lambda *report: second.append(report)) as second_token:
            assert int(first_token) != int(second_token)
            _report(first_token, jnp.int32(3))
            _report(second_token, jnp.int32(7))
            jax.effects_barrier()
        _report(second_token, jnp.int32(8))  # its listener is gone: dropped
        _report(first_token, jnp.int32(4))
        jax.effects_barrier()
    _report(first_token, jnp.int32(5))
    jax.effects_barrier()
    assert first == [(3, 10), (4, 10)]
    assert second == [(7, 10)]


def test_a_failing_listener_is_logged_and_does_not_fail_the_program(caplog):
    def broken(done, total):
        raise RuntimeError("listener broke")

    with training_progress(broken) as token:
        result = _report(token, jnp.int32(2))
        jax.effects_barrier()
    assert int(result) == 2
    assert "progress listener failed" in caplog.text
