"""The command line as a whole: every subcommand documents the same exit codes and global options, and reports an
error in one line with its code (the traceback only with --debug)."""

from __future__ import annotations

import json

import pytest

from kforge.env.level_files import LevelFileError
from kforge.pipeline.cli import DATASET_METADATA, EXIT_USAGE, main

pytestmark = pytest.mark.smoke

PIPELINE_SUBCOMMANDS = (
    ["run"],
    ["verify"],
    ["stats"],
    ["export"],
    ["levels", "sample"],
    ["levels", "export"],
    ["render"],
    ["demo"],
)


def test_the_dataset_metadata_file_is_the_one_storage_writes():
    from kforge.pipeline.storage.shard_store import GROUP_METADATA

    assert DATASET_METADATA == GROUP_METADATA


@pytest.mark.parametrize("subcommand", PIPELINE_SUBCOMMANDS, ids=" ".join)
def test_every_subcommand_help_lists_the_exit_codes_and_the_global_options(subcommand, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*subcommand, "--help"])
    assert exit_info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "exit codes: 0 success; 1 the data has a problem or the job is incomplete; 2 usage" in text
    assert "130 interrupted (SIGINT/SIGTERM)" in text
    assert "--debug" in text and "--verbose" in text


def _one_line_error(capsys, argv: list[str], code: int) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == code
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in captured.err, captured.err
    return lines[0]


def test_render_reports_a_missing_or_malformed_level_file_in_one_line(tmp_path, capsys):
    missing = tmp_path / "missing.json"
    assert "missing.json" in _one_line_error(capsys, ["render", str(missing)], EXIT_USAGE)
    malformed = tmp_path / "malformed.json"
    malformed.write_text(json.dumps({"env_state": {}}))
    assert str(malformed) in _one_line_error(capsys, ["render", str(malformed)], EXIT_USAGE)
    not_json = tmp_path / "not.json"
    not_json.write_text("{")
    assert "not valid JSON" in _one_line_error(capsys, ["render", str(not_json), "--verbose"], EXIT_USAGE)


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(LevelFileError, match="no such level file or bundled level"):
        main(["render", str(tmp_path / "missing.json"), "--debug"])


def test_the_same_kind_of_failure_has_the_same_code_in_every_subcommand(tmp_path, capsys):
    """A path that is not a dataset is an input error (2), whichever subcommand is given it."""
    not_a_dataset, missing = str(tmp_path), str(tmp_path / "missing")
    for dataset_argv in (
        ["verify"],
        ["stats"],
        ["export", "--format", "kinetix"],
        ["bc", "train"],
    ):
        tail = [str(tmp_path / "out")] if dataset_argv[0] == "export" else []
        assert f"{not_a_dataset}: not a dataset (no data/zarr.json)" in _one_line_error(
            capsys, [*dataset_argv, not_a_dataset, *tail], EXIT_USAGE
        )
        assert f"{missing}: no such dataset directory" in _one_line_error(
            capsys, [*dataset_argv, missing, *tail], EXIT_USAGE
        )
    bad_key = "split.num_levelz=3"
    for argv in (["run", "1M/s", bad_key, "--print-config"], ["levels", "export", "1M/s", "0", bad_key]):
        assert "unknown key split.num_levelz (did you mean split.num_levels?)" in _one_line_error(
            capsys, argv, EXIT_USAGE
        )
