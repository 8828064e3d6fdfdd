"""The two hand-written baselines (rule, heuristic).

Its schema (``config.py``, free of torch) imports at once; its implementation
(``policy.py``) on first use of one of its names."""

from ...utils.lazy import lazy_module
from .config import HeuristicAgentConfig, RuleAgentConfig

__getattr__, __dir__ = lazy_module(__name__, ".policy")

__all__ = ["RuleAgentConfig", "HeuristicAgentConfig"]
