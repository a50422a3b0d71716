"""The dataset pipeline over env and agents: one subpackage per concern, each using only those listed before it:

- `pipeline.storage`: the dataset's format (layout, state coding, shard store, commit records, writer, verify, lease);
- `pipeline.reading`: the batch loader and the dataset card;
- `pipeline.generation`: job configs, level batches, coordinator, workers, the run driver, tracking;
- `pipeline.kinetix`: Kinetix-Offline export and level import;
- `pipeline.learning`: behaviour cloning on a dataset and the evaluation of its policy;
- `pipeline.cli`: the `kforge` command.

Each subpackage's `__init__` names its public surface; the others import only from it.
"""
