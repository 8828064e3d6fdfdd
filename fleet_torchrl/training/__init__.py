"""Training: the one loop that serves every learner, its run state and checkpoints."""

from .checkpoint import CHECKPOINT, checkpoint_mismatch, training_fingerprint
from .config import TrainConfig
from .progress import EvalEntry, Progress
from .trainer import Trainer

__all__ = ["CHECKPOINT", "EvalEntry", "Progress", "TrainConfig", "Trainer",
           "checkpoint_mismatch", "training_fingerprint"]
