"""Data-generation pipeline (Ray workers, shard storage: not implemented yet); so far only the `kforge` command line."""
