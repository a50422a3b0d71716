"""Generation of a split's dataset: job configs, level batches (sample, filter, train experts, collect windows),
the coordinator and Ray workers, the run driver with resume, and run tracking.

Public surface: what the command line, Kinetix interop, jobs and benchmarks use.
"""

from pipeline.generation.config import (
    TRACKING_MODES,
    ConfigError,
    EnvSection,
    JobConfig,
    absolute_output_dir,
    config_path,
    data_definition,
    data_fingerprint,
    environment,
    load_config,
    load_yaml,
    merge_layers,
    parse_overrides,
    ppo_config,
    to_schema_object,
    to_yaml,
)
from pipeline.generation.console import closing_summary
from pipeline.generation.coordinator import Commit, Coordinator
from pipeline.generation.growth import ResumeRefused
from pipeline.generation.level_batch import (
    KeyPurpose,
    batches_per_shard,
    level_key,
    level_keys,
    num_shards,
    run_level_batch,
    sample_batch,
)
from pipeline.generation.run import DatasetDamaged, JobInterrupted, prepare_output, run_job, summarize
from pipeline.generation.tracking import start_tracking, tracking_mode
from pipeline.generation.worker import Worker

__all__ = [
    "TRACKING_MODES",
    "Commit",
    "ConfigError",
    "DatasetDamaged",
    "Coordinator",
    "EnvSection",
    "JobConfig",
    "JobInterrupted",
    "KeyPurpose",
    "ResumeRefused",
    "Worker",
    "absolute_output_dir",
    "batches_per_shard",
    "closing_summary",
    "config_path",
    "data_definition",
    "data_fingerprint",
    "environment",
    "level_key",
    "level_keys",
    "load_config",
    "load_yaml",
    "merge_layers",
    "parse_overrides",
    "num_shards",
    "ppo_config",
    "prepare_output",
    "run_job",
    "run_level_batch",
    "sample_batch",
    "start_tracking",
    "summarize",
    "to_schema_object",
    "to_yaml",
    "tracking_mode",
]
