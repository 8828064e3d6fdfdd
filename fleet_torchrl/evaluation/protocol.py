"""Evaluation protocol (MODEL §4): many sites, many ticks, common random numbers.

:func:`simulate` runs a policy on ``n_sims`` sites for ``ticks`` ticks (or until each fails)
straight on the simulator, without TorchRL in the loop (the loop itself is
:func:`fleet_torchrl.sim.rollout.run_sites`). Simulation ``i`` is site index ``i``
under ``seed``: two policies evaluated with the same seed are paired. The backends, ``fused``
(the default on CPU: the compiled event loop) and ``eager`` (any device), give the same
records bit for bit (``tests/sim/test_fused.py``).

Results are plain dicts (JSON-ready); :mod:`fleet_torchrl.evaluation.results` summarises,
pairs and stores them.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import Any

import torch
from torch import Tensor

from ..agents.base import Policy
from ..sim import SiteConfig
from ..sim.rollout import run_sites
from ..utils.numerics import flush_denormals
from .config import EvalConfig, fused_switch
from .results import summarize


def simulate(policy: Policy, site_cfg: SiteConfig, n_sims: int = 1000, ticks: int = 10_000,
             seed: int = 0, device: str | torch.device = "cpu", chunk: int = 256,
             progress: bool = False, desc: str | None = None,
             fused: bool | None = None, in_kernel: bool = True) -> dict[str, Tensor]:
    """Per-simulation records (CPU tensors): ``trips``, ``queue``, ``failed``,
    ``ticks_survived``; simulation ``i`` is site ``i`` of ``seed``.

    ``fused``: ``None`` uses the compiled kernel wherever it runs, ``True`` forces it,
    ``False`` runs the eager tick loop (see :func:`fleet_torchrl.sim.fused.use_fused`).
    With ``in_kernel`` (default) a policy that has a
    :meth:`~fleet_torchrl.agents.base.Policy.kernel_policy` decides inside the kernel (the
    same decisions, no Python per decision epoch).
    """
    device = torch.device(device)
    flush_denormals()  # subnormal network weights would slow every forward pass 10x
    policy = policy.to(device).eval()
    return run_sites(policy.decide, site_cfg, n_sims, ticks, seed,
                     device, chunk, fused, progress=progress,
                     desc=desc or f"eval {policy.name}",
                     kernel_policy=policy.kernel_policy() if in_kernel else None)


def evaluate_policy(policy: Policy, site_cfg: SiteConfig, n_sims: int, ticks: int, seed: int,
                    device: str = "cpu", chunk: int = 256, progress: bool = False,
                    name: str | None = None, fused: bool | None = None) -> dict[str, Any]:
    """Run the protocol and return a result dict (summary, per-simulation records, setup).
    ``fused``: the backend switch of :func:`simulate`."""
    t0 = time.perf_counter()
    rec = simulate(policy, site_cfg, n_sims, ticks, seed, device, chunk, progress,
                   desc=f"eval {name or policy.name}", fused=fused)
    wall = time.perf_counter() - t0
    return {
        "policy": name or policy.name,
        "n_sims": n_sims,
        "ticks": ticks,
        "seed": seed,
        **summarize(rec),
        "site": asdict(site_cfg),
        "wall_time_s": wall,
        "records": {k: v.tolist() for k, v in rec.items()},
    }


def evaluate_with(policy: Policy, site_cfg: SiteConfig, eval_cfg: EvalConfig,
                  name: str | None = None) -> dict[str, Any]:
    """:func:`evaluate_policy` with the protocol settings of an ``eval`` config."""
    e = eval_cfg
    return evaluate_policy(policy, site_cfg, e.n_sims, e.ticks, e.seed, e.device, e.chunk,
                           progress=e.progress, name=name,
                           fused=fused_switch(e.backend))
