"""The charging site, tick by tick (MODEL §1), for a batch of independent sites. Pure torch.

Layout
------
Nodes ``0..N-1``: ``0 = D`` (decision), ``1 = C`` (charger), ``2 = B`` (bypass), ``3 = M``
(merge), ``4..N-1`` road; ``N-1`` leads back to ``D``. A batch of ``B`` sites with ``V``
vehicles each is held in :class:`SiteState` as vehicle-major ``[V, B]`` tensors (position,
soc, charging ticks left) plus per-site ``[B]`` tensors (the decision of the vehicle at ``D``,
tick count). Vehicle-major because every reduction over vehicles then runs over contiguous
rows, and per-site tensors broadcast against per-vehicle ones without reshaping.

One tick (:meth:`Site.tick`) updates every vehicle of every site synchronously from the state
at the start of the tick, with a fixed number of tensor operations whatever ``B`` and ``V``:

1. the closure of ``X`` is an input (drawn by :meth:`Site.closures` from the common random
   numbers of :mod:`fleet_torchrl.sim.rng`);
2. each vehicle's target is a table lookup indexed by ``pos + (N + 1) * charge`` (node ``N``
   parks the vehicles a site of a distribution does not have, see below); a vehicle with
   charging ticks left has no target;
3. a vehicle moves iff its target was empty at the start of the tick and is not ``X`` while
   ``X`` is closed. Occupancy is one 64-bit mask per site (bit ``k`` = node ``k``), with the
   closed ``X`` counted as occupied, so the test is ``mask & check != 0`` (hence at most 62
   nodes). Merge priority is folded into the test: the vehicle leaving ``C`` checks the bits
   of ``M`` *and* ``B``. If ``B`` is occupied and ``M`` is free, the vehicle at ``B`` moves (its
   only target is ``M``), so ``C`` waits; if ``M`` is occupied neither moves. This is exactly
   "the one at B goes, the one at C waits";
4. energy: charging ``+E_charge/T_C`` capped at 100, moving ``-e_move``, otherwise ``-e_idle``;
   with ``leave_when_full`` (default) a charging vehicle that reaches 100 gets 0 ticks left, so
   it leaves ``C`` as soon as it can (the charger ends its session on a full battery);
5. a vehicle entering ``C`` gets ``T_C`` charging ticks;
6. counters: a move into ``D`` is a completed trip and needs a decision; a vehicle at ``D`` that
   decided to charge and did not enter ``C`` makes a queue tick;
7. failure: any ``soc < SoC_low`` after the tick.

Choices the model leaves open (documented in docs/MODEL.md §1 as well):

* ``soc`` is float32. ``TC`` for a vehicle that has finished charging but is stuck at ``C`` is
  ``1 / (T_C + 1)`` (its ticks left are 0, the charger is still not free).
* A vehicle arriving at ``D`` has its decision cleared; the caller must decide before the
  site's next tick (the environment does not tick sites that await a decision, the evaluation
  loop decides right after each tick).
* Sites can be frozen with the ``active`` mask (failed sites in evaluation, sites waiting for
  a decision in the environment): a frozen site's state and counters do not change at all.

Every state carries its sites' parameters (:class:`SiteParams`: ``N_V``, ``T_C``, the
charging gain per tick, the closure threshold), so the tick, the compiled kernel, the
encodings and the environment have one path: a single site is a batch of equal values
(:meth:`Site.site_params`), and a site *distribution* (``SiteConfig.ranges``, MODEL §1.6)
gives every site of the batch its own ``N_V``, ``p_c`` and ``T_C``, drawn with its initial
state from ``(seed, site index)`` (:meth:`Site.draw_params`). The state of a distribution
holds the largest fleet of the range; the vehicles a site does not have are *parked* on
an extra node ``N`` that has no occupancy bit, no successor but itself and no energy change,
so they never block, move, charge, count or fail. Site ``b`` of such a batch is then exactly
(bit for bit) the single site with ``b``'s parameters under the same seed and index: its
vehicles are the first ``N_V`` of the same draws.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from . import rng
from .config import MAX_NODES, SiteConfig

D, C, BYPASS, M = 0, 1, 2, 3


@dataclass
class SiteParams:
    """Per-site parameters of a batch (``[B]`` tensors): a single site's values repeated, or
    each site's draws from a site distribution."""

    n_vehicles: Tensor  # int64 N_V (vehicles beyond it are parked)
    t_c: Tensor  # int64 T_C
    gain: Tensor  # float32 e_charge / T_C per charging tick
    closure: Tensor  # int64 X is closed in a tick iff its 32-bit draw is below this
    p_c: Tensor  # float64 closure probability (closure = round(p_c * 2**32))

    def clone(self) -> SiteParams:
        return SiteParams(**{f.name: getattr(self, f.name).clone() for f in fields(self)})

    def update_(self, mask: Tensor, other: SiteParams) -> None:
        for f in fields(self):
            getattr(self, f.name).copy_(torch.where(mask, getattr(other, f.name),
                                                    getattr(self, f.name)))

    def select(self, idx: Tensor) -> SiteParams:
        return SiteParams(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})


