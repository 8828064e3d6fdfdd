"""Site distributions (MODEL §1.5): per-site parameters drawn from (seed, site index), parked
vehicles, and a mixed batch that is site for site the single sites it is drawn from."""

from __future__ import annotations

import copy
from dataclasses import replace

import pytest
import torch

from fleet_torchrl.agents import HeuristicPolicy, as_td_module
from fleet_torchrl.env import FleetChargingEnv, MDPConfig
from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import Site, SiteConfig, SiteRanges, rng
from fleet_torchrl.sim.rollout import run_sites
from fleet_torchrl.utils.checks import ConfigError

RANGES = SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9], t_c=[10, 50])
RANDOMIZED = SiteConfig(name="randomized", ranges=RANGES).validate()
BACKENDS = [False, True]


def single_site(params, b: int) -> SiteConfig:
    """The one-site config with site ``b``'s drawn parameters."""
    return replace(SiteConfig(), n_vehicles=int(params.n_vehicles[b]),
                   t_c=int(params.t_c[b]), p_c=float(params.p_c[b])).validate()


def test_draws_are_a_pure_function_of_seed_and_index():
    site = Site(RANDOMIZED)
    idx = torch.arange(2000)
    a, b = site.draw_params(7, idx), site.draw_params(7, idx)
    perm = torch.randperm(2000, generator=torch.Generator().manual_seed(0))
    shuffled = site.draw_params(7, idx[perm])  # what else is in the batch does not matter
    other = site.draw_params(8, idx)
    for name in ("n_vehicles", "t_c", "gain", "closure", "p_c"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.equal(getattr(a, name)[perm], getattr(shuffled, name)), name
        assert not torch.equal(getattr(a, name), getattr(other, name)), name
    # every value of the integer ranges, each about equally often; p_c fills its range
    assert sorted(a.n_vehicles.unique().tolist()) == [1, 2, 3, 4, 5]
    assert sorted(a.t_c.unique().tolist()) == list(range(10, 51))
    counts = torch.bincount(a.n_vehicles)[1:].float()
    assert counts.min() > 0.8 * counts.mean()
    assert 0.0 <= float(a.p_c.min()) < 0.02 and 0.88 < float(a.p_c.max()) < 0.9
    assert abs(float(a.p_c.mean()) - 0.45) < 0.03
    assert torch.equal(a.closure, torch.round(a.p_c * 2.0**32).long())
    assert torch.equal(a.gain, (40.0 / a.t_c.double()).float())


def test_a_parameter_without_range_keeps_the_site_value():
    cfg = SiteConfig(ranges=SiteRanges(t_c=[20, 30]), n_vehicles=4, p_c=0.6).validate()
    site = Site(cfg)
    p = site.draw_params(0, torch.arange(100))
    assert (p.n_vehicles == 4).all() and (p.p_c == 0.6).all()
    assert p.t_c.min() >= 20 and p.t_c.max() <= 30
    assert site.n_vehicles == 4


def test_parked_vehicles_are_inert():
    site = Site(RANDOMIZED)
    s, _ = site.init_state(3, torch.arange(256))
    parked = torch.arange(5)[:, None] >= s.params.n_vehicles
    assert parked.any() and (s.pos[parked] == site.park).all() and (s.soc[parked] == 100).all()
    assert ((s.pos == site.park) == parked).all()
    closed = site.closures(3, torch.arange(256), torch.arange(500)[:, None], s.params)
    for t in range(500):
        site.decide(s, torch.ones(256, dtype=torch.bool), torch.ones(256))
        site.tick(s, closed[t])
    assert (s.pos[parked] == site.park).all() and (s.soc[parked] == 100).all()
    assert (s.left[parked] == 0).all()
    assert ((s.pos == site.park) == parked).all()  # and no real vehicle ever parks


@pytest.mark.parametrize("use_fused", BACKENDS)
def test_mixed_batch_is_each_single_site_bit_for_bit(use_fused):
    """Simulation i of the distribution equals simulation i of the single site that has its
    drawn parameters (same seed and index): trips, queue ticks, failures, ticks survived."""
    n, ticks, seed = 48, 1500, 11
    policy, encode = HeuristicPolicy(), get_encoding("partial")

    def decide(site, s, ctx):
        return policy(encode(site, s))

    mixed = run_sites(decide, RANDOMIZED, n, ticks, seed, fused=use_fused)
    params = Site(RANDOMIZED).draw_params(seed, torch.arange(n))
    assert len(set(params.n_vehicles.tolist())) == 5
    for b in range(n):
        one = run_sites(decide, single_site(params, b), 1, ticks, seed, fused=use_fused,
                        site_index=torch.tensor([b]))
        for k in mixed:
            assert torch.equal(mixed[k][b:b + 1], one[k]), (b, k)


def test_mixed_batch_same_on_both_backends():
    a = simulate(HeuristicPolicy(), RANDOMIZED, 256, 2000, 2, fused=False)
    b = simulate(HeuristicPolicy(), RANDOMIZED, 256, 2000, 2, fused=True)
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.parametrize("use_fused", BACKENDS)
def test_env_draws_a_site_per_episode(use_fused):
    """Slot b's episode k is site k * B + b of the training seed: its parameters are those
    draws, and they change when the slot starts a new episode."""
    env = FleetChargingEnv(RANDOMIZED, "partial", 8, seed=4, fused=use_fused)
    env.reset()
    want = Site(RANDOMIZED).draw_params(rng.training_seed(4), torch.arange(8))
    assert torch.equal(env.state.params.t_c, want.t_c)
    assert torch.equal(env.state.params.n_vehicles, want.n_vehicles)
    mask = torch.zeros(8, dtype=torch.bool)
    mask[3] = True
    env.reset(env.current().set("_reset", mask[:, None]))
    again = Site(RANDOMIZED).draw_params(rng.training_seed(4), torch.tensor([8 + 3]))
    assert int(env.state.params.t_c[3]) == int(again.t_c[0])
    assert int(env.state.params.n_vehicles[3]) == int(again.n_vehicles[0])
    assert torch.equal(env.state.params.t_c[:3], want.t_c[:3])


def play(env: FleetChargingEnv, policy, steps: int) -> list:
    td, out = env.current(), []
    for _ in range(steps):
        td, root = env.step_and_maybe_reset(policy(td))
        out.append(td["next"].clone())
        td = root
    return out


def test_env_checkpoint_carries_the_drawn_sites():
    """A restored environment goes on with the same sites in flight (their parameters
    included) and the same later draws."""
    policy = as_td_module(HeuristicPolicy())
    env = FleetChargingEnv(RANDOMIZED, "partial", 16, MDPConfig(tau_e=300), seed=1)
    env.reset()
    play(env, policy, 60)
    sd = copy.deepcopy(env.state_dict())  # (a module's state_dict shares its buffers)
    follow = play(env, policy, 100)
    env2 = FleetChargingEnv(RANDOMIZED, "partial", 16, MDPConfig(tau_e=300), seed=99)
    env2.load_state_dict(sd)
    again = play(env2, policy, 100)
    assert any(bool(td["done"].any()) for td in follow)  # new sites were drawn on the way
    for a, b in zip(follow, again, strict=True):
        for key in ("observation", "reward", "trips", "done"):
            assert torch.equal(a[key], b[key]), key
    assert torch.equal(env.state.params.t_c, env2.state.params.t_c)


@pytest.mark.parametrize("field,value", [("n_vehicles", [0, 5]), ("n_vehicles", [1, 14]),
                                         ("p_c", [0.5, 0.2]), ("p_c", [0.0, 1.5]),
                                         ("t_c", [0, 10]), ("t_c", [10])])
def test_bad_ranges_are_rejected_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=rf"site\.ranges\.{field}"):
        SiteConfig(ranges=SiteRanges(**{field: value})).validate()
