"""Direct policy search (the cross-entropy method).

Its schema (``config.py``, free of torch) imports at once; its implementation
(``learner.py``) on first use of one of its names."""

from ...utils.lazy import lazy_module
from .config import INITS, POLICY_CLASSES, SearchAgentConfig

__getattr__, __dir__ = lazy_module(__name__, ".learner")

__all__ = ["POLICY_CLASSES", "INITS", "SearchAgentConfig"]
