"""Direct policy search (``agent=search``): the cross-entropy method on mean trips.

What it optimises is the quantity the evaluation reports: the mean trips per simulation on
common random numbers, with safety first (a candidate is ranked by its number of failed
simulations, then by its mean trips, so a candidate with any failure never beats a safe one).
It is this project's reference optimum of a policy class on a site: what the best member of
the class achieves there, against which the learners' gains can be judged (MODEL §3.4).

Policy classes (``agent.policy_class``), all on the ``partial`` encoding:

* ``table``: one action per cell of the discretisation of the tabular learner
  (:func:`fleet_torchrl.agents.tabular.state_index`), with ``agent.tc_bins`` charger bins
  (2: free / busy, the tabular learner's 200 cells; more: the busy time cut into shares, so
  the class can tell a charger that frees soon). The search distribution is one
  Bernoulli probability of *charge* per cell, started from a named policy (``agent.init``,
  ``p = 1 - p_min`` where it charges, ``p_min`` elsewhere; ``uniform``: 0.5 everywhere).
* ``threshold``: the six thresholds of :class:`fleet_torchrl.agents.threshold.ThresholdPolicy`
  (charge below ``low``; early while the charger is free; while it frees within ``busy_tc``).
  The search distribution is a diagonal Gaussian over them (socs / 100, ``sigma_init``
  defaults to 0.1 for this class), centred on the start's thresholds (the rule, the
  heuristic or a threshold policy; any other start begins at the heuristic's). A threshold
  outside the socs a site can have turns its rule off, so the Gaussian needs no special
  values.
* ``mlp``: a small network ``3 -> hidden (tanh) x depth -> 1`` that charges iff its output is
  positive. The search distribution is a diagonal Gaussian over its weights with standard
  deviation ``sigma_init``, centred on a network that imitates the ``agent.init`` policy
  (:func:`clone_policy`; ``uniform``: centred on 0).

One generation (one round of the training loop, :mod:`fleet_torchrl.training`):

1. draw ``agent.population`` candidates from the distribution; candidate 0 is the
   distribution's mode (the current greedy policy), so a generation always re-scores it;
2. simulate all of them in **one batched simulation** of ``population x sites`` sites for
   ``agent.ticks`` ticks (:func:`fleet_torchrl.sim.rollout.run_sites`): candidate ``k`` runs
   the sites ``k * sites ... (k + 1) * sites - 1`` of the batch, which are the site indices
   ``0 .. sites - 1`` of the generation's seed: every candidate sees the same initial states
   and closures (common random numbers), and a fresh set each generation (a hash of the
   training seed and the generation), apart from both evaluation sets;
3. rank, keep the ``agent.elite`` best, move the distribution towards them by
   ``agent.smoothing`` (the Bernoulli means / the Gaussian mean and standard deviation).

The training loop evaluates the mode every ``train.eval_every`` generations on its selection
set and keeps the best, as for every learner.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from ...env.encodings import get_encoding
from ...sim import SiteConfig
from ...sim import rng as _rng
from ...sim.fused import TABLE, THRESHOLD, KernelPolicy
from ...sim.rollout import run_sites
from ...utils.checks import check_choice, check_range
from ..base import INT, STR, Learner, Policy, check_spec_fields
from ..tabular.learner import N_SOC_BINS, n_cells, state_index
from ..threshold.policy import ThresholdPolicy, threshold_actions, threshold_row
from .config import POLICY_CLASSES, SearchAgentConfig

N_FEATURES = 3  # the partial encoding

# ------------------------------------------------------------------------ the policy class
def mlp_sizes(hidden: int, depth: int) -> list[tuple[int, int]]:
    """``(in, out)`` of each layer of the ``mlp`` class."""
    dims = [N_FEATURES, *([hidden] * depth), 1]
    return list(zip(dims[:-1], dims[1:], strict=True))


def mlp_n_params(sizes: list[tuple[int, int]]) -> int:
    return sum(i * o + o for i, o in sizes)


def mlp_logits(theta: Tensor, obs: Tensor, sizes: list[tuple[int, int]]) -> Tensor:
    """Outputs ``[K, n]`` of ``K`` networks (flat weights ``theta [K, P]``) on their own
    observations ``obs [K, n, F]``: one batched matrix product per layer."""
    k = theta.shape[0]
    x, at = obs, 0
    for j, (i, o) in enumerate(sizes):
        w = theta[:, at:at + i * o].view(k, i, o)
        at += i * o
        b = theta[:, at:at + o].view(k, 1, o)
        at += o
        x = torch.baddbmm(b, x, w)
        if j < len(sizes) - 1:
            x = torch.tanh(x)
    return x.squeeze(-1)


class SearchPolicy(Policy):
    """A member of a search policy class: a 200-cell action table or a small network."""

    name = "search"
    encoding = "partial"

    def __init__(self, policy_class: str = "table", hidden: int = 16, depth: int = 2,
                 n_tc: int = 2) -> None:
        super().__init__()
        self.policy_class, self.hidden, self.depth = policy_class, hidden, depth
        self.n_tc = n_tc
        if policy_class == "table":
            self.register_buffer("charge", torch.zeros(n_cells(n_tc), dtype=torch.int64))
        elif policy_class == "mlp":
            self.sizes = mlp_sizes(hidden, depth)
            self.register_buffer("theta", torch.zeros(mlp_n_params(self.sizes)))
        elif policy_class == "threshold":
            self.register_buffer("theta", threshold_row(40.0))
        else:
            raise ValueError(f"policy_class={policy_class!r} is invalid: allowed one of "
                             f"{', '.join(POLICY_CLASSES)}")

    def policy_spec(self) -> dict[str, Any]:
        return {"policy_class": self.policy_class, "hidden": self.hidden, "depth": self.depth,
                "n_tc": self.n_tc}

    size_fields = "spec.hidden, spec.depth and spec.n_tc"

    @classmethod
    def check_policy_spec(cls, spec: dict[str, Any]) -> None:
        check_spec_fields(spec, {"policy_class": STR, "hidden": INT, "depth": INT,
                                 "n_tc": INT})
        check_choice("spec.policy_class", spec.get("policy_class", "table"), POLICY_CLASSES)
        check_range("spec.hidden", spec.get("hidden", 16), 1, 4096)
        check_range("spec.depth", spec.get("depth", 2), 0, 16)
        check_range("spec.n_tc", spec.get("n_tc", 2), 2, 64)

    def check_loaded(self) -> str | None:
        """An action table holds 0 (pass) or 1 (charge) in every cell."""
        if self.policy_class != "table":
            return None  # a network charges iff its output is positive, thresholds compare
        bad = ((self.charge != 0) & (self.charge != 1)).nonzero()
        if bad.numel():
            i = int(bad[0, 0])
            return (f"charge[{i}] = {int(self.charge[i])}: an action table holds 0 (pass) or "
                    "1 (charge) only")
        return None

    def params(self) -> Tensor:
        """The flat parameters the search distribution is over."""
        return self.charge if self.policy_class == "table" else self.theta

    def forward(self, obs: Tensor) -> Tensor:
        # a population of one: the same code decides for a saved policy and in the search
        return population_actions(self.policy_class, self.params()[None], obs,
                                  getattr(self, "sizes", None), self.n_tc)

    def kernel_policy(self) -> KernelPolicy | None:
        return population_kernel_policy(self.policy_class, self.params()[None], 1, self.n_tc)


def population_actions(policy_class: str, params: Tensor, obs: Tensor,
                       sizes: list[tuple[int, int]] | None = None, n_tc: int = 2) -> Tensor:
    """Actions ``[K * n]`` of ``K`` candidates (``params [K, P]``) on a candidate-major batch
    of observations ``[K * n, F]`` (candidate ``k`` owns rows ``k * n ... (k + 1) * n - 1``)."""
    k = params.shape[0]
    if policy_class == "table":
        cell = state_index(obs, n_tc).view(k, -1)
        return params.gather(1, cell).reshape(-1).long()
    if policy_class == "threshold":
        return threshold_actions(params, obs.view(k, -1, obs.shape[-1])).reshape(-1)
    assert sizes is not None
    return (mlp_logits(params, obs.view(k, -1, obs.shape[-1]), sizes) > 0).reshape(-1).long()


def population_kernel_policy(policy_class: str, params: Tensor, sites: int,
                             n_tc: int = 2) -> KernelPolicy | None:
    """The in-kernel form of ``K`` candidates (``params [K, P]``) on a candidate-major batch
    of ``K * sites`` sites, or ``None`` for the network class (batched forward passes)."""
    k = params.shape[0]
    rows = torch.arange(k, dtype=torch.int64).repeat_interleave(sites)
    if policy_class == "table":
        return KernelPolicy(TABLE, table=params.to(torch.int8).cpu(), n_tc=n_tc, rows=rows)
    if policy_class == "threshold":
        return KernelPolicy(THRESHOLD, thresholds=params.to(torch.float32).cpu(), rows=rows)
    return None


@torch.no_grad()
def evaluate_population(policy_class: str, params: Tensor, site_cfg: SiteConfig, sites: int,
                        ticks: int, seed: int, sizes: list[tuple[int, int]] | None = None,
                        fused: bool | None = None, n_tc: int = 2) -> dict[str, Tensor]:
    """Every candidate of ``params [K, P]`` on the same ``sites`` sites of ``seed`` in one
    batched simulation. Returns ``[K, sites]`` records (``trips``, ``queue``, ``failed``,
    ``ticks_survived``): row ``k`` is exactly what a separate simulation of candidate ``k``
    on sites ``0 .. sites - 1`` gives."""
    k = params.shape[0]
    encode = get_encoding("partial")
    params = params.cpu()
    rec = run_sites(lambda site, s, ctx: population_actions(policy_class, params,
                                                            encode(site, s), sizes, n_tc),
                    site_cfg, k * sites, ticks, seed, "cpu", fused=fused,
                    site_index=torch.arange(sites, dtype=torch.int64).repeat(k),
                    kernel_policy=population_kernel_policy(policy_class, params, sites, n_tc))
    return {key: v.view(k, sites) for key, v in rec.items()}


def rank_key(failed: Tensor, trips: Tensor) -> Tensor:
    """Score of each candidate (``[K, n]`` records): fewer failed sites first, then more
    mean trips (any failure ranks below every safe candidate)."""
    n_failed = failed.sum(1).to(torch.float64)
    mean_trips = trips.to(torch.float64).mean(1)
    return -n_failed * 1e9 + mean_trips


def generation_seed(train_seed: int, generation: int) -> int:
    """The simulation seed of a generation: apart from the evaluation seeds, a pure function
    of (training seed, generation)."""
    return int(_rng.hash_ints(_rng.training_seed(train_seed), generation, _rng.STREAM_SEARCH))


class SearchLearner(Learner):
    """The cross-entropy method over a :class:`SearchPolicy` class (module docstring).

    It takes no environment steps (``steps_per_round = 0``): each round of the training loop
    is one generation, simulated by :func:`evaluate_population`.
    """

    steps_per_round = 0
    reset_each_round = False
    evaluate_start = True  # the start (e.g. a seeded policy) competes for the best snapshot

    @classmethod
    def from_context(cls, c: Any) -> SearchLearner:
        """Starts from ``agent.init``: uniform, a baseline or a saved policy, which must read
        the partial state the classes read."""
        from ..registry import base_policy

        init = c.agent.init
        if init == "uniform":
            start = None
        else:
            start = base_policy(init)
            if start.encoding != "partial":
                raise ValueError(f"agent.init={init!r}: a {start.encoding!r}-state policy "
                                 "cannot start a search over partial-state policies")
        return cls(c.agent, c.site, c.seed, start).to(c.device)

    def __init__(self, agent: SearchAgentConfig, site_cfg: SiteConfig, seed: int,
                 init_policy: Policy | None = None) -> None:
        super().__init__()
        self.agent, self.site_cfg, self.seed = agent, site_cfg, seed
        self.greedy = SearchPolicy(agent.policy_class, agent.hidden, agent.depth, agent.tc_bins)
        self.sizes = getattr(self.greedy, "sizes", None)
        if agent.policy_class == "table":
            if init_policy is None:
                p = torch.full((n_cells(agent.tc_bins),), 0.5)
            else:
                p = init_policy(cell_centres(agent.tc_bins)).float().clamp(agent.p_min,
                                                                           1 - agent.p_min)
            self.register_buffer("mean", p)
            self.register_buffer("std", torch.zeros(0))
        else:
            n = self.greedy.theta.numel()
            if agent.policy_class == "threshold":
                start = threshold_start(init_policy)
            else:
                start = torch.zeros(n) if init_policy is None else clone_policy(
                    init_policy, self.sizes, seed, site_cfg)
            self.register_buffer("mean", start)
            self.register_buffer("std", torch.full((n,), agent.initial_sigma))
        self.register_buffer("generation", torch.zeros((), dtype=torch.int64))
        self._sync_greedy()

    def _sync_greedy(self) -> None:
        if self.agent.policy_class == "table":
            self.greedy.charge.copy_((self.mean > 0.5).long())
        else:
            self.greedy.theta.copy_(self.mean)

    # ------------------------------------------------------------------ Learner
    def policy(self) -> SearchPolicy:
        return self.greedy

    exploration_tag = "train/spread"  # not an epsilon: the distribution's spread

    def exploration(self) -> float:
        """The spread of the search distribution: mean Bernoulli variance ``p (1 - p)`` of the
        table, mean standard deviation of the network's weights."""
        if self.agent.policy_class == "table":
            return float((self.mean * (1 - self.mean)).mean())
        return float(self.std.mean())

    def act(self, td: TensorDictBase) -> TensorDictBase:
        return td.set("action", self.greedy(td["observation"]))

    def observe(self, td: TensorDictBase, learn: Tensor) -> None:  # no environment steps
        pass

    def sample(self) -> Tensor:
        """``population`` candidates ``[K, P]``; candidate 0 is the mode."""
        a = self.agent
        if a.policy_class == "table":
            cand = (torch.rand(a.population, self.mean.numel(), device=self.mean.device)
                    < self.mean).long()
            cand[0] = (self.mean > 0.5).long()
        else:
            cand = self.mean + self.std * torch.randn(a.population, self.mean.numel(),
                                                      device=self.mean.device)
            cand[0] = self.mean
        return cand

    @torch.no_grad()
    def update(self) -> dict[str, float]:
        """One generation: sample, simulate the population, move towards the elite."""
        a = self.agent
        cand = self.sample()
        seed = generation_seed(self.seed, int(self.generation))
        rec = evaluate_population(a.policy_class, cand, self.site_cfg, a.sites, a.ticks, seed,
                                  self.sizes, n_tc=a.tc_bins)
        key = rank_key(rec["failed"], rec["trips"])
        order = key.argsort(descending=True, stable=True)[:a.elite]
        if a.elitist:  # only candidates that beat the mode on these sites pull the mean
            order = order[key[order] > key[0]]
        if order.numel():  # (none left: the distribution stays)
            elite = cand[order].to(self.mean.dtype)
            s = a.smoothing
            self.mean.mul_(1 - s).add_(s * elite.mean(0))
            if a.policy_class == "table":
                self.mean.clamp_(a.p_min, 1 - a.p_min)
            else:
                self.std.mul_(1 - s).add_(s * elite.std(0, unbiased=False))
                self.std.clamp_(min=a.sigma_min)
            self._sync_greedy()
        self.generation += 1
        return self._stats(rec, key, moved=int(order.numel()))

    @staticmethod
    def _stats(rec: dict[str, Tensor], key: Tensor, moved: int) -> dict[str, float]:
        trips = rec["trips"].to(torch.float64).mean(1)
        safe = rec["failed"].sum(1) == 0
        return {"train/mode_trips": float(trips[0]), "train/elite_used": moved,
                "train/best_trips": float(trips[key.argmax()]),
                "train/safe_share": float(safe.float().mean()),
                "train/mode_failures": float(rec["failed"][0].float().mean()),
                # decisions simulated: every arrival at D (a trip) is one decision
                "frames": int(rec["trips"].sum())}


