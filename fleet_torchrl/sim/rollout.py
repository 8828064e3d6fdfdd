"""Run a batch of sites for a number of ticks under a decision function (MODEL §4's loop).

:func:`run_sites` is the simulation core of the evaluation protocol
(:mod:`fleet_torchrl.evaluation.protocol`) and of the batched population evaluation of the
direct policy search (:mod:`fleet_torchrl.agents.search`). It knows nothing of policies or
encodings: ``decide(site, state)`` returns the action of every site (``[B]``, 1 = charge)
and only the sites with an undecided vehicle at ``D`` take it.

Simulation ``i`` is the site with index ``site_index[i]`` under ``seed`` (default ``i``): its
initial state and closure draws are those of that index, whatever else is in the batch, so
two runs with the same seed and index are paired. Two backends give the same records bit
for bit (``tests/sim/test_fused.py``):

* fused (the compiled kernel of :mod:`fleet_torchrl.sim.fused`, CPU or CUDA): one call runs
  every alive site to its next decision, its failure or the tick budget; then one ``decide``
  over the batch. One Python iteration per decision epoch; a failed site stops. With a
  ``kernel_policy`` (the rule, the heuristic, a threshold policy or an action table, lowered
  by :mod:`fleet_torchrl.agents.lowering`) the kernel decides itself and a whole run is one
  call (a few with a progress bar).
* eager (any device): each tick is one :meth:`Site.tick` and one ``decide`` over the whole
  batch. Closure draws are generated ``chunk`` ticks at a time; a failed site keeps being
  simulated but stops counting.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from . import fused as _fused
from .config import SiteConfig
from .fused import KernelPolicy
from .site import Site, SiteState

Decide = Callable[[Site, SiteState], Tensor]
_PROGRESS_TICKS = 1000  # ticks per kernel call of an in-kernel policy when a bar is shown


@torch.inference_mode()
def run_sites(decide: Decide, site_cfg: SiteConfig, n_sims: int, ticks: int, seed: int,
              device: str | torch.device = "cpu", chunk: int = 256,
              fused: bool | None = None, site_index: Tensor | None = None,
              progress: bool = False, desc: str = "simulate",
              kernel_policy: KernelPolicy | None = None) -> dict[str, Tensor]:
    """Per-simulation records (CPU tensors): ``trips``, ``queue``, ``failed``,
    ``ticks_survived``. ``fused``: ``None`` uses the compiled kernel wherever it runs,
    ``True`` forces it, ``False`` runs the eager tick loop
    (:func:`fleet_torchrl.sim.fused.use_fused`). ``kernel_policy``: the same decisions as
    ``decide``, taken inside the kernel (the eager loop ignores it and calls ``decide``)."""
    device = torch.device(device)
    if site_index is None:
        site_index = torch.arange(n_sims, dtype=torch.int64)
    elif site_index.shape != (n_sims,):
        raise ValueError(f"site_index must have shape ({n_sims},), got {tuple(site_index.shape)}")
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=ticks, desc=desc, unit="tick", unit_scale=True, leave=False)
    try:
        if _fused.use_fused(device, fused):
            return _run_fused(decide, Site(site_cfg, device), site_index.to(device), ticks,
                              seed, bar, kernel_policy)
        return _run_eager(decide, Site(site_cfg, device), site_index.to(device), ticks, seed,
                          chunk, bar)
    finally:
        if bar is not None:
            bar.close()


def _run_eager(decide: Decide, site: Site, idx: Tensor, ticks: int, seed: int, chunk: int,
               bar) -> dict[str, Tensor]:
    n_sims = idx.shape[0]
    s, needs = site.init_state(seed, idx)
    site.decide(s, needs, decide(site, s))
    trips = torch.zeros(n_sims, dtype=torch.int64, device=site.device)
    queue = torch.zeros_like(trips)
    alive = torch.ones(n_sims, dtype=torch.bool, device=site.device)
    survived = torch.zeros_like(trips)
    for t0 in range(0, ticks, chunk):
        n_t = min(chunk, ticks - t0)
        ticks_block = torch.arange(t0, t0 + n_t, device=site.device)
        closed_block = site.closures(seed, idx, ticks_block[:, None], s.params)  # [T, B]
        for t in range(n_t):
            # A failed site keeps being simulated but stops counting: masking three
            # counters is cheaper than freezing the whole state every tick.
            out = site.tick(s, closed_block[t])
            survived += alive
            trips += out.arrived & alive
            queue += out.queue & alive
            alive &= ~out.failed
            site.decide(s, out.arrived, decide(site, s))
        if bar is not None:
            bar.update(n_t)
    return {"trips": trips.cpu(), "queue": queue.cpu(), "failed": (~alive).cpu(),
            "ticks_survived": survived.cpu()}


def _run_fused(decide: Decide, site: Site, idx: Tensor, ticks: int, seed: int,
               bar, kernel_policy: KernelPolicy | None = None) -> dict[str, Tensor]:
    n_sims, dev = idx.shape[0], site.device
    s, needs = site.init_state(seed, idx)
    site.decide(s, needs, decide(site, s))
    site_hash = site.site_hash(seed, idx)
    trips = torch.zeros(n_sims, dtype=torch.int64, device=dev)
    queue = torch.zeros_like(trips)
    survived = torch.zeros_like(trips)
    alive = torch.ones(n_sims, dtype=torch.bool, device=dev)
    active = alive.clone()
    shown, limit = 0, ticks
    while True:
        if kernel_policy is not None and bar is not None:
            limit = min(ticks, shown + _PROGRESS_TICKS)
        out = _fused.advance(site, s, site_hash, limit, active, kernel_policy)
        trips += out.trips
        queue += out.queue
        survived += out.ticks
        alive &= ~out.failed
        active = alive & (s.tick < ticks)
        if kernel_policy is None:
            sel = out.arrived & active
            if bool(sel.any()):
                site.decide(s, sel, decide(site, s))
        if not bool(active.any()):
            break
        if bar is not None:  # progress: the slowest alive site's tick
            low = int(torch.where(active, s.tick, ticks).min())
            bar.update(low - shown)
            shown = low
    if bar is not None:
        bar.update(ticks - shown)
    return {"trips": trips.cpu(), "queue": queue.cpu(), "failed": (~alive).cpu(),
            "ticks_survived": survived.cpu()}
