"""The evaluation protocol (MODEL §4) and its results."""

from .config import EvalConfig
from .protocol import evaluate_policy, evaluate_with, simulate
from .results import (
    check_result_pair,
    compare,
    format_table,
    gain_over,
    load_result,
    save_result,
    seed_interval,
    site_strata,
    summarize,
    worst_stratum_gain,
)

__all__ = ["EvalConfig", "check_result_pair", "compare", "evaluate_policy", "evaluate_with",
           "format_table", "gain_over", "load_result", "save_result", "seed_interval",
           "simulate", "site_strata", "summarize", "worst_stratum_gain"]
