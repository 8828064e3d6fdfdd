"""Evaluation protocol (MODEL §4): many sites, many ticks, common random numbers.

:func:`simulate` runs a policy on ``n_sims`` sites for ``ticks`` ticks (or until each fails)
straight on the simulator, without TorchRL in the loop. Simulation ``i`` is site index ``i``
under ``seed``: two policies evaluated with the same seed are paired. Two backends give the
same records bit for bit (``tests/sim/test_fused.py``):

* ``fused`` (the default on CPU): an event loop. One call of the compiled kernel of
  :mod:`fleet_torchrl.sim.fused` runs every alive site to its next decision (a vehicle
  reaching ``D``), its failure or the tick budget; then one encoding and one policy forward
  over the batch decide for the sites at a decision. One Python iteration per decision epoch;
  a failed site stops.
* ``eager`` (any device; the only one off the CPU): each tick is one :meth:`Site.tick`, one
  encoding and one policy forward over the whole batch. Closure draws are generated ``chunk``
  ticks at a time; a failed site keeps being simulated but stops counting.

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
from ..env.encodings import get_encoding
from ..sim import Site, SiteConfig
from ..sim import fused as _fused
from .config import EvalConfig, fused_switch
from .results import summarize


@torch.inference_mode()
def simulate(policy: Policy, site_cfg: SiteConfig, n_sims: int = 1000, ticks: int = 10_000,
             seed: int = 0, device: str | torch.device = "cpu", chunk: int = 256,
             progress: bool = False, desc: str | None = None,
             fused: bool | None = None) -> dict[str, Tensor]:
    """Per-simulation records (CPU tensors): ``trips``, ``queue``, ``failed``,
    ``ticks_survived``.

    ``fused``: ``None`` uses the compiled event loop on CPU (when gcc can build it), ``True``
    forces it on CPU, ``False`` runs the eager tick loop; off the CPU the eager loop always
    runs (see :func:`fleet_torchrl.sim.fused.use_fused`).
    """
    device = torch.device(device)
    if _fused.use_fused(device, fused):
        return _simulate_fused(policy, site_cfg, n_sims, ticks, seed, progress, desc)
    site = Site(site_cfg, device)
    encode = get_encoding(policy.encoding)
    policy = policy.to(device).eval()
    idx = torch.arange(n_sims, device=device, dtype=torch.int64)
    s, needs = site.init_state(seed, idx)
    site.decide(s, needs, policy(encode(site, s)))
    trips = torch.zeros(n_sims, dtype=torch.int64, device=device)
    queue = torch.zeros_like(trips)
    alive = torch.ones(n_sims, dtype=torch.bool, device=device)
    survived = torch.zeros_like(trips)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=ticks, desc=desc or f"eval {policy.name}", unit="tick",
                   unit_scale=True, leave=False)
    for t0 in range(0, ticks, chunk):
        n_t = min(chunk, ticks - t0)
        ticks_block = torch.arange(t0, t0 + n_t, device=device)
        closed_block = site.closures(seed, idx, ticks_block[:, None])  # [T, B]
        for t in range(n_t):
            # A failed site keeps being simulated but stops counting: masking three
            # counters is cheaper than freezing the whole state every tick.
            out = site.tick(s, closed_block[t])
            survived += alive
            trips += out.arrived & alive
            queue += out.queue & alive
            alive &= ~out.failed
            site.decide(s, out.arrived, policy(encode(site, s)))
        if bar is not None:
            bar.update(n_t)
    if bar is not None:
        bar.close()
    return {"trips": trips.cpu(), "queue": queue.cpu(), "failed": (~alive).cpu(),
            "ticks_survived": survived.cpu()}


def _simulate_fused(policy: Policy, site_cfg: SiteConfig, n_sims: int, ticks: int, seed: int,
                    progress: bool, desc: str | None) -> dict[str, Tensor]:
    """:func:`simulate` as an event loop over decision epochs (CPU, compiled kernel)."""
    site = Site(site_cfg, "cpu")
    encode = get_encoding(policy.encoding)
    policy = policy.to("cpu").eval()
    idx = torch.arange(n_sims, dtype=torch.int64)
    s, needs = site.init_state(seed, idx)
    site.decide(s, needs, policy(encode(site, s)))
    site_hash = site.site_hash(seed, idx)
    trips = torch.zeros(n_sims, dtype=torch.int64)
    queue = torch.zeros_like(trips)
    survived = torch.zeros_like(trips)
    alive = torch.ones(n_sims, dtype=torch.bool)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=ticks, desc=desc or f"eval {policy.name}", unit="tick",
                   unit_scale=True, leave=False)
    active = alive.clone()
    shown = 0
    while True:
        out = _fused.advance(site, s, site_hash, ticks, active)
        trips += out.trips
        queue += out.queue
        survived += out.ticks
        alive &= ~out.failed
        active = alive & (s.tick < ticks)
        decide = out.arrived & active
        if not bool(decide.any()):
            if not bool(active.any()):
                break
        else:
            site.decide(s, decide, policy(encode(site, s)))
        if bar is not None:  # progress: the slowest alive site's tick
            low = int(torch.where(active, s.tick, ticks).min())
            bar.update(low - shown)
            shown = low
    if bar is not None:
        bar.update(ticks - shown)
        bar.close()
    return {"trips": trips, "queue": queue, "failed": ~alive, "ticks_survived": survived}


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
