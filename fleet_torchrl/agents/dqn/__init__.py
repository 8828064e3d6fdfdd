"""Deep Q-learning on TorchRL.

Its schema (``config.py``, free of torch) imports at once; its implementation
(``learner.py``) on first use of one of its names."""

from ...utils.lazy import lazy_module
from .config import ANCHOR_STATES, ANCHORS, LR_DECAYS, DQNAgentConfig, NetworkConfig

__getattr__, __dir__ = lazy_module(__name__, ".learner")

__all__ = ["LR_DECAYS", "ANCHORS", "ANCHOR_STATES", "DQNAgentConfig", "NetworkConfig"]
