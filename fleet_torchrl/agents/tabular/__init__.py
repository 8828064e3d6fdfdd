"""Tabular Q-learning.

Its schema (``config.py``, free of torch) imports at once; its implementation
(``learner.py``) on first use of one of its names."""

from ...utils.lazy import lazy_module
from .config import TabularAgentConfig

__getattr__, __dir__ = lazy_module(__name__, ".learner")

__all__ = ["TabularAgentConfig"]
