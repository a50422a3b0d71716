"""`kforge stats DATASET [--out DIR]`: a dataset card (markdown and PNG plots) of a generated dataset.

Everything comes from the dataset directory: the commit records (level outcomes, expert success rates, episode
lengths, learning curves, per-phase wall times), the zarr attributes (data fingerprint), config.yaml (the resolved
config with its scale) and the sizes of the stored objects (as the commit records give them; objects they do not
size are read once). The dataset and the card's folder may be local paths or object-store URLs (`s3://`, `gs://`).
Only committed level batches count, so a partial dataset gets a card of what it holds so far.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import io
import os
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from tqdm import tqdm

from kforge.pipeline.storage import (
    CONFIG_FILE,
    DATA_DIR,
    FILTERED_PREFIX,
    MANIFEST_DIR,
    DatasetError,
    Outcome,
    Store,
    all_committed,
    open_dataset,
    open_store,
    read_record_sized,
    record_key,
)

CARD_FILE = "card.md"
"""Name of the card in the output folder."""

FIGURES_DIR = "card"
"""Folder of the card's PNG plots, beside the card."""

PHASES = ("sample_and_filter", "train", "collect", "write")
"""Phases of a level batch timed in its record's provenance; "total" spans them all."""

SOLVED_ABOVE = 0.0
"""[-] a trained level counts as solved when its selected expert's evaluation success rate exceeds this."""

CURVE_BAND = (0.1, 0.9)
"""[-] quantiles over levels bounding the shaded band of the learning-curve plot."""

SUCCESS_RATE_BINS = 20
"""Histogram bins over the success rate range [0, 1]."""

EPISODE_LENGTH_BINS = 32
"""Histogram bins over [0, window steps] (fewer for short windows: at least one env step per bin)."""

FIGURE_SIZE = (6.4, 4.0)
"""[inch] width and height of each plot."""

FIGURE_DPI = 100
"""[px/inch] plot resolution (640 x 400 px)."""

PROGRESS_MIN_RECORDS = 200
"""Reading at least this many commit records shows a progress bar."""

MAX_CURVE_LEVELS = 100_000
"""Learning curves held for the plot: those of trained levels whose id is a multiple of a stride chosen so that at
most this many slots qualify (bounds memory for release-size datasets; small datasets keep every curve)."""

TRAINED_OUTCOMES = (Outcome.KEPT, Outcome.UNSOLVED, Outcome.FAILED)
"""Outcomes of levels whose expert was trained and judged."""

WINDOW_OUTCOMES = (Outcome.KEPT, Outcome.UNSOLVED)
"""Outcomes whose windows' episode lengths are plotted."""

KEY_CONFIG_VALUES = (
    "split.name",
    "split.size",
    "split.seed",
    "split.num_levels",
    "split.expert_budget",
    "experts.budget_mode",
    "scale",
    "work.levels_per_shard",
    "work.levels_per_batch",
    "filter.enabled",
    "filter.noop_steps",
    "env.dense_reward_scale",
    "env.physics",
    "ppo.num_envs",
    "ppo.num_steps",
    "ppo.update_epochs",
    "ppo.num_minibatches",
    "ppo.learning_rate",
    "ppo.hidden_size",
    "ppo.num_hidden_layers",
    "collect.window_steps",
    "collect.greedy",
    "ray.num_workers",
)
"""Config keys listed on the card (all keys: config.yaml in the dataset)."""


