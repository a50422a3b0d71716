"""The proof-of-use dataset's own figures, end to end: its config and data fingerprint (what regenerates the same
bytes), level outcomes, solved share, bytes per transition, and each stretch of generation (wall time, level batches
committed, kept levels, kept levels per hour) with the whole's kept levels per machine-hour.

    python -m benchmarks.proof_dataset --dataset DATASET --stretches STRETCHES_LOG \\
        --json benchmarks/results/proof_dataset_1M_s.json

`STRETCHES_LOG` holds one `stretch start <UTC time> levels=<split.num_levels> commit=<commit>` line when a stretch of
`kforge run` starts and one `stretch end <UTC time> rc=<exit code>` line when it ends (a resumed run is a new
stretch). A level batch belongs to the stretch during which its commit record was written (the record file's
modification time, so the dataset must be a local directory).
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import sys
from pathlib import Path

from omegaconf import OmegaConf

from benchmarks.machine import describe_machine, provenance
from kforge.pipeline.reading import collect_stats
from kforge.pipeline.storage import iter_records, record_key

SECONDS_PER_HOUR = 3600.0
STRETCH_LINE = re.compile(r"stretch (start|end) (\S+)(.*)")


def read_stretches(text: str) -> list[dict]:
    """The stretches of a log: start and end times (UTC, ISO 8601), the start line's fields and the exit code as
    logged; an unfinished last stretch has no end."""
    stretches: list[dict] = []
    for line in text.splitlines():
        match = STRETCH_LINE.match(line.strip())
        if not match:
            continue
        kind, moment, rest = match.groups()
        fields = dict(field.split("=", 1) for field in rest.split())
        if kind == "start":
            stretches.append({"start": moment, "end": None, **fields})
        elif stretches and stretches[-1]["end"] is None:
            stretches[-1]["end"], stretches[-1]["rc"] = moment, fields.get("rc")
    return stretches


def _epoch(moment: str) -> float:
    return datetime.datetime.fromisoformat(moment.replace("Z", "+00:00")).timestamp()


def stretch_figures(stretches: list[dict], commits: list[tuple[float, int]], now: float) -> list[dict]:
    """Per stretch: wall seconds, level batches committed and kept levels in it, kept levels per hour; `commits` are
    (commit time, kept levels) per level batch."""
    rows = []
    for stretch in stretches:
        start = _epoch(stretch["start"])
        end = now if stretch["end"] is None else _epoch(stretch["end"])
        inside = [kept for moment, kept in commits if start <= moment <= end]
        seconds = end - start
        rows.append(
            stretch
            | {
                "wall_seconds": round(seconds, 1),
                "level_batches": len(inside),
                "kept_levels": sum(inside),
                "kept_levels_per_hour": round(sum(inside) / seconds * SECONDS_PER_HOUR, 1) if seconds > 0 else None,
            }
        )
    return rows


def batch_commits(dataset: Path) -> list[tuple[float, int]]:
    """(commit time, kept levels) of every committed level batch of a local dataset."""
    return [
        ((dataset / record_key(record.shard, record.batch)).stat().st_mtime, record.num_kept)
        for record in iter_records(str(dataset))
    ]


def dataset_figures(dataset: Path) -> dict:
    """The dataset's config, fingerprint, level outcomes and storage figures (as `kforge stats` counts them)."""
    stats = collect_stats(dataset, show_progress=False)
    outcomes = {str(outcome): count for outcome, count in sorted(stats.outcomes.items(), key=lambda item: str(item[0]))}
    trained, kept = stats.trained, outcomes.get("kept", 0)
    config = OmegaConf.to_container(OmegaConf.load(dataset / "config.yaml"))
    config["output_dir"] = dataset.name  # the folder, not the machine's path to it
    return {
        "config": config,
        "data_fingerprint": stats.fingerprint,
        "level_batches": {"committed": stats.batches_committed, "total": stats.batches_total},
        "levels": {
            "sampled": stats.sampled,
            "filtered": stats.filtered,
            "trained": trained,
            "solved": stats.solved,
            "outcomes": outcomes,
        },
        "solved_share_of_trained": round(stats.solved / trained, 4) if trained else None,
        "kept_share_of_sampled": round(kept / stats.sampled, 4) if stats.sampled else None,
        "stored_transitions": stats.stored_transitions,
        "bytes": {"data": stats.data_bytes, "records": stats.manifest_bytes, "total": stats.total_bytes},
        "data_bytes_per_transition": round(stats.data_bytes / stats.stored_transitions, 2)
        if stats.stored_transitions
        else None,
        "worker_seconds": {phase: round(value, 1) for phase, value in stats.seconds.items()},
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True, help="a local dataset made by kforge run")
    parser.add_argument("--stretches", type=Path, required=True, help="the generation's stretch log")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)

    figures = dataset_figures(args.dataset)
    stretches = stretch_figures(
        read_stretches(args.stretches.read_text()),
        batch_commits(args.dataset),
        datetime.datetime.now(datetime.UTC).timestamp(),
    )
    hours = sum(row["wall_seconds"] for row in stretches) / SECONDS_PER_HOUR
    kept_in_stretches = sum(row["kept_levels"] for row in stretches)
    command = [
        {str(args.dataset): "DATASET", str(args.stretches): "STRETCHES_LOG"}.get(argument, argument)
        for argument in sys.argv
    ]
    report = provenance(command) | {  # the dataset named by its folder: no machine path in the report
        "machine": describe_machine(),
        "dataset": args.dataset.name,
        **figures,
        "stretches": stretches,
        "wall_hours": round(hours, 3),
        "kept_levels_per_machine_hour": round(kept_in_stretches / hours, 1) if hours else None,
    }
    for row in stretches:
        print(
            f"{row['start']}  {row['wall_seconds'] / 60:6.1f} min  {row['level_batches']:4d} batches  "
            f"{row['kept_levels']:4d} kept  {row['kept_levels_per_hour'] or 0:6.1f} kept/h"
        )
    levels = figures["levels"]
    print(
        f"{figures['level_batches']['committed']}/{figures['level_batches']['total']} level batches, "
        f"{levels['sampled']} sampled, {levels['outcomes'].get('kept', 0)} kept, solved share "
        f"{figures['solved_share_of_trained']}, {figures['data_bytes_per_transition']} B/transition, "
        f"{report['kept_levels_per_machine_hour']} kept levels per machine-hour over {hours:.2f} h"
    )
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
