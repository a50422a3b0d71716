"""`kforge stats`: the card's counts, bytes, fingerprint, config and timings agree with values computed here from the
records, the zarr arrays and the files; its plots are real PNGs; a non-dataset directory is refused by name.

One tiny dataset is generated in-process for the module (the test job's shapes, a seed whose levels cover the
cases). Its no-op filter checks a single step, so the filter drops a level without an actuator while other levels
are trained, one of them kept: the card then has a filtered, a kept and unsolved levels to count.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pipeline_test_helpers import run_in_process, tiny_job

from kforge.pipeline.cli.stats import main
from kforge.pipeline.reading.stats import CARD_FILE, FIGURES_DIR, PLOTS, SHARDS_FILE, collect_stats, write_card
from kforge.pipeline.storage.layout import VALID
from kforge.pipeline.storage.manifest import iter_records
from kforge.pipeline.storage.shard_store import open_dataset

DATASET_OVERRIDES = ("split.seed=7", "filter.noop_steps=1")
WINDOW_STEPS = 24  # [env steps] collect.window_steps of the test job
FIGURE_PIXELS = (640, 400)  # (width, height) of each plot: 6.4 x 4.0 inch at 100 dpi
MIN_PLOT_COLOURS = 3
"""A drawn plot has at least background, axes/text and a data colour."""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("stats") / "dataset"
    run_in_process(tiny_job(root, *DATASET_OVERRIDES))
    return root


@pytest.fixture(scope="module")
def card(dataset, tmp_path_factory):
    """(card text, output folder) of `kforge stats DATASET --out OUT`."""
    out = tmp_path_factory.mktemp("card")
    main([str(dataset), "--out", str(out), "--no-progress"])
    return (out / CARD_FILE).read_text(), out


def _section(card_text: str, title: str) -> str:
    return card_text.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]


def _table(card_text: str, title: str) -> dict[str, list[str]]:
    """First cell -> the other cells of each body row of the section's table."""
    rows = [line.strip("|").split("|") for line in _section(card_text, title).splitlines() if line.startswith("| ")]
    return {cells[0].strip(): [cell.strip() for cell in cells[1:]] for cells in rows[1:]}


def _number(text: str) -> float:
    return float(text.replace(",", ""))


def expected_counts(root) -> dict[str, int]:
    """Level counts from the commit records, and kept from the stored valid flags."""
    levels = [level for record in iter_records(root) for level in record.levels if level.outcome != "padding"]
    outcomes = [level.outcome for level in levels]
    trained = [level for level in levels if not level.outcome.startswith("filtered:")]
    counts = {
        "sampled": len(levels),
        "trained": len(trained),
        "solved": sum(level.expert_success_rate is not None and level.expert_success_rate > 0 for level in trained),
        "kept": int(open_dataset(root).read([VALID], range(open_dataset(root).geometry.num_slots))[VALID].sum()),
        "unsolved": outcomes.count("unsolved"),
        "failed": outcomes.count("failed"),
    }
    for outcome in set(outcomes):
        if outcome.startswith("filtered:"):
            counts[f"filtered: {outcome.removeprefix('filtered:')}"] = outcomes.count(outcome)
    return counts


def test_card_counts_equal_counts_from_the_records_and_arrays(dataset, card):
    expected = expected_counts(dataset)
    assert expected["kept"] >= 1 and expected["sampled"] > expected["trained"], "the dataset no longer covers the cases"
    rows = _table(card[0], "Levels")
    assert {label: int(_number(cells[0])) for label, cells in rows.items()} == expected
    assert rows["kept"][1] == f"{100 * expected['kept'] / expected['sampled']:.1f} %"


def test_card_bytes_match_the_files_on_disk(dataset, card):
    data_bytes = sum(path.stat().st_size for path in (dataset / "data").rglob("*") if path.is_file())
    manifest_bytes = sum(path.stat().st_size for path in (dataset / "manifest").rglob("*") if path.is_file())
    rows = _table(card[0], "Storage")
    assert _number(rows["data arrays (data/)"][0]) == data_bytes
    assert _number(rows["total"][0]) == data_bytes + manifest_bytes
    transitions = expected_counts(dataset)["kept"] * WINDOW_STEPS
    storage = _section(card[0], "Storage")
    assert f"Stored transitions: {transitions:,}" in storage
    assert f"{data_bytes / transitions:.1f} B of data arrays" in storage


