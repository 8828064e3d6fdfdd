"""Command line: paired comparison of two evaluation results.

    fleet-compare result=RESULT.json baseline=BASELINE.json
    (= python -m fleet_torchrl.compare result=... baseline=...)

Prints the gain in trips of RESULT over BASELINE in percent of the baseline's mean, with the
half-width of its 95% confidence interval from the paired per-simulation differences.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .cli import hydra_command
from .config import to_tool_config
from .experiments.config import CompareConfig
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Print the paired gain of ``result`` over ``baseline``."""
    from .evaluation import compare

    with user_errors():
        c = to_tool_config(dcfg, CompareConfig)
        g = compare(c.result, c.baseline)
    print(f"{g['policy']} vs {g['baseline']}: {g['gain_pct']:+.2f} % trips "
          f"(95% CI ± {g['gain_ci95']:.2f})")


main = hydra_command(task, config_name="compare")

if __name__ == "__main__":
    main()
