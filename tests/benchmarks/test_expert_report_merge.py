"""benchmarks/experts.py --merge: parts of one expert-quality measurement combine into the report one run would give,
and parts that do not belong together are refused."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.experts import merge_reports

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
MEASURED = RESULTS / "experts_s_1M_10M_selection_levels_0-31.json"
"""A recorded measurement of 32 random levels at two budgets; the tests cut it into parts and merge them back."""


def _quiet(_line: str) -> None:
    pass


@pytest.fixture(scope="module")
def measured() -> dict:
    return json.loads(MEASURED.read_text())


def _part(report: dict, rows: slice, budgets=None, machine=None) -> dict:
    """The report a run over `rows` of the random set (and only `budgets`) would have written."""
    whole = report["sets"]["random"]
    budgets = budgets or list(whole["budgets"])
    part = {key: copy.deepcopy(report[key]) for key in ("split_config", "scale", "overrides", "batch")}
    part["expert_selection"] = copy.deepcopy(report["expert_selection"])
    part["machine"] = machine or {"cpu_model": "test CPU", "cpu_count": 2}
    per_budget = {}
    for budget in budgets:
        entry = whole["budgets"][budget]
        levels = len(whole["levels"][rows])
        summary = dict(entry["summary"], levels=levels)
        per_budget[budget] = {
            "summary": summary,
            "per_level": {key: column[rows] for key, column in entry["per_level"].items()},
        }
    part["sets"] = {
        "random": {
            "levels": whole["levels"][rows],
            "filter_reason": whole["filter_reason"][rows],
            "budgets": per_budget,
        }
    }
    return part


def test_merging_two_level_ranges_gives_the_whole_measurement(measured):
    whole = measured["sets"]["random"]
    merged = merge_reports([_part(measured, slice(0, 16)), _part(measured, slice(16, None))], _quiet)
    result = merged["sets"]["random"]
    assert result["levels"] == whole["levels"]
    assert result["filter_reason"] == whole["filter_reason"]
    for budget, entry in whole["budgets"].items():
        successful = np.asarray(entry["per_level"]["successful"], bool)
        keep = np.asarray([reason == "kept" for reason in whole["filter_reason"]])
        summary = result["budgets"][budget]["summary"]
        assert summary["solved"] == successful.sum()
        assert summary["solved_kept"] == (successful & keep).sum()
        assert summary["levels"] == len(whole["levels"])
        assert result["budgets"][budget]["per_level"] == entry["per_level"]
    small, large = sorted(whole["budgets"], key=int)
    lost = np.asarray(whole["budgets"][small]["per_level"]["successful"], bool) & ~np.asarray(
        whole["budgets"][large]["per_level"]["successful"], bool
    )
    assert result["budget_comparisons"][0]["solved_only_by_smaller"] == [
        whole["levels"][i] for i in np.flatnonzero(lost)
    ]


def test_budgets_run_apart_merge_and_levels_missing_a_budget_are_left_out(measured):
    small, large = sorted(measured["sets"]["random"]["budgets"], key=int)
    parts = [_part(measured, slice(0, 32), [small]), _part(measured, slice(0, 8), [large])]
    lines = []
    merged = merge_reports(parts, lines.append)
    assert merged["sets"]["random"]["levels"] == measured["sets"]["random"]["levels"][:8]
    assert any("24 levels lack a budget" in line for line in lines)


def test_every_machine_of_the_parts_is_recorded(measured):
    first, second = {"cpu_model": "CPU A", "cpu_count": 2}, {"cpu_model": "CPU B", "cpu_count": 2}
    parts = [_part(measured, slice(0, 16), machine=first), _part(measured, slice(16, None), machine=second)]
    assert merge_reports(parts, _quiet)["machines"] == [first, second]
    same = [_part(measured, slice(0, 16), machine=first), _part(measured, slice(16, None), machine=first)]
    assert merge_reports(same, _quiet)["machines"] == [first]
    third = {"cpu_model": "CPU C", "cpu_count": 2}
    merged_again = merge_reports([merge_reports(parts, _quiet), _part(measured, slice(8, 24), machine=third)], _quiet)
    assert merged_again["machines"] == [first, second, third]


@pytest.mark.parametrize(
    ("key", "value"),
    [("batch", 8), ("scale", "tiny"), ("overrides", ["ppo.lr=1e-3"]), ("split_config", "configs/splits/10M/s.yaml")],
)
def test_parts_measured_with_different_settings_are_refused(measured, key, value):
    other = _part(measured, slice(16, None))
    other[key] = value
    with pytest.raises(SystemExit, match=key):
        merge_reports([_part(measured, slice(0, 16)), other], _quiet)


def test_parts_with_different_expert_selection_are_refused(measured):
    other = _part(measured, slice(16, None))
    other["expert_selection"] = None
    with pytest.raises(SystemExit, match="select experts differently"):
        merge_reports([_part(measured, slice(0, 16)), other], _quiet)


def test_a_level_with_two_different_results_is_refused(measured):
    first, overlapping = _part(measured, slice(0, 16)), _part(measured, slice(8, 24))
    budget = next(iter(overlapping["sets"]["random"]["budgets"]))
    column = overlapping["sets"]["random"]["budgets"][budget]["per_level"]["successful"]
    column[0] = not column[0]
    with pytest.raises(SystemExit, match="results differ"):
        merge_reports([first, overlapping], _quiet)
