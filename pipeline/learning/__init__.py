"""Learning from a dataset: behaviour cloning (config, training with checkpoints and resume, data parallel over the
local devices) and the evaluation of a trained policy beside the no-op and random policies and the experts.

Public surface: what the command line and benchmarks use. Each name's module is imported when the name is first used,
so that loading and checking a BC config imports neither JAX nor wandb.
"""

from kforge.pipeline.lazy import lazy_surface

__getattr__, __all__ = lazy_surface(
    __name__,
    {
        "kforge.pipeline.learning.config": "LEVEL_SETS load_bc_config run_config_file",
        "kforge.pipeline.learning.data": "kept_levels validation_split",
        "kforge.pipeline.learning.evaluation": (
            "Episodes evaluate_policy level_set_entry load_policy play_level_files readable_sizes report_table"
        ),
        "kforge.pipeline.learning.evaluation_sets": "UNSEEN_FIRST_LEVEL size_of",
        "kforge.pipeline.learning.train": "Learner TrainingInterrupted train_bc",
    },
)
