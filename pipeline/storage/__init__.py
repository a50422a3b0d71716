"""The dataset's storage format: layout of the stored fields, state coding, zarr v3 shard store, commit records,
the writer of a level batch and verification.

Public surface: what generation, reading, Kinetix interop and the command line use.
"""

from kforge.pipeline.storage.growth import grow_dataset
from kforge.pipeline.storage.layout import (
    ACTION,
    ACTION_MASK,
    DONE,
    STATE_PREFIX,
    VALID,
    DatasetError,
    Layout,
    make_layout,
    static_to_json,
    unflatten_state,
)
from kforge.pipeline.storage.lease import Lease, LeaseLost, commit_age_limit
from kforge.pipeline.storage.manifest import (
    all_committed,
    iter_records,
    read_record_json,
    read_record_sized,
    record_key,
    shard_name,
)
from kforge.pipeline.storage.records import (
    FILTERED_PREFIX,
    PROVENANCE,
    BatchRecord,
    Outcome,
)
from kforge.pipeline.storage.repair import require_intact, withdraw_bad_batches
from kforge.pipeline.storage.shard_store import (
    CONFIG_FILE,
    DATA_DIR,
    MANIFEST_DIR,
    DatasetSpec,
    Geometry,
    create_dataset,
    open_dataset,
)
from kforge.pipeline.storage.store import Store, StoreError, is_remote, join, open_store
from kforge.pipeline.storage.verify import format_report, verify_dataset
from kforge.pipeline.storage.writer import (
    BatchTrajectories,
    ShardWriter,
    commit_level_batch,
    learning_curves,
)

__all__ = [
    "BatchRecord",
    "Outcome",
    "Lease",
    "LeaseLost",
    "Store",
    "StoreError",
    "is_remote",
    "join",
    "open_store",
    "commit_age_limit",
    "ACTION",
    "ACTION_MASK",
    "CONFIG_FILE",
    "DATA_DIR",
    "DONE",
    "FILTERED_PREFIX",
    "MANIFEST_DIR",
    "PROVENANCE",
    "STATE_PREFIX",
    "VALID",
    "BatchTrajectories",
    "ShardWriter",
    "commit_level_batch",
    "DatasetError",
    "DatasetSpec",
    "Geometry",
    "Layout",
    "all_committed",
    "create_dataset",
    "format_report",
    "grow_dataset",
    "iter_records",
    "learning_curves",
    "make_layout",
    "open_dataset",
    "read_record_json",
    "read_record_sized",
    "record_key",
    "require_intact",
    "shard_name",
    "static_to_json",
    "unflatten_state",
    "verify_dataset",
    "withdraw_bad_batches",
]