def clone_policy(policy: Policy, sizes: list[tuple[int, int]], seed: int,
                 site_cfg: SiteConfig | None = None, n_states: int = 20_000,
                 steps: int = 1500) -> Tensor:
    """Flat weights of an ``mlp`` member that imitates ``policy`` (behaviour cloning on
    random ``partial`` states of the site, logistic loss): the Gaussian search's starting
    mean."""
    site_cfg = site_cfg or SiteConfig()
    g = torch.Generator().manual_seed(seed)
    lo = site_cfg.soc_low / 100.0
    soc = lo + (1.0 - lo) * torch.rand(n_states, 2, generator=g)
    busy = torch.rand(n_states, generator=g) < 0.5
    tc = torch.where(busy, torch.rand(n_states, generator=g).clamp(min=1 / (site_cfg.t_c + 1)),
                     0.0)
    obs = torch.cat([soc, tc[:, None]], dim=1)
    with torch.no_grad():
        target = policy(obs).float()
    theta = (0.3 * torch.randn(mlp_n_params(sizes), generator=g)).requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=0.02)
    for _ in range(steps):
        logits = mlp_logits(theta[None], obs[None], sizes)[0]
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return theta.detach()


# finite stand-ins for "off" in a Gaussian search, at the edge where a small step turns the
# rule on (a live soc is at least soc_low, 30 by default; TC of a busy charger is above 0)
_OFF = {1: 0.3, 3: 1.0, 4: 0.0, 5: 0.3}  # free_upper, others_below, busy_tc, busy_upper


