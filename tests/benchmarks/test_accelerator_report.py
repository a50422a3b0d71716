"""The accelerator report: its plan, its target checks, and (slow) one toy run end to end on the CPU."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.accelerator import FULL, Budget, check_targets, kinetix_interpreter

REPO_ROOT = Path(__file__).resolve().parents[2]
ACCELERATOR = [sys.executable, "-m", "benchmarks.accelerator"]
"""The report's command, run from the top of the checkout."""


def test_dry_run_prints_the_full_plan_without_measuring():
    output = subprocess.run([*ACCELERATOR, "--dry-run"], capture_output=True, text=True, cwd=REPO_ROOT, check=True)
    plan = json.loads(output.stdout)
    assert plan["backend"] == "cpu"
    assert plan["plan"]["sizes"] == ["s", "m", "l"]
    assert plan["plan"]["engine_batches"] == [16384, 65536, 4096]  # every size at 16,384 first, then the largest
    assert plan["plan"]["engine_solver_loops"] == []  # the backend's own form alone: settled on a GPU
    assert plan["budget_seconds"] <= 600
    assert FULL.ppo_levels == (64, 256)


def test_targets_compare_with_jax2d_its_published_peaks_and_kinetix():
    report = {
        "engine": {
            "s/4096": {"ours_steps_per_second": 3e7, "jax2d_steps_per_second": 1e7, "speedup_vs_jax2d": 3.0},
            "l/4096": {"ours_steps_per_second": 1e6, "jax2d_steps_per_second": 8e5, "speedup_vs_jax2d": 1.25},
            "m/4096": {"skipped": "time budget"},
        },
        "ppo": {"s/64": {"steps_per_second": 4e5}, "s/256": {"steps_per_second": 6e5}, "m/64": {"error": "x"}},
        "kinetix_ppo": {"s": {"steps_per_second": 1e5}, "m": {"steps_per_second": 1e5}},
    }
    targets = check_targets(report)
    assert targets["engine_vs_jax2d"] == {"s/4096": True, "l/4096": False, "m/4096": None}
    assert targets["engine_vs_published_peak"] == {"s/4096": True, "l/4096": False, "m/4096": None}
    assert targets["ppo_vs_kinetix"] == {"s": True, "m": None}


def test_a_budget_for_some_sections_gives_them_all_of_its_time():
    budget = Budget(100.0, ("ppo", "pipeline"))
    assert not budget.enabled("engine") and not budget.allows("engine")
    assert budget.enabled("ppo") and budget.allows("ppo") and budget.allows("pipeline")


@pytest.mark.slow
def test_quick_report_runs_every_section_on_the_cpu():
    output = subprocess.run(
        [*ACCELERATOR, "--quick", "--budget", "3000"], capture_output=True, text=True, cwd=REPO_ROOT, check=True
    )
    report = json.loads(output.stdout)
    assert report["backend"] == "cpu"
    for section in ("engine", "env", "ppo", "pipeline", "determinism"):
        for key, figures in report[section].items():
            assert "error" not in figures and "skipped" not in figures, (section, key, figures)
    assert report["engine"]["s/8"]["ours_steps_per_second"] > 0
    assert report["engine"]["s/8"]["jax2d_steps_per_second"] > 0
    assert report["engine"]["s/8"]["ours_solver_loops"] == "looped"  # the CPU's "auto"
    for figures in report["engine"]["s/8"]["solver_loops"].values():
        assert figures["steps_per_second"] > 0 and figures["speedup_vs_jax2d"] > 0
    assert sorted(report["engine"]["s/8"]["solver_loops"]) == ["looped", "unrolled"]
    assert report["engine"]["s/8"]["compiled_concurrently"] == min(report["compile_threads"], 2)  # ours and Jax2D
    assert report["env"]["s/8"]["steps_per_second"] > 0
    assert report["ppo"]["s/2"]["steps_per_second"] > 0
    assert report["ppo"]["s/2"]["compiled_concurrently"] == 1  # the quick plan's one training program
    assert report["pipeline"]["s"]["levels"] == 2 and report["pipeline"]["s"]["ray"] is True  # installed here
    assert set(report["targets"]["engine_vs_jax2d"]) == {"s/8"}
    for ops in ("default_ops", "deterministic_ops"):  # on the CPU both repeat, and "vs the CPU" compares with itself
        assert report["determinism"]["engine/s"][ops]["repeat_bitwise_equal"] is True
        assert report["determinism"]["engine/s"][ops]["max_abs_difference_vs_cpu"] == 0.0
    assert report["determinism"]["pipeline/s"]["byte_identical"] is True
    assert report["determinism"]["pipeline/s"]["data_arrays"] > 0


def test_kinetix_ppo_runs_within_the_ppo_sections_budget():
    from benchmarks.accelerator import _attempt

    report, budget, logged = {}, Budget(100.0, ("ppo",)), []
    _attempt(report, "kinetix_ppo", "s", budget, lambda: {"steps_per_second": 1.0}, logged.append, budget_section="ppo")
    _attempt(report, "env", "s/8", budget, lambda: {"steps_per_second": 1.0}, logged.append)
    assert report == {"kinetix_ppo": {"s": {"steps_per_second": 1.0}}}


def test_dry_run_takes_the_determinism_batch():
    output = subprocess.run(
        [*ACCELERATOR, "--dry-run", "--determinism-batch", "4096"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert json.loads(output.stdout)["plan"]["determinism_batch"] == 4096


def test_dry_run_takes_the_engine_solver_loops_and_refuses_an_unknown_one():
    output = subprocess.run(
        [*ACCELERATOR, "--dry-run", "--engine-solver-loops", "looped"], capture_output=True, text=True, cwd=REPO_ROOT
    )
    assert output.returncode == 0, output.stderr
    assert json.loads(output.stdout)["plan"]["engine_solver_loops"] == ["looped"]
    refused = subprocess.run(
        [*ACCELERATOR, "--dry-run", "--engine-solver-loops", "fast"], capture_output=True, text=True, cwd=REPO_ROOT
    )
    assert refused.returncode == 2
    assert "argument --engine-solver-loops: invalid choice: 'fast'" in refused.stderr


def test_kinetix_runs_in_its_virtualenv_or_in_this_interpreter_with_its_package_folder_first(tmp_path):
    assert kinetix_interpreter(None, None) is None
    assert kinetix_interpreter(tmp_path / "venv", None) == (tmp_path / "venv" / "bin" / "python", None)
    assert kinetix_interpreter(tmp_path / "venv", tmp_path / "site") == (Path(sys.executable), tmp_path / "site")


def test_a_checkpoint_gets_the_report_after_every_figure(tmp_path):
    from benchmarks.accelerator import QUICK, run

    snapshots = []
    report = run(QUICK, 0.0, None, lambda line: None, ("engine", "env"), checkpoint=snapshots.append)
    assert [sorted(k for k in ("engine", "env") if k in snapshot) for snapshot in snapshots] == [
        ["engine"],
        ["engine", "env"],
    ]  # a run cut short after its first figure would have kept it
    assert snapshots[-1] == report and snapshots[0]["targets"]["engine_vs_jax2d"] == {"s/8": None}
    output = subprocess.run(
        [
            *ACCELERATOR,
            "--quick",
            "--sections",
            "env",
            "--budget",
            "0",
            "--out",
            str(tmp_path / "r.json"),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert json.loads((tmp_path / "r.json").read_text()) == json.loads(output.stdout)
