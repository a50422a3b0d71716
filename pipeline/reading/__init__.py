"""Reading a dataset: the batch loader that feeds learners, and the dataset card (counts, bytes, timings, plots).

Public surface: the loader and the card.
"""

from kforge.pipeline.reading.loader import WHOLE_OBJECT_BYTES, ActionEnvStateMask, TrajectoryDatasetManager
from kforge.pipeline.reading.stats import CARD_FILE, FIGURES_DIR, SHARDS_FILE, DatasetStats, collect_stats, write_card

__all__ = [
    "CARD_FILE",
    "FIGURES_DIR",
    "SHARDS_FILE",
    "WHOLE_OBJECT_BYTES",
    "ActionEnvStateMask",
    "DatasetStats",
    "TrajectoryDatasetManager",
    "collect_stats",
    "write_card",
]
