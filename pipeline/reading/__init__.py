"""Reading a dataset: the batch loader that feeds learners, and the dataset card (counts, bytes, timings, plots).

Public surface: the loader and the card.
"""

from kforge.pipeline.reading.loader import TrajectoryDatasetManager
from kforge.pipeline.reading.stats import collect_stats, write_card

__all__ = [
    "TrajectoryDatasetManager",
    "collect_stats",
    "write_card",
]
