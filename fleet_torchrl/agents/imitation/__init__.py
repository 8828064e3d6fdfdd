"""The planner's distillation (DAgger).

Its schema (``config.py``, free of torch) imports at once; its implementation
(``learner.py``) on first use of one of its names."""

from ...utils.lazy import lazy_module
from .config import LABEL_WEIGHTS, ImitationAgentConfig

__getattr__, __dir__ = lazy_module(__name__, ".learner")

__all__ = ["LABEL_WEIGHTS", "ImitationAgentConfig"]
