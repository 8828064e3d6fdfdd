"""The batched TorchRL environment: specs, decision epochs, rewards, resets, seeds."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy, as_td_module
from fleet_torchrl.env import FleetChargingEnv, MDPConfig, discount_exponent, step_ticks
from fleet_torchrl.sim import D, SiteConfig
from fleet_torchrl.sim.config import SiteRanges


@pytest.mark.parametrize("encoding", ["partial", "all"])
@pytest.mark.parametrize("num_sites", [1, 64])
def test_check_env_specs(encoding, num_sites):
    env = FleetChargingEnv(encoding=encoding, num_sites=num_sites)
    check_env_specs(env, seed=0)
    n_feat = 3 if encoding == "partial" else 16
    assert env.observation_spec["observation"].shape == (num_sites, n_feat)
    assert env.action_spec.shape == (num_sites,)


def test_every_step_starts_at_a_decision():
    env = FleetChargingEnv(num_sites=16, seed=1)
    td = env.reset()
    for _ in range(30):
        # a vehicle sits at D awaiting a decision in every site that is not done
        assert (env.state.pos == D).any(0).all()
        td = env.step(td.set("action", torch.randint(0, 2, (16,))))
        td = env.step_mdp(td) if not td["next", "done"].any() else env.reset()


def test_reward_is_mean_tick_cost_and_counters_add_up():
    env = FleetChargingEnv(num_sites=32, seed=2)
    td = env.rollout(100, as_td_module(RulePolicy()), break_when_any_done=False)
    ticks = td["next", "ticks"] - td["ticks"]
    queue = td["next", "queue_ticks"] - td["queue_ticks"]
    trips = td["next", "trips"] - td["trips"]
    ok = ~td["next", "done"]  # counters restart at resets
    assert (ticks[ok] >= 1).all()
    # rule never fails on the default site here: the cost is queue ticks only
    assert not td["next", "terminated"].any()
    assert torch.allclose(td["next", "reward"][ok], -queue[ok].float() / ticks[ok].float())
    assert (trips[ok] == 1).all()  # a step ends with exactly one arrival at D
    assert td["next", "reward"].min() < 0  # the rule queues


def test_throughput_reward_of_a_step_by_hand():
    """``mdp.reward=throughput``: tick k of a step earns ``gamma_tick^k (trip - rho)``; a step
    of dt ticks ends with its one trip: ``g^(dt-1) - rho (1 - g^dt) / (1 - g)``."""
    g, rho = 0.97, 0.1
    mdp = MDPConfig(reward="throughput", gamma_tick=g, rho=rho)
    plain = FleetChargingEnv(num_sites=16, seed=3)
    trips = FleetChargingEnv(num_sites=16, seed=3, mdp=mdp)
    rule = as_td_module(RulePolicy())
    a = plain.rollout(40, rule, break_when_any_done=False)
    b = trips.rollout(40, rule, break_when_any_done=False)
    assert (a["next", "queue_ticks"] == b["next", "queue_ticks"]).all()  # same dynamics
    dt = step_ticks(b).double()
    ok = ~b["next", "done"]
    by_hand = g ** (dt - 1) - rho * (1 - g ** dt) / (1 - g)
    assert torch.allclose(b["next", "reward"][ok].double(), by_hand[ok], atol=1e-5)
    assert torch.equal(discount_exponent(b, mdp), dt.float())  # the learners' gamma_tick^dt
    assert (discount_exponent(a, MDPConfig()) == 1).all()  # thesis: per decision
    assert mdp.discount == g and MDPConfig().discount == 0.9


def test_throughput_reward_of_a_failing_step_by_hand():
    """A failure tick costs ``p_f`` (discounted like every tick) and ends the episode."""
    site = SiteConfig(e_move=5.0, xi=60.0, soc_low=30.0)
    g, rho, p_f = 0.9, 0.2, 50.0
    env = FleetChargingEnv(site=site, num_sites=8, seed=0,
                           mdp=MDPConfig(reward="throughput", gamma_tick=g, rho=rho, p_f=p_f))
    pass_always = TensorDict({"action": torch.zeros(8, dtype=torch.int64)}, batch_size=[8])
    td = env.reset()
    for _ in range(50):
        td = env.step(td.update(pass_always))
        nxt = td["next"]
        failed = nxt["terminated"].squeeze(-1)
        if failed.any():
            dt = step_ticks(td)[failed].squeeze(-1).double()
            # every tick pays rho, the last one p_f as well, and earns its trip if a vehicle
            # reached D in the failing tick (the only tick of a step that can hold a trip)
            trip = (nxt["trips"] - td["trips"])[failed].squeeze(-1).double()
            by_hand = -rho * (1 - g ** dt) / (1 - g) + (trip - p_f) * g ** (dt - 1)
            assert torch.allclose(nxt["reward"][failed].squeeze(-1).double(), by_hand,
                                  atol=1e-4)
            return
        td = env.step_mdp(td)
    raise AssertionError("no site failed")


def test_failure_terminates_with_failure_cost():
    site = SiteConfig(e_move=5.0, xi=60.0, soc_low=30.0)
    env = FleetChargingEnv(site=site, num_sites=8, seed=0)
    pass_always = TensorDict({"action": torch.zeros(8, dtype=torch.int64)}, batch_size=[8])
    td = env.reset()
    for _ in range(50):
        td = env.step(td.update(pass_always))
        term = td["next", "terminated"].squeeze(-1)
        if term.any():
            ticks = (td["next", "ticks"] - td["ticks"]).squeeze(-1)
            r = td["next", "reward"].squeeze(-1)
            assert torch.allclose(r[term], -50.0 / ticks[term].float())
            assert td["next", "done"].squeeze(-1)[term].all()
            return
        td = env.step_mdp(td)
    pytest.fail("never failed with 5 energy per move and no charging")


def test_truncation_at_tick_budget():
    env = FleetChargingEnv(num_sites=4, mdp=MDPConfig(tau_e=60), seed=0)
    td = env.rollout(100, as_td_module(RulePolicy()), break_when_any_done=True)
    last = td[:, -1]
    assert last["next", "truncated"].any() and not last["next", "terminated"].any()
    assert (last["next", "ticks"][last["next", "truncated"]] >= 60).all()


def test_partial_reset_only_touches_masked_sites():
    env = FleetChargingEnv(num_sites=6, seed=3)
    td = env.reset()
    td = env.step_mdp(env.step(td.set("action", torch.ones(6, dtype=torch.int64))))
    before = env.state.clone()
    mask = torch.tensor([True, False, True, False, False, False])
    inp = td.clone().set("_reset", mask.unsqueeze(-1))
    out = env.reset(inp)
    keep = ~mask
    assert torch.equal(env.state.pos[:, keep], before.pos[:, keep])
    assert torch.equal(env.state.soc[:, keep], before.soc[:, keep])
    assert torch.equal(out["observation"][keep], td["observation"][keep])
    assert torch.equal(env._observe()["observation"], out["observation"])
    assert not torch.equal(env.state.soc[:, mask], before.soc[:, mask])
    assert (out["queue_ticks"][mask] == 0).all()


def test_training_sites_are_not_the_evaluation_sites():
    from fleet_torchrl.sim import Site
    from fleet_torchrl.sim.rng import training_seed

    env = FleetChargingEnv(num_sites=16, seed=0)
    assert env._seed == training_seed(0) != 0
    env.set_seed(3)
    assert env._seed == training_seed(3)
    site = Site(SiteConfig())
    train_sites, _ = site.init_state(env._seed, torch.arange(16))
    eval_sites, _ = site.init_state(0, torch.arange(16))  # evaluation sims 0..15, seed 0
    assert not torch.equal(train_sites.soc, eval_sites.soc)


def test_same_seed_same_rollout_and_new_seed_differs():
    def roll(seed):
        env = FleetChargingEnv(num_sites=8)
        env.set_seed(seed)
        return env.rollout(40, as_td_module(HeuristicPolicy()), break_when_any_done=False)

    a, b, c = roll(5), roll(5), roll(6)
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])
    assert not torch.equal(a["next", "observation"], c["next", "observation"])


# a site that fails often, with a soc below zero at its failure (a move costs 40 of a soc
# that may start at 10): what once put observations outside Bounded(0, 1)
DEEP_FAILS = SiteConfig(soc_low=10.0, xi=0.0, e_move=40.0)


def _step_until_a_site_fails(env, td):
    for _ in range(100):
        td = env.step(td.set("action", torch.zeros(env.num_sites, dtype=torch.int64)))
        if td["next", "terminated"].any():
            return td
        td = env.step_mdp(td)
    raise AssertionError("no site failed")


def test_a_terminated_site_is_stepped_only_after_its_reset():
    env = FleetChargingEnv(site=SiteConfig(e_move=5.0, xi=60.0, soc_low=30.0), num_sites=4,
                           seed=0)
    td = _step_until_a_site_fails(env, env.reset())
    ended = td["next", "terminated"].squeeze(-1)
    assert torch.equal(env.ended(), ended)
    root = env.step_mdp(td).set("action", torch.zeros(4, dtype=torch.int64))
    with pytest.raises(ValueError, match="terminated and were not reset: reset them") as e:
        env.step(root.clone())
    assert "\n" not in str(e.value)
    # left out with TorchRL's partial-step mask, a terminated site stays as it is
    before = env.state.clone()
    out = env.step(root.clone().set("_step", ~ended))["next"]
    assert torch.equal(env.state.soc[:, ended], before.soc[:, ended])
    assert torch.equal(out["ticks"][ended], root["ticks"][ended])
    assert (out["reward"][ended] == 0).all() and out["terminated"][ended].all()
    # reset (only the done sites, as step_and_maybe_reset does), it steps again
    done = out["done"].squeeze(-1) | ended
    env.reset(out.clone().set("_reset", done.unsqueeze(-1)))
    assert not env.ended().any()
    env.step(env.current().set("action", torch.zeros(4, dtype=torch.int64)))


def test_observations_stay_inside_their_spec_on_a_site_that_fails():
    env = FleetChargingEnv(site=DEEP_FAILS, num_sites=16, seed=0)
    spec = env.observation_spec["observation"]
    td = env.rollout(60, as_td_module(RulePolicy()), break_when_any_done=False)
    assert td["next", "terminated"].sum() >= 5  # it fails, often
    for obs in (td["observation"], td["next", "observation"]):
        assert spec.is_in(obs[:, 0]) and obs.min() >= 0 and obs.max() <= 1
    # at its failure a vehicle's soc went below zero: the feature reads 0, not below
    fails = FleetChargingEnv(site=DEEP_FAILS, num_sites=64, seed=1, encoding="all")
    td = _step_until_a_site_fails(fails, fails.reset())
    assert (fails.state.soc < 0).any(), "no soc below zero: the case is not exercised"
    assert td["next", "observation"].min() >= 0


def test_every_episode_plays_to_its_end_with_partial_steps():
    """TorchRL's ``rollout(break_when_all_done=True)`` steps only the sites still running
    (its ``"_step"`` mask): no site is stepped after it terminated, and each one ends."""
    env = FleetChargingEnv(site=DEEP_FAILS, num_sites=8, seed=2, mdp=MDPConfig(tau_e=400))
    td = env.rollout(500, as_td_module(RulePolicy()), break_when_any_done=False,
                     break_when_all_done=True)
    assert td["next", "done"].any(-2).all()  # every site's episode ended
    assert env.observation_spec["observation"].is_in(td["next", "observation"][:, -1])
    check_env_specs(env, seed=0)


def test_the_env_says_what_it_simulates():
    env = FleetChargingEnv(site=SiteConfig(name="mine", p_c=0.5), encoding="all", num_sites=3,
                           mdp=MDPConfig(reward="throughput"))
    text = repr(env)
    assert text == str(env) and len(text.splitlines()) <= 4
    for part in ("FleetChargingEnv(", "batch_size=[3]", "device=cpu", "site='mine'",
                 "p_c=0.5", "n_vehicles=3", "encoding='all' (16 features)",
                 "reward='throughput'", "tau_e=3000", "gamma_tick=0.998"):
        assert part in text, (part, text)
    drawn = repr(FleetChargingEnv(site=SiteConfig(ranges=SiteRanges(t_c=[10, 50]))))
    assert "drawn per site: t_c=[10, 50]" in drawn and "reward='thesis'" in drawn


def test_specs_hold_on_a_site_that_fails():
    check_env_specs(FleetChargingEnv(site=DEEP_FAILS, num_sites=8, seed=0), seed=0)
