"""Throughput benchmark: ``make bench`` (``python -m fleet_torchrl.bench --help``).

Measures, for batch sizes ``B`` in {1, 64, 1024, 8192} (median of ``--repeats`` runs):

* ``sim``: bare :meth:`Site.tick` calls (closures pre-drawn), ticks/s and site-ticks/s;
* ``eval``: the evaluation loop with the rule policy deciding in the loop, site-ticks/s;
* ``env``: TorchRL environment steps (decision epochs) per second with the rule policy;

and the wall time of the thesis protocol for one policy (1000 sims x 10 000 ticks).
Results print as Markdown (paste into docs/BENCHMARKS.md) and, with ``--out``, as JSON.
"""

from __future__ import annotations

import statistics
import time

import torch

from ..agents import RulePolicy, as_td_module
from ..evaluation import simulate
from ..sim import Site, SiteConfig


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


@torch.inference_mode()
def bench_sim(b: int, ticks: int, repeats: int, device: str) -> float:
    site = Site(SiteConfig(), device)
    idx = torch.arange(b, device=device)
    closed = site.closures(0, idx, torch.arange(ticks, device=device)[:, None])

    def run():
        s, _ = site.init_state(0, idx)
        for t in range(ticks):
            site.tick(s, closed[t])

    return median_time(run, repeats)


def bench_eval(b: int, ticks: int, repeats: int, device: str) -> float:
    return median_time(lambda: simulate(RulePolicy(), SiteConfig(), b, ticks, 0, device),
                        repeats)


def bench_env(b: int, steps: int, repeats: int, device: str) -> float:
    from ..env import FleetChargingEnv

    env = FleetChargingEnv(num_sites=b, device=device)
    policy = as_td_module(RulePolicy())
    return median_time(lambda: env.rollout(steps, policy, break_when_any_done=False), repeats)
