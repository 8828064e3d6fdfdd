"""Throughput benchmark: ``make bench`` (``python -m fleet_torchrl.bench --help``).

Measures, for batch sizes ``B`` in {1, 64, 1024, 8192} (median of ``bench.repeats`` runs):

* ``sim``: bare :meth:`Site.tick` calls (closures pre-drawn), ticks/s and site-ticks/s;
* ``eval``: the evaluation loop with the rule policy deciding in the loop, site-ticks/s;
* ``env``: TorchRL environment steps (decision epochs) per second with the rule policy;

``eval`` and ``env`` both with the eager tick loop and with the fused kernel
(:mod:`fleet_torchrl.sim.fused`); and the wall time of the thesis protocol for one policy
(1000 sims x 10 000 ticks): eager, fused and the numpy reference
(:func:`fleet_torchrl.sim.reference.simulate_reference`), with the kernel's one-off compile
time apart.
Results print as Markdown (paste into docs/BENCHMARKS.md) and, with ``--out``, as JSON.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time

import torch

from ..agents import RulePolicy, as_td_module
from ..evaluation import simulate
from ..sim import Site, SiteConfig, SiteRanges, fused
from ..training.spec import RunSpec


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


def bench_eval(b: int, ticks: int, repeats: int, device: str,
               use_fused: bool | None = False) -> float:
    return median_time(lambda: simulate(RulePolicy(), SiteConfig(), b, ticks, 0, device,
                                        fused=use_fused), repeats)


def bench_env(b: int, steps: int, repeats: int, device: str,
              use_fused: bool | None = False) -> float:
    from ..env import FleetChargingEnv

    env = FleetChargingEnv(num_sites=b, device=device, fused=use_fused)
    policy = as_td_module(RulePolicy())
    return median_time(lambda: env.rollout(steps, policy, break_when_any_done=False), repeats)


def bench_env_reference(b: int, steps: int, repeats: int) -> float:
    """The same decision epochs on the numpy reference (rule deciding, no TorchRL)."""
    from ..sim.reference import env_steps_reference, rule_policy

    return median_time(lambda: env_steps_reference(rule_policy, SiteConfig(), b, steps, 0),
                       repeats)


_COMPILE = """
import time
t0 = time.perf_counter()
import torch
from fleet_torchrl.sim import Site, SiteConfig, fused
site = Site(SiteConfig())
s, needs = site.init_state(0, torch.arange(4))
fused.advance(site, s, site.site_hash(0, torch.arange(4)), 50)
print(time.perf_counter() - t0)
"""


def compile_time() -> float:
    """Seconds a fresh process takes to compile the kernel (numba, into a throw-away cache
    dir) and run it once; numba then caches it on disk, once per machine."""
    with tempfile.TemporaryDirectory() as d:
        env = {**os.environ, "NUMBA_CACHE_DIR": d}
        r = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True,
                           env=env, check=True)
        return float(r.stdout.strip().splitlines()[-1])


def bench_protocol(repeats: int, n_sims: int = 1000, ticks: int = 10_000) -> dict[str, float]:
    """Median wall times (s) of the thesis protocol with the rule policy on CPU: ``fused``
    (the rule inside the kernel: one call), ``fused_stepwise`` (the kernel stops at every
    decision epoch for the policy's forward pass, as a network's evaluation does),
    ``eager`` and ``reference`` (numpy), ``compile`` (once per machine), and
    ``fused_randomized`` (every simulation its own site of ``site=randomized``)."""
    from ..sim.reference import rule_policy, simulate_reference

    cfg = SiteConfig()
    out = {"compile": compile_time()}
    run = lambda c=cfg, **kw: simulate(RulePolicy(), c, n_sims, ticks, 0, "cpu", **kw)  # noqa: E731
    out["fused"] = median_time(lambda: run(fused=True), repeats)
    out["fused_stepwise"] = median_time(lambda: run(fused=True, in_kernel=False), repeats)
    out["eager"] = median_time(lambda: run(fused=False), repeats)
    mixed = SiteConfig(name="randomized", ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9],
                                                            t_c=[10, 50])).validate()
    out["fused_randomized"] = median_time(lambda: run(mixed, fused=True), repeats)
    out["reference"] = median_time(lambda: simulate_reference(rule_policy, cfg, n_sims, ticks, 0),
                                   max(1, repeats // 2))
    return out


@torch.inference_mode()
def bench_kernel(b: int, ticks: int, repeats: int, device: str = "cpu") -> float:
    """Seconds of one kernel call running ``b`` default sites for ``ticks`` ticks with the
    rule inside the kernel (site-ticks per second at large batches, CPU or CUDA)."""
    site = Site(SiteConfig(), device)
    idx = torch.arange(b, device=device)
    pol = RulePolicy().kernel_policy()
    h = site.site_hash(0, idx)

    def run():
        s, _ = site.init_state(0, idx)
        fused.advance(site, s, h, ticks, None, pol)
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()

    return median_time(run, repeats)


def bench_training(specs: dict[str, RunSpec], rounds: int = 4) -> dict[str, dict[str, float]]:
    """Training throughput of each recipe (name -> its training's run spec: the table's
    runs, ``conf/recipes/``, on the benchmark's device): decisions per second over
    ``rounds`` rounds (collection, learning and the round's bookkeeping; evaluation,
    checkpoints and TensorBoard left out), after one warm-up round."""
    from dataclasses import replace

    from ..training import Trainer

    out = {}
    with tempfile.TemporaryDirectory() as d:
        for name, spec in specs.items():
            spec = replace(spec, train=replace(spec.train, out_dir=f"{d}/{name}"))
            trainer = Trainer(spec, f"{d}/{name}_run")
            trainer.play_round()  # warm-up (buffers fill, kernel loaded)
            t0 = time.perf_counter()
            frames = sum(trainer.play_round()["frames"] for _ in range(rounds))
            dt = time.perf_counter() - t0
            # the search simulates its own population (population x sites per generation)
            sites = (spec.agent.population * spec.agent.sites
                     if trainer.learner.steps_per_round == 0 else spec.agent.num_sites)
            out[name] = {"decisions_per_s": frames / dt, "round_s": dt / rounds,
                         "sites": sites}
    return out
