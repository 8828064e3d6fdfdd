"""The fused event-driven advance (sim/fused.py) against the eager torch tick, bit for bit."""

from __future__ import annotations

import tempfile

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from fleet_torchrl.agents.base import Policy
from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
from fleet_torchrl.env import FleetChargingEnv
from fleet_torchrl.env.config import MDPConfig
from fleet_torchrl.evaluation import EvalConfig, simulate
from fleet_torchrl.sim import Site, SiteConfig, fused
from fleet_torchrl.utils.checks import ConfigError

pytestmark = pytest.mark.skipif(not fused.available(), reason="no C compiler for the kernel")

CONFIGS = {
    "default": SiteConfig(),
    "fixed_length_charges": SiteConfig(leave_when_full=False),
    "one_vehicle": SiteConfig(n_vehicles=1),
    "five_vehicles": SiteConfig(n_vehicles=5),
    "t_c_10": SiteConfig(t_c=10),
    "t_c_50": SiteConfig(t_c=50),
    "never_closed": SiteConfig(p_c=0.0),
    "p_c_0.9": SiteConfig(p_c=0.9),
    "eight_nodes": SiteConfig(n_nodes=8, closed_node=6),
}


class HashPolicy(Policy):
    """Random-looking actions that are a pure function of each observation row's bits (a
    stateful generator would draw differently when called once per tick vs once per
    decision epoch)."""

    name = "hash"

    def __init__(self, encoding: str = "partial") -> None:
        super().__init__()
        self.encoding = encoding

    def forward(self, obs: Tensor) -> Tensor:
        x = obs.contiguous().view(torch.int32).to(torch.int64).sum(-1)
        return ((x * 2654435761) >> 11) & 1


def tiny_dqn(encoding: str, n_obs: int) -> DQNPolicy:
    torch.manual_seed(0)
    return DQNPolicy(NetworkConfig(name=encoding, width=8, depth=1), n_obs, encoding)


def bits(t: Tensor) -> Tensor:
    return t.view(torch.int32) if t.dtype == torch.float32 else t


def assert_same_records(cfg: SiteConfig, policy: Policy, n_sims: int = 64, ticks: int = 800,
                        seed: int = 5) -> dict[str, Tensor]:
    eager = simulate(policy, cfg, n_sims, ticks, seed, fused=False)
    fast = simulate(policy, cfg, n_sims, ticks, seed, fused=True)
    for k in eager:
        assert torch.equal(eager[k], fast[k]), k
    return eager


@pytest.mark.parametrize("name", list(CONFIGS))
def test_simulate_records_identical_on_every_site(name):
    assert_same_records(CONFIGS[name], RulePolicy())


@pytest.mark.parametrize("policy", [
    HeuristicPolicy(),
    HashPolicy(),
    HashPolicy("all"),
    tiny_dqn("partial", 3),
    tiny_dqn("all", SiteConfig().n_nodes + 1),
], ids=["heuristic", "hash", "hash_all", "dqn_partial", "dqn_all"])
@pytest.mark.parametrize("name", ["default", "p_c_0.9", "five_vehicles"])
def test_simulate_records_identical_for_every_policy(name, policy):
    assert_same_records(CONFIGS[name], policy, n_sims=48, ticks=500)


@pytest.mark.parametrize("name", ["default", "t_c_50", "fixed_length_charges"])
def test_simulate_failing_sites_identical(name):
    rec = assert_same_records(CONFIGS[name], RulePolicy(threshold=32), ticks=1500)
    assert rec["failed"].any()  # a failed site stops in the fused loop, counts stop in both
    assert (rec["ticks_survived"][rec["failed"]] < 1500).all()