@dataclasses.dataclass
class DatasetStats:
    """What a card reports, gathered from one dataset directory."""

    root: str  # where the dataset lives (a local path or a URL)
    split: str
    fingerprint: str
    config: dict  # resolved config (config.yaml), or the data-defining sections if that file is missing
    batches_total: int
    batches_committed: int
    levels_per_batch: int
    window_steps: int  # env steps per stored trajectory
    outcomes: collections.Counter  # outcome -> levels, padding slots left out
    success_rates: np.ndarray  # (trained levels,) f32 [-] the selected expert's evaluation success rate (NaN: none)
    episode_lengths: dict[str, collections.Counter]  # outcome in WINDOW_OUTCOMES -> {length [env steps]: episodes}
    curve_env_steps: list[int] | None  # x axis of the learning curves (None: the records have none)
    curves: np.ndarray  # (held levels, points) f32 [-] success-rate curves of every curve_stride-th trained level
    curve_stride: int  # curves are held for trained levels whose id is a multiple of this
    budget_modes: collections.Counter  # experts.budget_mode -> level batches trained with it (None: not recorded)
    trained_env_steps: np.ndarray  # (trained levels with it recorded,) int [env steps] each level's training used
    seconds: dict[str, float]  # summed wall time per phase and "total" over the timed level batches
    timed_batches: int  # level batches whose record holds provenance wall times
    workers: list[str]
    data_bytes: int  # files under data/ (the arrays)
    manifest_bytes: int  # files under manifest/ (the commit records)
    shards: dict[int, collections.Counter]  # shard -> its counts (SHARD_COLUMNS keys) and seconds per phase

    @property
    def sampled(self) -> int:
        return sum(self.outcomes.values())

    @property
    def filtered(self) -> dict[str, int]:
        """Filter reason -> levels dropped for it."""
        return {
            outcome.removeprefix(FILTERED_PREFIX): count
            for outcome, count in sorted(self.outcomes.items())
            if outcome.startswith(FILTERED_PREFIX)
        }

    @property
    def trained(self) -> int:
        return sum(self.outcomes[outcome] for outcome in TRAINED_OUTCOMES)

    @property
    def solved(self) -> int:
        """Trained levels whose selected expert's evaluation success rate exceeds `SOLVED_ABOVE`."""
        return int(np.sum(self.success_rates > SOLVED_ABOVE))

    @property
    def stored_transitions(self) -> int:
        return self.outcomes[Outcome.KEPT] * self.window_steps

    @property
    def total_bytes(self) -> int:
        return self.data_bytes + self.manifest_bytes


NOT_RECORDED = "(not recorded)"
"""Card entry of a config key the dataset's config does not hold (a dataset without config.yaml)."""


def _config_value(config: dict, key: str, default=None):
    value = config
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return default
        value = value[part]
    return value


def _yaml_scalar(value) -> str:
    """A config value as config.yaml writes it (null, true, false)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _float(value: float | None) -> float:
    """A JSON number of a record as a float; None (a NaN when written) back to NaN."""
    return np.nan if value is None else float(value)


def stored_bytes(store: Store, prefix: str, known: Mapping[str, int | None]) -> int:
    """Total size of the objects below `prefix` (0 if there are none): the size in `known` (recorded in the commit
    records) of each key it names, the others read (tensorstore lists keys without sizes)."""
    return sum(size if (size := known.get(key)) is not None else store.size(key) for key in store.list(prefix))


class _RecordTally:
    """The figures of a dataset's commit records, added record by record."""

    def __init__(self, root: str, curve_stride: int):
        self.root = root
        self.curve_stride = curve_stride
        self.outcomes = collections.Counter()
        self.rates: list[float] = []
        self.curves: list[list[float]] = []
        self.curve_steps: list | None = None
        self.workers: set = set()
        self.budget_modes = collections.Counter()
        self.trained_steps: list = []
        self.lengths = {outcome: collections.Counter() for outcome in WINDOW_OUTCOMES}
        self.seconds = collections.Counter()
        self.timed = 0
        self.shards: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)

    def add(self, shard: int, batch: int, record) -> None:
        """Count a batch's commit record."""
        shard_counts = self.shards[shard]
        shard_counts["batches"] += 1
        self.budget_modes[record.budget_mode] += 1
        for level in record.levels:
            if level.outcome != Outcome.PADDING:
                self._add_level(level, shard_counts)
        steps = None if record.curve_env_steps is None else list(record.curve_env_steps)
        if steps is not None:
            if self.curve_steps is not None and steps != self.curve_steps:
                raise DatasetError(
                    f"{self.root}: shard {shard} batch {batch} has other learning-curve steps than the rest"
                )
            self.curve_steps = steps
        provenance = record.provenance
        if provenance and "total" in provenance.get("seconds", {}):
            self.timed += 1
            self.seconds.update(provenance["seconds"])
            shard_counts.update({f"seconds/{phase}": value for phase, value in provenance["seconds"].items()})
            self.workers.add(provenance.get("worker", "?"))

    def _add_level(self, level, shard_counts: collections.Counter) -> None:
        outcome = level.outcome
        self.outcomes[outcome] += 1
        shard_counts["sampled"] += 1
        shard_counts[outcome] += 1
        trained = outcome.is_trained
        shard_counts["trained"] += trained
        shard_counts["solved"] += trained and _float(level.expert_success_rate) > SOLVED_ABOVE
        if outcome.has_window:
            self.lengths[outcome].update(level.episode_lengths)
        if trained:
            self.rates.append(_float(level.expert_success_rate))
            if level.trained_env_steps is not None:
                self.trained_steps.append(level.trained_env_steps)
            if level.curve_success_rate is not None and level.level_id % self.curve_stride == 0:
                self.curves.append([_float(value) for value in level.curve_success_rate])


