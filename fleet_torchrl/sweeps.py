"""Generalisation sweeps (MODEL §5 item 3): policies trained on the default site, evaluated
on changed sites.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then python -m fleet_torchrl.sweeps_summary pc

Each Hydra job evaluates every policy of ``sweep.policies`` at one point (``site.<param> =
sweep.value``) with the evaluation protocol (``eval.n_sims`` x ``eval.ticks``, common random
numbers: all policies of a point see the same sites) and writes
``results/sweeps/<name>/<param>=<value>.json`` atomically. A point whose file exists is
skipped, so rerunning a sweep only runs what is missing; a point that fails writes an
``.error`` file beside it and does not stop the other points. The saved policies must exist
(``make policies`` trains what is missing); a job never trains.
"""

from __future__ import annotations

import sys
import traceback

import hydra
from omegaconf import DictConfig

from .config import register_configs, to_config
from .experiments.sweeps import point_path, run_point
from .utils.cli import user_errors
from .utils.runinfo import write_text

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        cfg = to_config(dcfg)
    try:
        run_point(cfg)
    except Exception as e:  # keep the other points of the multirun going
        path = point_path(cfg)
        write_text(path.with_suffix(".error"), traceback.format_exc())
        print(f"error: point {path.stem} failed ({type(e).__name__}: {e}); see "
              f"{path.with_suffix('.error')}", file=sys.stderr)


if __name__ == "__main__":
    main()
