"""The evaluation protocol (MODEL §4) and its results. The schema imports at once; the rest
on first use (:mod:`fleet_torchrl.utils.lazy`)."""

from typing import TYPE_CHECKING

from ..utils.lazy import lazy_exports
from .config import EvalConfig

__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: ".protocol" for n in ("evaluate_policy", "evaluate_with", "simulate")},
    **{n: ".results" for n in ("check_result_pair", "compare", "format_table", "gain_over",
                               "load_result", "save_result", "seed_interval", "site_strata",
                               "strata_below", "summarize", "worst_stratum_gain")}})

if TYPE_CHECKING:
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
        strata_below,
        summarize,
        worst_stratum_gain,
    )

__all__ = ["EvalConfig", "check_result_pair", "compare", "evaluate_policy", "evaluate_with",
           "format_table", "gain_over", "load_result", "save_result", "seed_interval",
           "simulate", "site_strata", "strata_below", "summarize", "worst_stratum_gain"]
