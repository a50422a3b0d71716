"""The data-generation pipeline, in four layers over env and agents, with the command line on top:

- `pipeline.storage`: the dataset's format (layout, state coding, shard store, commit records, writer, verify);
- `pipeline.generation`: job configs, level batches, coordinator, Ray workers, the run driver, tracking;
- `pipeline.reading`: the batch loader and the dataset card;
- `pipeline.kinetix`: Kinetix-Offline export and level import;
- `pipeline.cli`: the `kforge` command.

Each subpackage's `__init__` names its public surface; the others import only from it.
"""
