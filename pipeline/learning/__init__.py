"""Learning from a dataset: behaviour cloning (config, training with checkpoints and resume, data parallel over the
local devices) and the evaluation of a trained policy beside the no-op and random policies and the experts.

Public surface: what the command line uses, and the dataset's kept levels and the first unseen level id that the BC
benchmark reports. Each name's module is imported when the name is first used, so that loading and checking a BC
config imports neither JAX nor wandb.
"""

from kforge.pipeline.lazy import lazy_surface

__getattr__, __all__ = lazy_surface(
    __name__,
    {
        "kforge.pipeline.learning.config": "LEVEL_SETS load_bc_config run_config_file",
        "kforge.pipeline.learning.data": "kept_levels",
        "kforge.pipeline.learning.evaluation": "Episodes evaluate_policy load_policy report_table",
        "kforge.pipeline.learning.evaluation_sets": "UNSEEN_FIRST_LEVEL",
        "kforge.pipeline.learning.train": "TrainingInterrupted train_bc",
    },
)