def threshold_start(policy: Policy | None) -> Tensor:
    """The thresholds a threshold-class search starts from: the start policy's own (the
    rule, the heuristic, a threshold policy), else the heuristic's; rules a policy does not
    use are set just off (finite, so the Gaussian can move them on)."""
    from ..baselines.policy import HeuristicPolicy, RulePolicy

    if isinstance(policy, ThresholdPolicy):
        row = policy.theta.clone()
    elif isinstance(policy, SearchPolicy) and policy.policy_class == "threshold":
        row = policy.theta.clone()
    elif isinstance(policy, RulePolicy):
        row = threshold_row(policy.threshold)
    else:
        h = policy if isinstance(policy, HeuristicPolicy) else HeuristicPolicy()
        row = threshold_row(h.threshold, h.upper, 0.0,
                            h.others_below if h.others_below < 100 else None)
    for i, off in _OFF.items():
        if not torch.isfinite(row[i]) or (i == 4 and row[i] < 0):
            row[i] = off
    return row.float()


def cell_centres(n_tc: int = 2) -> Tensor:
    """One ``partial`` observation at the centre of each cell of the discretisation with
    ``n_tc`` charger bins, in cell order (so ``policy(cell_centres())`` is a policy's action
    table): socs at the middle of their bins, TC 0 (free) or the middle of its share of
    (0, 1]."""
    cells = torch.arange(n_cells(n_tc))
    tc_bin = cells % n_tc
    soc_bins = cells // n_tc
    soc_d, others = soc_bins // N_SOC_BINS, soc_bins % N_SOC_BINS
    tc = torch.where(tc_bin > 0, (tc_bin - 0.5) / max(n_tc - 1, 1), 0.0)
    obs = torch.stack(((soc_d * 10 + 5) / 100.0, (others * 10 + 5) / 100.0, tc), dim=1).float()
    assert bool((state_index(obs, n_tc) == cells).all())
    return obs


__all__ = ["POLICY_CLASSES", "SearchAgentConfig", "SearchLearner", "SearchPolicy",
           "cell_centres", "evaluate_population", "generation_seed", "mlp_logits", "rank_key"]