def test_advance_matches_the_eager_tick_loop_state_for_state():
    site = Site(SiteConfig(p_c=0.9, t_c=10))
    b = 200
    idx = torch.arange(b)
    s, needs = site.init_state(11, idx)
    site.decide(s, needs, idx % 3 == 0)
    h = site.site_hash(11, idx)
    active = idx % 7 != 0
    limit = 5 + idx % 40  # per-site tick limits
    mdp = MDPConfig(reward="throughput")
    ref = s.clone()
    out = fused.advance(site, s, h, limit, active, p_f=mdp.p_f, p_q=mdp.p_q, rho=mdp.rho,
                        gamma_tick=mdp.gamma_tick)
    # the eager loop of FleetChargingEnv._step (both rewards), with a per-site limit
    run = active.clone()
    n, trips, queue = (torch.zeros(b, dtype=torch.int64) for _ in range(3))
    cost, acc = torch.zeros(b), torch.zeros(b)
    disc = torch.ones(b)
    failed, arrived = torch.zeros(b, dtype=torch.bool), torch.zeros(b, dtype=torch.bool)
    while bool(run.any()):
        was = run.clone()
        o = site.tick(ref, site.closures_hashed(h, ref.tick), run)
        cost -= torch.where(o.failed, mdp.p_f, torch.where(o.queue, mdp.p_q, 0.0))
        acc += disc * (o.arrived.float() - mdp.rho * was - mdp.p_f * o.failed.float())
        disc = torch.where(was, disc * mdp.gamma_tick, disc)
        n += run
        trips += o.arrived
        queue += o.queue
        failed |= o.failed
        arrived = torch.where(was, o.arrived, arrived)
        run &= ~(o.arrived | o.failed | (ref.tick >= limit))
    for f in ("pos", "soc", "left", "charge", "tick"):
        assert torch.equal(bits(getattr(ref, f)), bits(getattr(s, f))), f
    assert torch.equal(out.ticks, n) and torch.equal(out.trips, trips)
    assert torch.equal(out.queue, queue) and torch.equal(out.failed, failed)
    assert torch.equal(out.arrived, arrived)
    assert torch.equal(bits(out.cost), bits(cost)) and torch.equal(bits(out.discounted),
                                                                   bits(acc))
    assert (out.ticks[~active] == 0).all() and (out.ticks[active] >= 1).all()


@pytest.mark.parametrize("reward,cfg", [("thesis", SiteConfig()),
                                        ("throughput", SiteConfig(n_vehicles=5, t_c=10))])
def test_env_rollouts_identical(reward, cfg):
    policy = TensorDictModule(HashPolicy(), in_keys=["observation"], out_keys=["action"])
    mdp = MDPConfig(reward=reward, tau_e=200)
    rollouts = []
    for use_fused in (False, True):
        env = FleetChargingEnv(cfg, "partial", 16, mdp, seed=3, fused=use_fused)
        assert env.fused is use_fused
        rollouts.append(env.rollout(150, policy, break_when_any_done=False))
    eager, fast = rollouts
    keys = list(eager.keys(True, True))
    assert ("next", "reward") in keys and ("next", "observation") in keys
    for k in keys:
        assert torch.equal(bits(eager[k]), bits(fast[k])), k
    assert eager["next", "terminated"].any() and eager["next", "truncated"].any()


def test_compiles_once_and_caches_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("FLEET_TORCHRL_CACHE", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    fused._reset_for_tests()
    try:
        before = fused.compilations
        fused.load()
        assert fused.compilations == before + 1
        assert fused.library_path() is not None
        assert fused.library_path().parent == tmp_path
        site = Site(SiteConfig())
        s, needs = site.init_state(0, torch.arange(4))
        site.decide(s, needs, torch.ones(4, dtype=torch.bool))
        fused.advance(site, s, site.site_hash(0, torch.arange(4)), 50)
        fused.advance(site, s, site.site_hash(0, torch.arange(4)), 100)
        assert fused.compilations == before + 1  # loaded once per process
        fused._reset_for_tests()
        fused.load()  # a new process would find it on disk
        assert fused.compilations == before + 1
    finally:
        fused._reset_for_tests()


def test_backend_switch():
    assert not fused.use_fused("cuda", None) and not fused.use_fused("cuda", True)
    assert not fused.use_fused("cpu", False) and fused.use_fused("cpu", None)
    assert EvalConfig(backend="eager").validate().backend == "eager"
    with pytest.raises(ConfigError, match="eval.backend"):
        EvalConfig(backend="jit").validate()
