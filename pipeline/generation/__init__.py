"""Generation of a split's dataset: job configs, level batches (sample, filter, train experts, collect windows),
the coordinator and Ray workers, the run driver with resume, and run tracking.

Public surface: what the command line, Kinetix interop, jobs and benchmarks use. Each name's module is imported when
the name is first used, so that loading and checking a job config imports neither JAX nor Ray.
"""

from kforge.pipeline.lazy import lazy_surface

__getattr__, __all__ = lazy_surface(
    __name__,
    {
        "kforge.pipeline.generation.config_yaml": "to_yaml",
        "kforge.pipeline.generation.loading": "load_config load_yaml merge_layers parse_overrides to_schema_object",
        "kforge.pipeline.generation.resolved": "ResolvedJob resolve",
        "kforge.pipeline.generation.schema": "TRACKING_MODES ConfigError EnvSection JobConfig",
        "kforge.pipeline.generation.sources": "absolute_output_dir",
        "kforge.pipeline.generation.console": "closing_summary seconds_left",
        "kforge.pipeline.generation.growth": "ResumeRefused",
        "kforge.pipeline.generation.level_batch": "KeyPurpose level_keys sample_batch",
        "kforge.pipeline.generation.run": "JobInterrupted run_job",
        "kforge.pipeline.generation.tracking": "tracking_mode",
    },
)
