"""Stages of a long benchmark, each kept in `WORK_DIR/stages/<stage>.json` once done, so that an interrupted run
resumes at the stage it stopped in."""

from __future__ import annotations

import json
import os
from pathlib import Path


def stage(work_dir: Path, name: str, settings: dict, compute, log) -> dict:
    """The result of stage `name`: read from its file when done with the same settings, else computed and kept."""
    path = work_dir / "stages" / f"{name}.json"
    if path.is_file():
        kept = json.loads(path.read_text())
        if kept["settings"] == settings:
            log(f"{name}: done before, read from {path}")
            return kept["result"]
        log(f"{name}: settings changed since it was done, running it again")
    log(f"{name}: running")
    result = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps({"settings": settings, "result": result}, indent=1))
    os.replace(temporary, path)
    return result
