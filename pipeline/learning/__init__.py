"""Learning from a dataset: behaviour cloning (config, training with checkpoints and resume, data parallel over the
local devices) and the evaluation of a trained policy beside the no-op and random policies and the experts.

Public surface: what the command line and benchmarks use.
"""

from pipeline.learning.config import BCConfig, load_bc_config, network_config
from pipeline.learning.evaluation import (
    LEVEL_SETS,
    Baseline,
    StartSet,
    TrainedPolicy,
    evaluate_policy,
    hand_starts,
    load_policy,
    play,
    report_table,
)
from pipeline.learning.train import (
    LEVELS_FILE,
    METRICS_FILE,
    SUMMARY_FILE,
    Learner,
    TrainingInterrupted,
    TrainSummary,
    train_bc,
)

__all__ = [
    "LEVELS_FILE",
    "LEVEL_SETS",
    "METRICS_FILE",
    "SUMMARY_FILE",
    "BCConfig",
    "Baseline",
    "Learner",
    "StartSet",
    "TrainSummary",
    "TrainedPolicy",
    "TrainingInterrupted",
    "evaluate_policy",
    "hand_starts",
    "load_bc_config",
    "load_policy",
    "network_config",
    "play",
    "report_table",
    "train_bc",
]
