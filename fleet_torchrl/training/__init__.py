"""Training: the one loop that serves every learner, its run state and checkpoints. The
schemas (the ``train`` group, the run spec) import at once; the rest on first use
(:mod:`fleet_torchrl.utils.lazy`)."""

from typing import TYPE_CHECKING

from ..utils.lazy import lazy_exports
from .config import TrainConfig
from .spec import RunSpec

__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: ".checkpoint" for n in ("CHECKPOINT", "checkpoint_mismatch", "result_fingerprint",
                                  "training_fingerprint")},
    **{n: ".progress" for n in ("EvalEntry", "Progress")},
    "Trainer": ".trainer"})

if TYPE_CHECKING:
    from .checkpoint import (
        CHECKPOINT,
        checkpoint_mismatch,
        result_fingerprint,
        training_fingerprint,
    )
    from .progress import EvalEntry, Progress
    from .trainer import Trainer

__all__ = ["CHECKPOINT", "EvalEntry", "Progress", "RunSpec", "TrainConfig", "Trainer",
           "checkpoint_mismatch", "result_fingerprint", "training_fingerprint"]
