"""Interop with Kinetix-Offline: export of a dataset as Kinetix's zarr v2 shards, and loading levels back from them.

Public surface: the exporter and the level loader.
"""

from kforge.pipeline.kinetix.export import DEFAULT_TRAJECTORIES_PER_SHARD, export_kinetix
from kforge.pipeline.kinetix.importer import load_kinetix_levels

__all__ = [
    "DEFAULT_TRAJECTORIES_PER_SHARD",
    "export_kinetix",
    "load_kinetix_levels",
]
