"""benchmarks/results/ holds the reports the docs cite, and only those: every report is named by README.md or a page
of docs/, and every report a doc names is there."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.smoke

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"
COMMIT_KEYS = {"commit", "commits", "trees", "committed_in"}
"""How a report names the code it measured: `commit` (benchmarks.machine.provenance), the commits of the trees it
compared (`commits`, `trees`), or for a report written before reports recorded it, `committed_in`: the commit that
last wrote the report."""
REPORT_NAME = re.compile(r"(?:benchmarks/results/)?([A-Za-z0-9.-]*_[A-Za-z0-9_.-]*\.json)")
"""A report as a doc names it: a JSON file name with an underscore (scratch outputs in commands, such as
`chaos.json` or `kx-random-s.json`, have none), with or without its folder."""


def docs() -> dict[str, str]:
    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    return {page.relative_to(REPO).as_posix(): page.read_text() for page in pages}


def cited_reports(text: str) -> set[str]:
    return set(REPORT_NAME.findall(text))


def test_a_report_is_found_with_or_without_its_folder_and_scratch_outputs_are_not():
    text = "see `benchmarks/results/engine_a.json` and `fidelity_b_c.json`; `--out chaos.json`, `kx-random-s.json`"
    assert cited_reports(text) == {"engine_a.json", "fidelity_b_c.json"}


def test_every_report_is_cited_by_a_doc():
    cited = set().union(*map(cited_reports, docs().values()))
    uncited = sorted(path.name for path in RESULTS.iterdir() if path.name not in cited)
    assert uncited == [], f"reports no doc cites (remove them, or cite them where their figures are stated): {uncited}"


def test_every_report_a_doc_cites_exists():
    cited = [(page, name) for page, text in docs().items() for name in cited_reports(text)]
    missing = sorted(f"{page}: {name}" for page, name in cited if not (RESULTS / name).exists())
    assert missing == []


def names_its_commit(report: dict) -> bool:
    """Whether a report names the code it measured: a key of COMMIT_KEYS, or its `provenance` record's commit."""
    return bool(COMMIT_KEYS & set(report)) or bool(report.get("provenance", {}).get("commit"))


def test_every_report_records_the_commit_it_measured():
    unrecorded = sorted(
        path.name for path in RESULTS.glob("*.json") if not names_its_commit(json.loads(path.read_text()))
    )
    assert unrecorded == []
