"""Adaptive budgets: levels stop when their evaluations decide, slots refill, and a level's result depends only on
its index and the config (not on its slot, the levels beside it, or the order batches are claimed in). Streamed
budgets: the same streaming, every trained level its whole budget."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest
from pipeline_test_helpers import run_in_process, tiny_job

from kforge.pipeline.generation import ConfigError, resolve
from kforge.pipeline.generation.adaptive import StopRule, Verdict, streamed_level_batches
from kforge.pipeline.generation.definition import data_definition, data_fingerprint
from kforge.pipeline.reading.stats import collect_stats, write_card
from kforge.pipeline.storage import FILTERED_PREFIX, iter_records

ADAPTIVE_JOB = [
    "experts.budget_mode=adaptive",
    "split.num_levels=8",
    "work.levels_per_shard=8",
    "split.expert_budget=1024",  # 16 updates of 4 envs x 16 steps
    "ppo.select_every_updates=4",  # 4 evaluations
    "experts.solved_evaluations=1",
    "experts.give_up_env_steps=0",  # no success at the first evaluation: give up
]
SEGMENT_STEPS = 4 * 4 * 16


def test_a_level_stops_when_solved_reliably_gives_up_without_success_or_trains_its_budget():
    rule = StopRule(solved_evaluations=2, solved_window=True, give_up_evaluations=3, num_evaluations=10)
    assert rule.verdict([1.0], False, window_successful=True) is None  # one perfect evaluation is not enough
    assert rule.verdict([0.5, 1.0, 1.0], True, window_successful=True) is Verdict.SOLVED
    assert rule.verdict([0.5, 1.0, 1.0], True, window_successful=False) is None  # the window it would keep fails
    assert rule.verdict([1.0] * 10, True, window_successful=False) is Verdict.BUDGET_SPENT
    assert rule.verdict([1.0, 0.5], True, window_successful=True) is None
    without_window = dataclasses.replace(rule, solved_window=False)  # the rule before windows were checked
    assert without_window.verdict([0.5, 1.0, 1.0], True, window_successful=False) is Verdict.SOLVED
    assert rule.verdict([0.0, 0.0], False) is None  # before the give-up point
    assert rule.verdict([0.0, 0.0, 0.0], False) is Verdict.GAVE_UP
    assert rule.verdict([0.0, 0.0, 0.0], True) is None  # a successful training episode is progress
    assert rule.verdict([0.0, 0.25, 0.0], False) is None
    assert rule.verdict([0.5] * 10, True) is Verdict.BUDGET_SPENT


def test_the_stop_rule_counts_evaluations_from_the_configs_env_steps(tmp_path):
    job = tiny_job(tmp_path, *ADAPTIVE_JOB, "experts.give_up_env_steps=300", "experts.solved_evaluations=3")
    rule = StopRule.of(resolve(job))
    assert (rule.solved_evaluations, rule.give_up_evaluations, rule.num_evaluations) == (3, 2, 4)  # 300 / 256 up


def test_adaptive_budgets_need_an_evaluation_period_dividing_the_updates(tmp_path):
    with pytest.raises(ConfigError, match="experts.budget_mode=adaptive: .*select_every_updates"):
        tiny_job(tmp_path, *ADAPTIVE_JOB, "ppo.select_every_updates=5")
    with pytest.raises(ConfigError, match="experts.budget_mode=streamed: .*select_every_updates"):
        tiny_job(tmp_path, *ADAPTIVE_JOB, "experts.budget_mode=streamed", "ppo.select_every_updates=5")
    with pytest.raises(ConfigError, match="experts.budget_mode must be one of fixed, streamed, adaptive"):
        tiny_job(tmp_path, "experts.budget_mode=elastic")


def test_the_fixed_mode_keeps_the_data_fingerprint_of_jobs_made_before_budget_modes(tmp_path):
    fixed = resolve(tiny_job(tmp_path))
    assert "experts" not in data_definition(fixed)
    assert data_fingerprint(resolve(tiny_job(tmp_path, "experts.give_up_env_steps=7"))) == data_fingerprint(fixed)
    adaptive = resolve(tiny_job(tmp_path, *ADAPTIVE_JOB))
    assert data_fingerprint(adaptive) != data_fingerprint(
        resolve(tiny_job(tmp_path, *ADAPTIVE_JOB, "experts.budget_mode=fixed"))
    )
    assert data_definition(adaptive)["experts"]["budget_mode"] == "adaptive"


def test_the_streamed_rule_trains_every_level_its_whole_budget(tmp_path):
    job = resolve(tiny_job(tmp_path, *ADAPTIVE_JOB, "experts.budget_mode=streamed"))
    rule = StopRule.of(job)
    assert rule.num_evaluations == 4
    for first_three in ([1.0, 1.0, 1.0], [0.0, 0.0, 0.0]):  # adaptive would have stopped both
        assert rule.verdict(first_three, False) is None
        assert rule.verdict([*first_three, first_three[-1]], False) is Verdict.BUDGET_SPENT
    streamed = data_definition(job)
    assert streamed["experts"]["budget_mode"] == "streamed"
    others = {
        data_fingerprint(resolve(tiny_job(tmp_path))),
        data_fingerprint(resolve(tiny_job(tmp_path, *ADAPTIVE_JOB))),
    }
    assert data_fingerprint(job) not in others


def batches_in_order(job, order):
    claims = iter(order)
    return dict(streamed_level_batches(resolve(job), 0, lambda: next(claims, None)))


@pytest.mark.slow
def test_levels_trained_in_other_orders_and_slots_give_bit_identical_experts_and_windows(tmp_path):
    job = tiny_job(tmp_path, *ADAPTIVE_JOB)
    forward = batches_in_order(job, [0, 1, 2, 3])
    backward = batches_in_order(job, [3, 1, 0, 2])
    assert sorted(forward) == sorted(backward) == [0, 1, 2, 3]
    trained = np.concatenate([forward[b].trained_env_steps for b in range(4)])
    outcomes = [outcome for b in range(4) for outcome in forward[b].outcome]
    in_training = [not outcome.startswith(FILTERED_PREFIX) for outcome in outcomes]
    # Levels stopped at different points, so slots were refilled while others trained on.
    assert len(set(trained[in_training])) > 1, trained
    assert set(trained[in_training]) <= {SEGMENT_STEPS * k for k in range(1, 5)}
    for batch in range(4):
        one, other = forward[batch], backward[batch]
        jax.tree.map(np.testing.assert_array_equal, one.states, other.states)
        for field in ("action", "done", "success", "kept", "level_id", "expert_success_rate", "expert_env_steps"):
            np.testing.assert_array_equal(getattr(one, field), getattr(other, field), err_msg=field)
        np.testing.assert_array_equal(one.trained_env_steps, other.trained_env_steps)
        np.testing.assert_array_equal(one.curves.success_rate, other.curves.success_rate)
        assert list(one.outcome) == list(other.outcome) and one.budget_mode == "adaptive"
        assert np.all(one.expert_env_steps <= np.maximum(one.trained_env_steps, SEGMENT_STEPS))
    # A level whose expert was perfect in evaluation stopped early only if its window succeeded (then it is kept);
    # here such levels' windows fail, so they train on to the budget (stopping them early kept nothing).
    perfect = [
        (int(result.trained_env_steps[i]), bool(result.kept[i]))
        for result in forward.values()
        for i in range(len(result.kept))
        if result.expert_success_rate[i] == 1.0
    ]
    assert perfect, "no level of the tiny job was perfect in evaluation: the solved rule went untried"
    assert all(kept or trained == 1024 for trained, kept in perfect), perfect


@pytest.mark.slow
def test_an_adaptive_job_commits_records_with_the_mode_and_each_experts_env_steps(tmp_path):
    job = tiny_job(tmp_path / "data", *ADAPTIVE_JOB)
    run_in_process(job)
    records = list(iter_records(job.output_dir))
    assert len(records) == 4 and {record.budget_mode for record in records} == {"adaptive"}
    for record in records:
        for level in record.levels:
            assert level.trained_env_steps in {0} | {SEGMENT_STEPS * k for k in range(1, 5)}
            assert (level.trained_env_steps == 0) == (not level.outcome.is_trained)
    trained = [level.trained_env_steps for record in records for level in record.levels if level.outcome.is_trained]
    card = Path(write_card(collect_stats(job.output_dir, show_progress=False), tmp_path / "card")).read_text()
    assert "Level batches by `experts.budget_mode`: adaptive: 4." in card
    assert f"Env steps trained per trained level: mean {np.mean(trained):,.0f}" in card


@pytest.mark.slow
def test_a_streamed_job_trains_the_whole_budget_and_gives_filtered_levels_no_slot(tmp_path):
    job = tiny_job(tmp_path / "data", *ADAPTIVE_JOB, "experts.budget_mode=streamed")
    run_in_process(job)
    records = list(iter_records(job.output_dir))
    assert len(records) == 4 and {record.budget_mode for record in records} == {"streamed"}
    levels = [level for record in records for level in record.levels]
    trained = [level for level in levels if level.outcome.is_trained]
    assert trained and len(trained) < len(levels)  # the tiny split's filter drops some levels
    assert {level.trained_env_steps for level in trained} == {1024}
    assert {level.trained_env_steps for level in levels if not level.outcome.is_trained} == {0}
