"""Learning from a dataset: behaviour cloning (config, training with checkpoints and resume, data parallel over the
local devices) and the evaluation of a trained policy beside the no-op and random policies and the experts.

Public surface: what the command line and benchmarks use. Each name's module is imported when the name is first used,
so that loading and checking a BC config imports neither JAX nor wandb.
"""

from kforge.pipeline.lazy import lazy_surface

__getattr__, __all__ = lazy_surface(
    __name__,
    {
        "kforge.pipeline.learning.config": (
            "LEVEL_SETS RUN_CONFIG_FILE BCConfig load_bc_config network_config run_config_file"
        ),
        "kforge.pipeline.learning.evaluation": (
            "Baseline TrainedPolicy evaluate_policy load_policy play play_level_files play_physics play_set rates "
            "report_table"
        ),
        "kforge.pipeline.learning.evaluation_sets": (
            "UNSEEN_FIRST_LEVEL UNSEEN_LEVELS StartSet check_unseen_disjoint dataset_level_ids hand_starts "
            "level_file_starts unseen_starts"
        ),
        "kforge.pipeline.learning.train": (
            "LEVELS_FILE METRICS_FILE SUMMARY_FILE Learner TrainingInterrupted TrainSummary train_bc"
        ),
    },
)
