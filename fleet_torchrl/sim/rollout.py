"""Run a batch of sites for a number of ticks under a decision function (MODEL §4's loop).

:func:`run_sites` is the simulation core of the evaluation protocol
(:mod:`fleet_torchrl.evaluation.protocol`) and of the batched population evaluation of the
direct policy search (:mod:`fleet_torchrl.agents.search`). It knows nothing of policies or
encodings: ``decide(site, state, ctx)`` returns the action of every site (``[B]``, 1 =
charge) and only the sites with an undecided vehicle at ``D`` take it; ``ctx``
(:class:`DecisionContext`) says which sites those are and each site's index, for a decision
function that works on the sites themselves (the rollout planner) rather than on one batched
forward pass.

:func:`advance` runs sites to their next event under a decision function on either
backend, the same events and states bit for bit: what the planner's rollouts and the
environment's eager step run.

Simulation ``i`` is the site with index ``site_index[i]`` under ``seed`` (default ``i``): its
initial state and closure draws are those of that index, whatever else is in the batch, so
two runs with the same seed and index are paired. Two backends give the same records bit
for bit (``tests/sim/test_fused.py``):

* fused (the compiled kernel of :mod:`fleet_torchrl.sim.fused`, CPU or CUDA): one call runs
  every alive site to its next decision, its failure or the tick budget; then one ``decide``
  over the batch. One Python iteration per decision epoch; a failed site stops. With a
  ``kernel_policy`` (the rule, the heuristic, a threshold policy or an action table: a
  policy's :meth:`~fleet_torchrl.agents.base.Policy.kernel_policy`) the kernel decides itself
  and a whole run is one call (a few with a progress bar).
* eager (any device): each tick is one :meth:`Site.tick` and one ``decide`` over the whole
  batch. Closure draws are generated ``chunk`` ticks at a time; a failed site keeps being
  simulated but stops counting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from . import fused as _fused
from .config import SiteConfig
from .fused import Events, KernelPolicy
from .site import Site, SiteState


@dataclass
class DecisionContext:
    """What a decision function may know besides the state: which sites decide now (the
    others' actions are ignored) and each site's index (simulation ``i`` of the protocol:
    a label, e.g. for a planner's own random streams)."""

    need: Tensor  # [B] bool
    index: Tensor  # [B] int64
    fused: bool | None = None  # the backend of the simulation (a planner's rollouts follow it)


Decide = Callable[[Site, SiteState, DecisionContext], Tensor]
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
    from ..utils.resources import check_memory
    from .config import site_bytes

    device = torch.device(device)
    check_memory("n_sims", n_sims, n_sims * site_bytes(site_cfg), "the simulated sites")
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
    site.decide(s, needs, decide(site, s, DecisionContext(needs, idx, False)))
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
            site.decide(s, out.arrived, decide(site, s, DecisionContext(out.arrived, idx, False)))
        if bar is not None:
            bar.update(n_t)
    return {"trips": trips.cpu(), "queue": queue.cpu(), "failed": (~alive).cpu(),
            "ticks_survived": survived.cpu()}


def _run_fused(decide: Decide, site: Site, idx: Tensor, ticks: int, seed: int,
               bar, kernel_policy: KernelPolicy | None = None) -> dict[str, Tensor]:
    n_sims, dev = idx.shape[0], site.device
    s, needs = site.init_state(seed, idx)
    site.decide(s, needs, decide(site, s, DecisionContext(needs, idx, True)))
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
                site.decide(s, sel, decide(site, s, DecisionContext(sel, idx, True)))
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


def advance(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
            decide: Decide | None = None, kernel_policy: KernelPolicy | None = None,
            index: Tensor | None = None, fused: bool | None = None) -> Events:
    """Run every site of ``state`` until it fails or its tick counter reaches ``max_ticks``
    (an int or ``[B]``), each arrival at ``D`` decided by ``decide`` (with ``index`` as the
    sites' labels); without ``decide``, until its next arrival (:func:`fused.advance`'s
    contract). The compiled kernel runs it in one call with a ``kernel_policy`` (the same
    decisions as ``decide``), else with one ``decide`` per decision epoch; ``fused=False``
    runs the eager tick loop. Same events and states on both backends, bit for bit."""
    b = state.pos.shape[1]
    index = torch.arange(b, device=state.pos.device) if index is None else index
    if not _fused.use_fused(state.pos.device, fused):
        return advance_eager(site, state, site_hash, max_ticks, decide, index)
    if decide is None or kernel_policy is not None:
        return _fused.advance(site, state, site_hash, max_ticks, None, kernel_policy)
    limit = torch.as_tensor(max_ticks, dtype=torch.int64, device=state.pos.device)
    total = None
    active = torch.ones(b, dtype=torch.bool, device=state.pos.device)
    while True:  # stop at each arrival, decide it, go on
        ev = _fused.advance(site, state, site_hash, limit, active)
        total = ev if total is None else _merge(total, ev, active)
        active &= ~ev.failed & (state.tick < limit)
        sel = ev.arrived & active
        if bool(sel.any()):
            site.decide(state, sel, decide(site, state, DecisionContext(sel, index, True)))
        # an arrival at the limit is decided too, as the kernel's in-kernel policies do
        done_now = ev.arrived & ~ev.failed & ~active & (state.tick >= limit)
        if bool(done_now.any()):
            site.decide(state, done_now,
                        decide(site, state, DecisionContext(done_now, index, True)))
        if not bool(active.any()):
            return total


def _merge(total: Events, ev: Events, active: Tensor) -> Events:
    """Events of two consecutive calls (the second one's last tick wins where it ran)."""
    ran = ev.ticks > 0
    return Events(ticks=total.ticks + ev.ticks, trips=total.trips + ev.trips,
                  queue=total.queue + ev.queue,
                  arrived=torch.where(ran, ev.arrived, total.arrived),
                  failed=torch.where(ran, ev.failed, total.failed),
                  queued=torch.where(ran, ev.queued, total.queued))


def advance_eager(site: Site, state: SiteState, site_hash: Tensor, max_ticks: Tensor | int,
                  decide: Decide | None = None, index: Tensor | None = None,
                  active: Tensor | None = None) -> Events:
    """:func:`advance` (and :func:`fused.advance`) one :meth:`Site.tick` at a time: the
    reference the kernel is tested against, and the path of devices without it."""
    b, dev = state.pos.shape[1], state.pos.device
    index = torch.arange(b, device=dev) if index is None else index
    run = (torch.ones(b, dtype=torch.bool, device=dev) if active is None
           else active.to(torch.bool).clone())
    limit = torch.as_tensor(max_ticks, dtype=torch.int64, device=dev)
    z = dict(dtype=torch.int64, device=dev)
    f = dict(dtype=torch.bool, device=dev)
    ev = Events(ticks=torch.zeros(b, **z), trips=torch.zeros(b, **z), queue=torch.zeros(b, **z),
                arrived=torch.zeros(b, **f), failed=torch.zeros(b, **f),
                queued=torch.zeros(b, **f))
    while bool(run.any()):
        out = site.tick(state, site.closures_hashed(site_hash, state.tick, state.params), run)
        ev.ticks += run
        ev.trips += out.arrived
        ev.queue += out.queue
        ev.arrived.copy_(torch.where(run, out.arrived, ev.arrived))
        ev.failed.copy_(torch.where(run, out.failed, ev.failed))
        ev.queued.copy_(torch.where(run, out.queue, ev.queued))
        stop = out.failed | (state.tick >= limit)
        if decide is None:
            stop |= out.arrived
        else:  # decided on arrival (not on failure), as the kernel's policies are
            sel = out.arrived & ~out.failed & run
            if bool(sel.any()):
                site.decide(state, sel, decide(site, state, DecisionContext(sel, index, False)))
        run &= ~stop
    return ev