def _dataset_config(dataset) -> dict:
    """The generation config stored with the dataset, or the data config of its attributes."""
    config_text = dataset.store.read(CONFIG_FILE)
    if config_text is not None:
        return OmegaConf.to_container(OmegaConf.create(config_text.decode()))
    return dict(dataset.spec.attributes.get("data_config", {}))


def collect_stats(root: str | os.PathLike, show_progress: bool = True) -> DatasetStats:
    """Read a dataset's records, attributes and file sizes; `DatasetError` if `root` is not a dataset."""
    dataset = open_dataset(root)
    store, root = dataset.store, dataset.root
    attributes = dataset.spec.attributes
    config = _dataset_config(dataset)
    batches = [(shard, batch) for shard, found in all_committed(store).items() for batch in found]
    tally = _RecordTally(root, -(-dataset.geometry.num_slots // MAX_CURVE_LEVELS))
    progress = show_progress and len(batches) >= PROGRESS_MIN_RECORDS
    sizes: dict[str, int | None] = {}
    for shard, batch in tqdm(batches, desc="commit records", unit="record", disable=not progress):
        record, sizes[record_key(shard, batch)] = read_record_sized(store, shard, batch)
        sizes.update(record.object_sizes)
        tally.add(shard, batch, record)
    return DatasetStats(
        root=root,
        split=dataset.spec.split,
        fingerprint=str(attributes.get("data_fingerprint", "unknown")),
        config=config,
        batches_total=dataset.geometry.num_batches,
        batches_committed=len(batches),
        levels_per_batch=dataset.geometry.levels_per_batch,
        window_steps=dataset.layout.num_steps,
        outcomes=tally.outcomes,
        success_rates=np.asarray(tally.rates, np.float32),
        episode_lengths=tally.lengths,
        curve_env_steps=tally.curve_steps,
        curves=np.asarray(tally.curves, np.float32).reshape(len(tally.curves), len(tally.curve_steps or ())),
        curve_stride=tally.curve_stride,
        budget_modes=tally.budget_modes,
        trained_env_steps=np.asarray(tally.trained_steps, np.int64),
        seconds=dict(tally.seconds),
        timed_batches=tally.timed,
        workers=sorted(tally.workers),
        data_bytes=stored_bytes(store, f"{DATA_DIR}/", sizes),
        manifest_bytes=stored_bytes(store, f"{MANIFEST_DIR}/", sizes),
        shards=dict(tally.shards),
    )


SHARDS_FILE = "shards.csv"
"""Per-shard table next to the plots: one row per shard with committed level batches."""


def shard_columns(stats: DatasetStats) -> list[str]:
    """Columns of the per-shard table: counts by outcome, then summed wall seconds per phase."""
    present = set().union(*stats.shards.values()) if stats.shards else set()
    filtered = sorted(key for key in present if key.startswith(FILTERED_PREFIX))
    timings = [f"seconds/{phase}" for phase in (*PHASES, "total") if f"seconds/{phase}" in present]
    return ["batches", "sampled", *filtered, "trained", "solved", *TRAINED_OUTCOMES, *timings]


def shard_table(stats: DatasetStats) -> str:
    """The per-shard counts and timings as CSV text (seconds with millisecond resolution)."""
    columns = shard_columns(stats)
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(["shard", *columns])
    for shard, counts in sorted(stats.shards.items()):
        writer.writerow([shard, *(_csv_value(counts[column]) for column in columns)])
    return text.getvalue()


def _csv_value(value: float) -> str:
    return str(value) if float(value).is_integer() else f"{value:.3f}"


# ------------------------------------------------------------------------------------------------------ card


def _share(part: float, whole: float) -> str:
    return f"{100 * part / whole:.1f} %" if whole else "n/a"


def _bytes(count: float) -> str:
    """Bytes with a decimal unit (kB = 1e3 B, as the release's sizes)."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= size:
            return f"{count / size:.2f} {unit}"
    return f"{count:.0f} B"


def _per(count: float, items: int) -> str:
    return f"{count / items:.1f} B" if items else "n/a (nothing stored)"


def count_rows(stats: DatasetStats) -> list[tuple[str, int, str]]:
    """(label, levels, meaning) rows of the card's counts table."""
    outcomes = stats.outcomes
    rows = [("sampled", stats.sampled, "levels of the split in committed level batches")]
    rows += [
        (f"filtered: {reason}", count, "dropped by the trivial-level filter before training")
        for reason, count in stats.filtered.items()
    ]
    rows += [
        ("trained", stats.trained, "an expert was trained on the level"),
        ("solved", stats.solved, f"trained, and the selected expert's evaluation success rate > {SOLVED_ABOVE:g}"),
        ("kept", outcomes[Outcome.KEPT], "the expert's window was stored: every episode ending in it is a success"),
        ("unsolved", outcomes[Outcome.UNSOLVED], "trained, window not stored"),
        ("failed", outcomes[Outcome.FAILED], "training or rollout produced non-finite values"),
    ]
    return rows


def card_markdown(stats: DatasetStats, figures: dict[str, str]) -> str:
    """The card's markdown; `figures` maps a plot title to its path relative to the card."""
    scale = _config_value(stats.config, "scale")
    complete = "complete" if stats.batches_committed == stats.batches_total else "partial"
    lines = [
        f"# Dataset card: {stats.split}" + (f" (scale {scale})" if scale else ""),
        "",
        f"- Directory: `{stats.root}`",
        f"- Data fingerprint (hash of the data-defining config and the physics parameters): `{stats.fingerprint}`",
        f"- Level batches committed: {stats.batches_committed:,} of {stats.batches_total:,} ({complete})",
        "",
        "## Levels",
        "",
        "| count | levels | share of sampled | meaning |",
        "|---|---:|---:|---|",
    ]
    sampled = stats.sampled
    lines += [
        f"| {label} | {count:,} | {_share(count, sampled)} | {meaning} |" for label, count, meaning in count_rows(stats)
    ]
    kept = stats.outcomes[Outcome.KEPT]
    transitions = stats.stored_transitions
    lines += [
        "",
        "## Storage",
        "",
        "| what | bytes | |",
        "|---|---:|---|",
        f"| data arrays (data/) | {stats.data_bytes:,} | {_bytes(stats.data_bytes)} |",
        f"| commit records (manifest/) | {stats.manifest_bytes:,} | {_bytes(stats.manifest_bytes)} |",
        f"| total | {stats.total_bytes:,} | {_bytes(stats.total_bytes)} |",
        "",
        f"Stored transitions: {transitions:,} ({kept:,} kept levels x {stats.window_steps} env steps). Per stored "
        f"transition: {_per(stats.data_bytes, transitions)} of data arrays, {_per(stats.total_bytes, transitions)} "
        f"in total; per kept level: {_bytes(stats.total_bytes / kept) if kept else 'n/a'} in total.",
        "",
        "## Expert budgets",
        "",
        *_budget_lines(stats),
        "",
        "## Time",
        "",
    ]
    lines += _time_lines(stats)
    lines += ["", f"Counts and timings per shard: `{FIGURES_DIR}/{SHARDS_FILE}`."]
    lines += ["", "## Config", "", "| key | value |", "|---|---|"]
    lines += [
        f"| {key} | {_yaml_scalar(_config_value(stats.config, key, NOT_RECORDED))} |" for key in KEY_CONFIG_VALUES
    ]
    lines += ["", f"Every key with its type and meaning: `{CONFIG_FILE}` in the dataset directory.", "", "## Plots", ""]
    lines += [f"![{title}]({path})" for title, path in figures.items()]
    return "\n".join(lines) + "\n"


def _budget_lines(stats: DatasetStats) -> list[str]:
    """Budget modes of the level batches, and the env steps their experts trained."""
    modes = ", ".join(
        f"{mode or 'not recorded (fixed, before budget modes)'}: {count:,}"
        for mode, count in sorted(stats.budget_modes.items(), key=lambda item: str(item[0]))
    )
    lines = [f"Level batches by `experts.budget_mode`: {modes or 'none committed'}."]
    steps, budget = stats.trained_env_steps, _config_value(stats.config, "split.expert_budget")
    if len(steps):
        share = f", {_share(steps.mean(), budget)} of the budget" if budget else ""
        lines += [
            "",
            f"Env steps trained per trained level: mean {steps.mean():,.0f}{share} (min {steps.min():,}, max "
            f"{steps.max():,}), {steps.sum():,} in all over {len(steps):,} levels.",
        ]
    return lines


def _time_lines(stats: DatasetStats) -> list[str]:
    if not stats.timed_batches:
        return ["No level batch records wall times (provenance)."]
    seconds, total = stats.seconds, stats.seconds.get("total", 0.0)
    lines = [
        f"Summed over {stats.timed_batches:,} level batches on {len(stats.workers)} worker(s) "
        f"({', '.join(stats.workers)}), each worker's first compilations included; workers run in parallel, so the "
        "job's wall time is shorter.",
        "",
        "| phase | seconds | share of total | seconds per level batch |",
        "|---|---:|---:|---:|",
    ]
    for phase in (*PHASES, "total"):
        value = seconds.get(phase, 0.0)
        lines.append(f"| {phase} | {value:,.1f} | {_share(value, total)} | {value / stats.timed_batches:,.2f} |")
    train = seconds.get("train", 0.0)
    trained_steps = (
        stats.timed_batches * stats.levels_per_batch * (_config_value(stats.config, "split.expert_budget") or 0)
        if None in stats.budget_modes or "fixed" in stats.budget_modes
        else int(stats.trained_env_steps.sum())
    )
    lines += [
        "",
        f"Train + collect: {_share(train + seconds.get('collect', 0.0), total)} of the total.",
    ]
    if train and trained_steps:
        lines.append(
            f"Expert training throughput: {trained_steps / train:,.0f} env steps/s per worker (every slot of a level "
            "batch is trained, filtered and padding levels included)."
        )
    return lines


# ----------------------------------------------------------------------------------------------------- plots


def _figure():
    from matplotlib.figure import Figure

    figure = Figure(figsize=FIGURE_SIZE, dpi=FIGURE_DPI, layout="constrained")
    return figure, figure.subplots()


def _no_data(axes, message: str) -> None:
    axes.text(0.5, 0.5, message, ha="center", va="center", transform=axes.transAxes)


def plot_outcomes(stats: DatasetStats, out: Path | io.BytesIO) -> None:
    """Bar chart: levels per outcome (kept, unsolved, failed, each filter reason)."""
    figure, axes = _figure()
    outcomes = stats.outcomes
    labels = [*TRAINED_OUTCOMES] + [f"{FILTERED_PREFIX}{reason}" for reason in stats.filtered]
    counts = [outcomes[label] for label in labels]
    colours = ["tab:green", "tab:orange", "tab:red"] + ["tab:gray"] * len(stats.filtered)
    bars = axes.bar(labels, counts, color=colours)
    axes.bar_label(bars)
    axes.set_ylabel("levels")
    axes.set_title(f"Outcomes of {stats.sampled:,} sampled levels (solved in training: {stats.solved:,})")
    axes.tick_params(axis="x", labelrotation=20)
    figure.savefig(out, format="png")


def plot_success_rates(stats: DatasetStats, out: Path | io.BytesIO) -> None:
    """Histogram of the trained levels' selected experts' evaluation success rates."""
    figure, axes = _figure()
    known = stats.success_rates[np.isfinite(stats.success_rates)]
    if len(known):
        axes.hist(known, bins=np.linspace(0.0, 1.0, SUCCESS_RATE_BINS + 1), color="tab:blue")
    else:
        _no_data(axes, "no trained level has a success rate")
    axes.set_xlabel("selected expert's evaluation success rate")
    axes.set_ylabel("levels")
    unknown = len(stats.success_rates) - len(known)
    axes.set_title(f"{len(stats.success_rates):,} trained levels; {unknown:,} without a success rate")
    figure.savefig(out, format="png")


def plot_episode_lengths(stats: DatasetStats, out: Path | io.BytesIO) -> None:
    """Histograms of the episode lengths in the experts' windows: kept and unsolved levels."""
    figure, axes = _figure()
    bins = np.linspace(0, stats.window_steps, min(EPISODE_LENGTH_BINS, stats.window_steps) + 1)
    plotted = False
    for outcome, colour in zip(WINDOW_OUTCOMES, ("tab:green", "tab:orange"), strict=True):
        counts = stats.episode_lengths[outcome]
        if counts:
            label = f"{outcome} ({counts.total():,})"
            lengths, weights = list(counts), list(counts.values())
            axes.hist(lengths, bins=bins, weights=weights, histtype="step", linewidth=2, color=colour, label=label)
            plotted = True
    if plotted:
        axes.legend(title="level outcome (episodes)")
    else:
        _no_data(axes, "no episode ended in a kept or unsolved window")
    axes.set_xlabel("episode length [env steps]")
    axes.set_ylabel("episodes")
    axes.set_title(f"Episodes ending inside the {stats.window_steps}-step windows")
    figure.savefig(out, format="png")


def plot_learning_curves(stats: DatasetStats, out: Path | io.BytesIO) -> None:
    """Mean and quantile band over trained levels of the training success rate against env steps per level."""
    figure, axes = _figure()
    curves = stats.curves
    if stats.curve_env_steps and len(curves):
        steps = np.asarray(stats.curve_env_steps)
        with warnings.catch_warnings():  # points where no level ended an episode are NaN: left as gaps
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(curves, axis=0)
            low, high = np.nanquantile(curves, CURVE_BAND, axis=0)
        axes.fill_between(
            steps, low, high, alpha=0.3, color="tab:blue", label=f"{CURVE_BAND[0]:.0%}-{CURVE_BAND[1]:.0%} quantiles"
        )
        axes.plot(steps, mean, color="tab:blue", marker=".", label="mean")
        axes.legend(loc="best")
        axes.set_ylim(-0.02, 1.02)
    else:
        _no_data(axes, "no learning curves in the records")
    axes.set_xlabel("env steps per level")
    axes.set_ylabel("success rate of ended episodes")
    every = f", every {stats.curve_stride:,}th level id" if stats.curve_stride > 1 else ""
    axes.set_title(f"Training curves of {len(curves):,} trained levels{every}")
    figure.savefig(out, format="png")


PLOTS = {
    "outcomes": ("Level outcomes", plot_outcomes),
    "expert_success_rate": ("Expert success rates", plot_success_rates),
    "episode_lengths": ("Episode lengths", plot_episode_lengths),
    "learning_curves": ("Training curves", plot_learning_curves),
}
"""File stem -> (title on the card, function drawing it)."""


def write_card(stats: DatasetStats, out_dir: str | os.PathLike) -> str:
    """Write the plots into `out_dir`/card/ and the card into `out_dir`/card.md (a local folder or an object-store
    URL); returns where the card is."""
    store = open_store(out_dir)
    store.write(f"{FIGURES_DIR}/{SHARDS_FILE}", shard_table(stats).encode())
    figures = {}
    for stem, (title, plot) in PLOTS.items():
        relative = f"{FIGURES_DIR}/{stem}.png"
        image = io.BytesIO()
        plot(stats, image)
        store.write(relative, image.getvalue())
        figures[title] = relative
    store.write(CARD_FILE, card_markdown(stats, figures).encode())
    return store.url(CARD_FILE)
