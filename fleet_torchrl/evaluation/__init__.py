"""The evaluation protocol (MODEL §4) and its results."""

from .config import EvalConfig
from .protocol import evaluate_policy, evaluate_with, simulate
from .results import (
    compare,
    format_table,
    gain_over,
    load_result,
    save_result,
    seed_interval,
    summarize,
)

__all__ = ["EvalConfig", "compare", "evaluate_policy", "evaluate_with", "format_table",
           "gain_over", "load_result", "save_result", "seed_interval", "simulate", "summarize"]
