"""The vocabulary of commit records: each level's outcome and the record keys that are not part of the data."""

KEPT = "kept"
"""Outcome of a level whose trajectory is stored."""

UNSOLVED = "unsolved"
"""Outcome of a trained level whose expert window was not successful."""

FAILED = "failed"
"""Outcome of a level whose training or rollout produced non-finite values (contained to that level)."""

PADDING = "padding"
"""Outcome of a slot past `split.num_levels` in the last shard."""

FILTERED_PREFIX = "filtered:"
"""Outcome prefix of a level dropped by the trivial-level filter, followed by the reason's name."""

PROVENANCE = "provenance"
"""Record key of how a batch was made (wall times, worker); it varies between runs and is not part of the data."""