@dataclass
class SiteState:
    """State of ``B`` sites. Tensors are updated in place by :meth:`Site.tick`."""

    pos: Tensor  # [V, B] int64 node of each vehicle
    soc: Tensor  # [V, B] float32 state of charge, 0..100
    left: Tensor  # [V, B] int64 charging ticks left (0 unless charging at C)
    charge: Tensor  # [B] bool decision of the vehicle at D (True = charge)
    tick: Tensor  # [B] int64 ticks this site has run since it was initialised
    params: SiteParams  # per-site parameters (N_V, T_C, gain, closure threshold)

    @property
    def batch_size(self) -> int:
        return self.pos.shape[1]

    def clone(self) -> SiteState:
        return SiteState(**{f.name: getattr(self, f.name).clone() for f in fields(self)})

    def update_(self, mask: Tensor, other: SiteState) -> SiteState:
        """Overwrite the sites selected by the ``[B]`` bool ``mask`` with ``other``'s."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if f.name == "params":
                mine.update_(mask, theirs)
            else:
                mine.copy_(torch.where(mask, theirs, mine))  # [B] broadcasts over [V, B]
        return self

    def select(self, idx: Tensor) -> SiteState:
        """A new state of the sites ``idx`` (``[K]`` indices, repeats allowed), in that
        order: copies of their vehicles, decisions, tick counts and parameters."""
        return SiteState(pos=self.pos[:, idx], soc=self.soc[:, idx], left=self.left[:, idx],
                         charge=self.charge[idx], tick=self.tick[idx],
                         params=self.params.select(idx))


@dataclass
class TickOutcome:
    """What happened in one tick, per site (``[B]`` bool tensors)."""

    arrived: Tensor  # a vehicle moved from N-1 into D: one trip completed, a decision is needed
    queue: Tensor  # the vehicle at D had decided to charge and could not enter C
    failed: Tensor  # some soc < SoC_low after the tick


class Site:
    """A site model on a device: the tick rules, initial states and closure draws."""

    def __init__(self, cfg: SiteConfig, device: torch.device | str = "cpu") -> None:
        cfg.validate()  # as it stands now (a site with no vehicle would never reach a decision)
        self.cfg = cfg
        self.device = torch.device(device)
        n = self.n_nodes = cfg.n_nodes
        self.ranges = cfg.ranges if cfg.randomized else None
        self.n_vehicles = cfg.max_vehicles  # rows of the state (the top of a drawn range)
        self.t_c = cfg.t_c
        self.p_c = cfg.p_c
        self.soc_low = cfg.soc_low
        self.gain = cfg.e_charge / cfg.t_c
        self.leave_when_full = cfg.leave_when_full

        # node n parks the vehicles a site of a distribution does not have; the tables are
        # indexed by pos + (n + 1) * charge
        self.park = n
        self._stride = n + 1
        succ = [0] * (n + 1)
        succ[D], succ[C], succ[BYPASS] = BYPASS, M, M
        for k in range(M, n):
            succ[k] = (k + 1) % n  # M -> 4, road -> next, N-1 -> D
        succ[n] = n  # parked stays parked
        succ_charge = list(succ)
        succ_charge[D] = C
        if n > MAX_NODES:
            raise ValueError(f"n_nodes={n} exceeds {MAX_NODES} (occupancy is a 64-bit mask)")
        kw = dict(dtype=torch.int64, device=self.device)
        self._succ = torch.tensor(succ + succ_charge, **kw)
        # bits a vehicle checks before moving: its target's; the vehicle leaving C checks
        # M and B (merge priority to the bypass); the parking node has no bit
        check = [1 << t if t < n else 0 for t in succ + succ_charge]
        check[C] = check[n + 1 + C] = (1 << M) | (1 << BYPASS)
        self._check = torch.tensor(check, **kw)
        self._bit = torch.tensor([1 << k for k in range(n)] + [0], **kw)
        self._closed_bit = 1 << cfg.closed_node
        self._delta = torch.tensor([-cfg.e_idle, -cfg.e_move, self.gain, 0.0],
                                   dtype=torch.float32, device=self.device)
        self._start_nodes = torch.tensor([k for k in range(n) if k != C], **kw)

    def kernel_constants(self, device: torch.device | str | None = None
                         ) -> tuple[Tensor, Tensor, Tensor]:
        """The tick rules' constants as the compiled kernel reads them (sim/fused.py), on
        ``device`` (this site's by default), built once per device:

        * ``tables`` ``[2, 2 * (n_nodes + 1)]`` int64: each node's successor, then the
          occupancy bits a vehicle there checks before moving, indexed by
          ``pos + (n_nodes + 1) * charge`` (row ``D`` of the charging half sends to ``C``);
        * ``geo`` ``[3]`` int64: that stride ``n_nodes + 1``, the closed node's bit, and
          whether the charger ends a session on a full battery;
        * ``energy`` ``[3]`` float32: the soc change of an idle and of a moving tick, and
          the failure line ``soc_low``."""
        device = torch.device(device) if device is not None else self.device
        key = ("_kernel_constants", device)
        cached = self.__dict__.get(key)
        if cached is None:
            d_idle, d_move = float(self._delta[0]), float(self._delta[1])
            geo = torch.tensor([self._stride, self._closed_bit, int(self.leave_when_full)],
                               dtype=torch.int64)
            energy = torch.tensor([d_idle, d_move, self.soc_low], dtype=torch.float32)
            tables = torch.stack((self._succ, self._check))
            cached = tuple(t.to(device).contiguous() for t in (tables, geo, energy))
            self.__dict__[key] = cached
        return cached

    # ------------------------------------------------------------------ random draws
    def closures(self, seed: int, site_idx: Tensor, ticks: Tensor,
                 params: SiteParams | None = None) -> Tensor:
        """Whether ``X`` is closed for each (site, tick): bool tensor of the broadcast shape.

        ``site_idx`` and ``ticks`` broadcast against each other, e.g. ``[B]`` and ``[T, 1]``
        give a ``[T, B]`` block of draws. The tick number is the site's own tick count at the
        start of the tick (the first tick of a site is tick 0). The draw is
        ``mix(hash(seed, site, stream) ^ hash(tick)) < p_c * 2**32``: a pure function of the
        three integers that costs one mixing round per element of the block. ``params``:
        the sites' parameters (default :meth:`site_params` of ``site_idx``).
        """
        if params is None:
            params = self.site_params(seed, site_idx.reshape(-1))
        return self.closures_hashed(self.site_hash(seed, site_idx), ticks, params)

    def site_hash(self, seed: int, site_idx: Tensor) -> Tensor:
        """The per-site half of the closure draw (cache it while the site index is fixed)."""
        return rng.hash_ints(seed, site_idx, rng.STREAM_CLOSURE, device=self.device)

    def closures_hashed(self, site_hash: Tensor, ticks: Tensor, params: SiteParams) -> Tensor:
        """:meth:`closures` from a precomputed :meth:`site_hash` and the sites' parameters
        (``[B]`` along the last dimension): each site's own closure threshold."""
        return rng.mix_below(site_hash, rng.hash_ints(ticks, device=self.device),
                             params.closure)

    def site_params(self, seed: int, site_idx: Tensor) -> SiteParams:
        """The parameters of the sites ``site_idx``: drawn from the distribution
        (:meth:`draw_params`), or the single site's values repeated."""
        if self.ranges is not None:
            return self.draw_params(seed, site_idx)
        return self.constant_params(site_idx.shape[0])

    def constant_params(self, b: int) -> SiteParams:
        """The single site's parameters for a batch of ``b`` sites (no draw)."""
        cfg = self.cfg
        kw = dict(device=self.device)
        p_c = torch.full((b,), float(cfg.p_c), dtype=torch.float64, **kw)
        return SiteParams(
            n_vehicles=torch.full((b,), self.n_vehicles, dtype=torch.int64, **kw),
            t_c=torch.full((b,), int(cfg.t_c), dtype=torch.int64, **kw),
            gain=torch.full((b,), float(cfg.e_charge) / cfg.t_c, dtype=torch.float64,
                            **kw).float(),
            closure=torch.round(p_c * float(1 << 32)).to(torch.int64),
            p_c=p_c)

    def draw_params(self, seed: int, site_idx: Tensor) -> SiteParams:
        """The parameters of each site of a distribution, a pure function of ``(seed, site
        index)`` (MODEL §1.6): integers uniform on their range (a 32-bit draw modulo the
        range's size), ``p_c`` = low + u (high - low) with u on the 24-bit grid of [0, 1)."""
        cfg, r = self.cfg, self.ranges
        assert r is not None, "draw_params needs a site distribution (site.ranges)"
        site_idx = site_idx.to(self.device, torch.int64)
        kw = dict(dtype=torch.int64, device=self.device)

        def integer(k: int, rng_range: list[int] | None, fixed: int) -> Tensor:
            if rng_range is None:
                return torch.full(site_idx.shape, fixed, **kw)
            lo, hi = int(rng_range[0]), int(rng_range[1])
            h = rng.hash_ints(seed, site_idx, rng.STREAM_SITE, k, device=self.device)
            return lo + h % (hi - lo + 1)

        n_v = integer(0, r.n_vehicles, cfg.n_vehicles)
        t_c = integer(1, r.t_c, cfg.t_c)
        if r.p_c is None:
            p_c = torch.full(site_idx.shape, float(cfg.p_c), dtype=torch.float64,
                             device=self.device)
        else:
            u = rng.uniform(seed, site_idx, rng.STREAM_SITE, 2, device=self.device)
            p_c = float(r.p_c[0]) + u.double() * (float(r.p_c[1]) - float(r.p_c[0]))
        gain = (float(cfg.e_charge) / t_c.double()).float()  # as e_charge / t_c, then float32
        closure = torch.round(p_c * float(1 << 32)).to(torch.int64)
        return SiteParams(n_vehicles=n_v, t_c=t_c, gain=gain, closure=closure, p_c=p_c)

    def init_state(self, seed: int, site_idx: Tensor) -> tuple[SiteState, Tensor]:
        """Random initial states (MODEL §1) as a pure function of ``(seed, site index)``.

        Vehicles sit on distinct nodes drawn uniformly from all nodes but ``C``; ``soc`` is
        uniform on ``[SoC_low + xi, 100]``. Returns the state and the ``[B]`` bool mask of sites
        whose vehicle on ``D`` needs a decision at once.
        """
        site_idx = site_idx.to(self.device, torch.int64)
        b, v = site_idx.shape[0], self.n_vehicles
        params = self.site_params(seed, site_idx)
        cand = self._start_nodes
        keys = rng.uniform(seed, site_idx[None, :], cand[:, None], rng.STREAM_INIT_POS,
                           device=self.device)  # [N-1, B]
        # argsort of iid keys is a uniform random permutation of the candidate nodes
        pos = cand[torch.argsort(keys, dim=0, stable=True)[:v]]
        u = rng.uniform(seed, site_idx[None, :], torch.arange(v, device=self.device)[:, None],
                        rng.STREAM_INIT_SOC, device=self.device)
        lo = self.soc_low + self.cfg.xi
        soc = lo + u * (100.0 - lo)
        if self.ranges is not None:  # the vehicles a site does not have are parked, full
            parked = torch.arange(v, device=self.device)[:, None] >= params.n_vehicles
            pos = pos.masked_fill(parked, self.park)
            soc = soc.masked_fill(parked, 100.0)
        state = SiteState(
            pos=pos,
            soc=soc,
            left=torch.zeros(v, b, dtype=torch.int64, device=self.device),
            charge=torch.zeros(b, dtype=torch.bool, device=self.device),
            tick=torch.zeros(b, dtype=torch.int64, device=self.device),
            params=params,
        )
        return state, (pos == D).any(0)

    def state(self, pos: Tensor, soc: Tensor, left: Tensor | None = None,
              charge: Tensor | None = None, tick: Tensor | None = None) -> SiteState:
        """A hand-built state of ``B`` sites of this (single) site: ``pos``, ``soc`` (and
        ``left``, default 0) ``[V, B]``; ``charge`` (default False) and ``tick`` (default 0)
        ``[B]``; the site's own parameters, with ``N_V`` the ``V`` vehicles given."""
        pos = torch.as_tensor(pos, dtype=torch.int64, device=self.device)
        v, b = pos.shape
        kw = dict(device=self.device)
        params = self.constant_params(b)
        params.n_vehicles.fill_(v)
        return SiteState(
            pos=pos, soc=torch.as_tensor(soc, dtype=torch.float32, **kw),
            left=(torch.zeros(v, b, dtype=torch.int64, **kw) if left is None
                  else torch.as_tensor(left, dtype=torch.int64, **kw)),
            charge=(torch.zeros(b, dtype=torch.bool, **kw) if charge is None
                    else torch.as_tensor(charge, dtype=torch.bool, **kw)),
            tick=(torch.zeros(b, dtype=torch.int64, **kw) if tick is None
                  else torch.as_tensor(tick, dtype=torch.int64, **kw)),
            params=params)

    # ---------------------------------------------------------------------- the tick
    def tick(self, s: SiteState, closed: Tensor, active: Tensor | None = None) -> TickOutcome:
        """Advance every active site by one tick, in place. ``closed``: ``[B]`` bool.

        With ``active=None`` every site advances (the fast path of the evaluation loop).
        """
        pos, left, par = s.pos, s.left, s.params
        idx = pos + s.charge * self._stride
        tgt = self._succ.take(idx)
        occ = self._bit.take(pos).sum(0)  # [B] occupancy bits at the start of the tick
        occ_d = (occ & 1).bool()
        occ |= closed * self._closed_bit  # a closed X counts as occupied
        charging = left > 0  # a charging vehicle has no target
        move = ~((self._check.take(idx) & occ).bool() | charging)
        if active is not None:
            move &= active
            charging &= active
        code = charging * 2 + move  # 0 idle, 1 move, 2 charge
        if active is not None:
            code.masked_fill_(~active, 3)  # 3: frozen, no change
        code.masked_fill_(pos == self.park, 3)  # parked vehicles never change
        delta = torch.where(code == 2, par.gain, self._delta.take(code))
        s.soc.add_(delta).clamp_(max=100.0)
        left.sub_(charging.long())
        if self.leave_when_full:  # the charger ends the session on a full battery
            left.masked_fill_(charging & (s.soc >= 100.0), 0)
        into_c = move & (tgt == C)
        left.copy_(torch.where(into_c, par.t_c, left))
        queue = occ_d & s.charge & ~into_c.any(0)
        arrived = (move & (tgt == D)).any(0)
        s.pos = torch.where(move, tgt, pos)
        s.charge &= ~arrived  # the newcomer at D has not decided yet
        failed = (s.soc < self.soc_low).any(0)
        if active is not None:
            queue &= active
            failed &= active
            s.tick += active
        else:
            s.tick += 1
        return TickOutcome(arrived=arrived, queue=queue, failed=failed)

    def reserve_floor(self, params: SiteParams) -> Tensor:
        """Per site (``[B]`` float32), the soc below which a vehicle leaving ``D`` without a
        charge might not come back: ``SoC_low`` plus one lap moving every tick
        (``N_N * e_move``) plus waiting at ``D`` behind every other vehicle's full charge
        (``(N_V - 1) * T_C * e_idle``). A policy-independent safety line: the rollout planner
        never turns a charge into a pass below it."""
        cfg = self.cfg
        lap = cfg.soc_low + self.n_nodes * cfg.e_move
        wait = (params.n_vehicles - 1).clamp(min=0) * params.t_c * cfg.e_idle
        return (lap + wait).to(torch.float32)

    @staticmethod
    def decide(s: SiteState, mask: Tensor, charge: Tensor) -> None:
        """Record the decision (``charge``: ``[B]`` bool/0-1) of the sites in ``mask``."""
        s.charge = torch.where(mask, charge.to(torch.bool), s.charge)