def test_card_names_the_fingerprint_config_and_timings(dataset, card):
    text = card[0]
    assert open_dataset(dataset).spec.attributes["data_fingerprint"] in text
    config = _table(text, "Config")
    assert config["split.expert_budget"] == ["256"] and config["filter.noop_steps"] == ["1"]
    assert config["scale"] == ["null"] and config["env.physics"] == ["kinetix"]

    seconds = [record.provenance["seconds"] for record in iter_records(dataset)]
    total = sum(s["total"] for s in seconds)
    timings = _table(text, "Time")
    assert _number(timings["total"][0]) == pytest.approx(total, abs=0.05)
    assert _number(timings["train"][0]) == pytest.approx(sum(s["train"] for s in seconds), abs=0.05)
    share = 100 * sum(s["train"] + s["collect"] for s in seconds) / total
    assert f"Train + collect: {share:.1f} % of the total." in _section(text, "Time")


def test_shard_table_counts_and_times_each_shard_from_its_records(dataset, card):
    with open(card[1] / FIGURES_DIR / SHARDS_FILE, newline="") as file:
        rows = {int(row["shard"]): row for row in csv.DictReader(file)}
    assert sorted(rows) == [0, 1]
    for shard, row in rows.items():
        records = [record for record in iter_records(dataset) if record.shard == shard]
        levels = [level for record in records for level in record.levels if level.outcome != "padding"]
        assert int(row["batches"]) == len(records) and int(row["sampled"]) == len(levels)
        assert int(row["kept"]) == sum(level.outcome == "kept" for level in levels)
        assert int(row["trained"]) == sum(not level.outcome.startswith("filtered:") for level in levels)
        seconds = sum(record.provenance["seconds"]["train"] for record in records)
        assert float(row["seconds/train"]) == pytest.approx(seconds, abs=1e-3)
    assert sum(int(row["sampled"]) for row in rows.values()) == expected_counts(dataset)["sampled"]


def test_plots_are_pngs_with_content(card):
    text, out = card
    for stem in PLOTS:
        relative = f"{FIGURES_DIR}/{stem}.png"
        assert f"]({relative})" in text
        with Image.open(out / relative) as image:
            assert image.format == "PNG" and image.size == FIGURE_PIXELS
            pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
        assert len(np.unique(pixels, axis=0)) >= MIN_PLOT_COLOURS, stem


def test_records_without_timings_or_curves_still_give_a_card(dataset, tmp_path):
    """Records of older datasets lack provenance, learning curves and budget modes; the counts remain and the card
    and plots say so."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    for path in (copy / "manifest").rglob("*.json"):
        record = json.loads(path.read_text())
        record.pop("provenance")
        record.pop("curve_env_steps")
        record.pop("budget_mode")
        for level in record["levels"]:
            level.pop("learning_curve")
            level.pop("trained_env_steps")
        path.write_text(json.dumps(record))
    text = Path(write_card(collect_stats(copy, show_progress=False), tmp_path / "out")).read_text()
    assert "No level batch records wall times" in text
    budgets = _section(text, "Expert budgets")
    assert "not recorded (fixed, before budget modes)" in budgets and "Env steps trained" not in budgets
    rows = _table(text, "Levels")
    assert {label: int(_number(cells[0])) for label, cells in rows.items()} == expected_counts(dataset)
    assert all((tmp_path / "out" / FIGURES_DIR / f"{stem}.png").is_file() for stem in PLOTS)


def test_a_directory_that_is_not_a_dataset_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path), "--no-progress"])
    assert exit_info.value.code == 2  # the caller's input, not damaged data
    assert re.search(rf"error: {re.escape(str(tmp_path))}: not a dataset", capsys.readouterr().err)
    assert not (tmp_path / CARD_FILE).exists()


def test_card_shows_the_budget_mode_and_the_env_steps_each_expert_trained(dataset, card):
    records = list(iter_records(dataset))
    budgets = _section(card[0], "Expert budgets")
    assert f"Level batches by `experts.budget_mode`: fixed: {len(records)}." in budgets
    trained = [level.trained_env_steps for r in records for level in r.levels if level.outcome.is_trained]
    assert set(trained) == {256}  # the fixed mode trains every level for the split's budget
    assert f"mean 256, 100.0 % of the budget (min 256, max 256), {256 * len(trained):,} in all" in budgets
