"""TorchRL's own tools on the environment, beside ``check_env_specs`` (tests/env/test_env.py):
``ParallelEnv`` from a lambda, a ``functools.partial`` or an ``EnvCreator`` (all of which load
the env's ``state_dict`` with ``strict=False`` and its tensors left out), and ``Collector``
driven by a project policy wrapped with ``as_td_module``."""

from __future__ import annotations

import functools
import warnings

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import EnvCreator, ParallelEnv

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy, as_td_module
from fleet_torchrl.env import FleetChargingEnv
from fleet_torchrl.sim import SiteConfig

SITES, STEPS = 4, 12


def _alone(seed: int):
    """The rollout one env of ``seed`` makes by itself under the rule (what a worker of a
    ParallelEnv must reproduce)."""
    env = FleetChargingEnv(num_sites=SITES, seed=seed)
    return env.rollout(STEPS, as_td_module(RulePolicy()), break_when_any_done=False)


@pytest.mark.parametrize("how", ["lambda", "partial", "env_creator"])
def test_parallel_env_workers_run_the_env_they_were_given(how):
    makers = {
        "lambda": [lambda: FleetChargingEnv(num_sites=SITES, seed=0),
                   lambda: FleetChargingEnv(num_sites=SITES, seed=1)],
        "partial": [functools.partial(FleetChargingEnv, num_sites=SITES, seed=s)
                    for s in (0, 1)],
        "env_creator": [EnvCreator(lambda: FleetChargingEnv(num_sites=SITES, seed=0)),
                        EnvCreator(functools.partial(FleetChargingEnv, num_sites=SITES,
                                                     seed=1))],
    }[how]
    env = ParallelEnv(2, makers)
    try:
        td = env.rollout(STEPS, as_td_module(RulePolicy()), break_when_any_done=False)
    finally:
        env.close()
    assert td.shape == (2, SITES, STEPS)
    for worker, seed in enumerate((0, 1)):
        alone = _alone(seed)
        for key in ("observation", ("next", "observation"), ("next", "reward"),
                    ("next", "trips"), "action"):
            assert torch.equal(td[worker][key], alone[key]), (worker, key)
    assert not torch.equal(td[0]["observation"], td[1]["observation"])  # seeds differ


def test_parallel_env_of_one_maker_passes_check_env_specs():
    from torchrl.envs.utils import check_env_specs

    env = ParallelEnv(2, lambda: FleetChargingEnv(num_sites=SITES))
    try:
        check_env_specs(env, seed=0)
        assert env.batch_size == (2, SITES)
    finally:
        env.close()


def test_load_state_dict_strict_false_keeps_what_is_missing():
    env = FleetChargingEnv(num_sites=SITES, seed=3)
    env.rollout(5, as_td_module(RulePolicy()), break_when_any_done=False)
    before = env.state_dict()
    env.load_state_dict({}, strict=False)  # what EnvCreator passes once tensors are shared
    after = env.state_dict()
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    other = FleetChargingEnv(num_sites=SITES, seed=9)
    part = {k: v for k, v in other.state_dict().items() if k in ("site.soc", "seed")}
    env.load_state_dict(part, strict=False)  # what is given is taken, the rest kept
    now = env.state_dict()
    assert torch.equal(now["site.soc"], part["site.soc"]) and int(now["seed"]) == int(
        part["seed"])
    assert torch.equal(now["site.pos"], before["site.pos"])
    with pytest.raises(RuntimeError, match="missing key.*site.pos"):
        env.load_state_dict({}, strict=True)


def _tabular():
    from fleet_torchrl.agents.tabular import TabularQPolicy

    pol = TabularQPolicy()
    pol.q.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
    return pol


def _dqn():
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig

    torch.manual_seed(0)
    return DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial", "heuristic", 0.5)


def _dqn_greedy():
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig

    torch.manual_seed(1)
    return DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial")


def _threshold():
    from fleet_torchrl.agents.threshold import ThresholdPolicy

    return ThresholdPolicy(low=30.0, free_upper=70.0, busy_tc=0.4, busy_upper=50.0)


def _imitation():
    from fleet_torchrl.agents.imitation import ImitationPolicy

    torch.manual_seed(2)
    return ImitationPolicy(hidden=8, depth=1)


def _search():
    from fleet_torchrl.agents.search import SearchPolicy

    pol = SearchPolicy("mlp", hidden=4, depth=1)
    pol.theta.normal_(generator=torch.Generator().manual_seed(0))
    return pol


POLICIES = {"rule": RulePolicy, "heuristic": HeuristicPolicy, "threshold": _threshold,
            "tabular": _tabular, "dqn": _dqn, "dqn_greedy": _dqn_greedy, "search": _search,
            "imitation": _imitation}


@pytest.mark.parametrize("make", POLICIES.values(), ids=POLICIES.keys())
def test_collector_runs_a_wrapped_project_policy(make):
    """Every policy class, the learned ones with ``policy_spec`` among them, drives TorchRL's
    Collector (a method named ``spec`` used to shadow the attribute TorchRL reads), with no
    warning: the env reports ``is_init`` itself, so the collector misses no InitTracker."""
    policy = make()
    env = FleetChargingEnv(num_sites=SITES, seed=0)
    frames = SITES * 10
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # TorchRL's FutureWarning about InitTracker included
        collector = Collector(env, as_td_module(policy), frames_per_batch=frames,
                              total_frames=2 * frames)
        try:
            batches = [b.clone() for b in collector]
        finally:
            collector.shutdown()
    assert [b.numel() for b in batches] == [frames, frames]
    for batch in batches:
        flat = batch.reshape(-1)  # the policies' own [B, F] -> [B] form
        assert torch.equal(flat["action"], policy(flat["observation"]))
        assert batch["next", "ticks"].gt(batch["ticks"]).all()  # every step moves time on
    # the first batch is the rollout of a fresh env under the same policy
    alone = FleetChargingEnv(num_sites=SITES, seed=0).rollout(
        10, as_td_module(policy), break_when_any_done=False)
    assert torch.equal(batches[0]["next", "observation"], alone["next", "observation"])


def test_load_state_dict_keeps_drawn_site_parameters_that_are_absent():
    from fleet_torchrl.sim import SiteRanges

    site = SiteConfig(ranges=SiteRanges(n_vehicles=[1, 5], p_c=[0.0, 0.9], t_c=[10, 50]))
    env = FleetChargingEnv(site=site, num_sites=SITES, seed=4)
    sd = env.state_dict()
    params = {k: v for k, v in sd.items() if k.startswith("site.params.")}
    assert params  # a distribution's checkpoint holds its draws
    other = FleetChargingEnv(site=site, num_sites=SITES, seed=5)
    other.load_state_dict({k: v for k, v in sd.items() if k not in params}, strict=True)
    assert int(other.state_dict()["seed"]) == int(sd["seed"])
    kept = other.state_dict()
    fresh = FleetChargingEnv(site=site, num_sites=SITES, seed=5).state_dict()
    assert not all(torch.equal(v, fresh[k]) for k, v in params.items())  # seeds draw apart
    assert all(torch.equal(kept[k], fresh[k]) for k in params)  # its own draws, kept
    other.load_state_dict(sd)
    assert all(torch.equal(other.state_dict()[k], v) for k, v in params.items())


def test_env_reports_where_episodes_start():
    """``is_init`` (InitTracker's key): true on a reset site, false after a step; a partial
    reset marks only the sites it restarts."""
    env = FleetChargingEnv(num_sites=SITES, seed=0)
    td = env.reset()
    assert td["is_init"].shape == (SITES, 1) and td["is_init"].all()
    td = env.step(as_td_module(RulePolicy())(td))
    assert not td["next", "is_init"].any()
    mask = torch.tensor([True, False, True, False]).unsqueeze(-1)
    td = env.reset(td["next"].clone().set("_reset", mask))
    assert torch.equal(td["is_init"], mask)


def _collected(policy, frames: int = SITES * 16):
    env = FleetChargingEnv(num_sites=SITES, seed=0)
    collector = Collector(env, as_td_module(policy), frames_per_batch=frames,
                          total_frames=frames)
    try:
        return next(iter(collector)).clone().reshape(-1)
    finally:
        collector.shutdown()


@pytest.mark.parametrize("make", [_dqn, _dqn_greedy], ids=["anchored", "greedy"])
@pytest.mark.parametrize("double", [False, True], ids=["dqn", "double_dqn"])
def test_dqn_loss_takes_a_wrapped_dqn_policy(make, double):
    """``as_td_module`` of a DQN policy is a Q-value actor with one site's action spec:
    TorchRL's DQNLoss builds on it without being told the action space, computes a finite
    loss on a collected batch, and its gradient reaches the policy's own Q-network."""
    from torchrl.objectives import DQNLoss

    policy = make()
    env = FleetChargingEnv(num_sites=SITES, seed=0)
    module = as_td_module(policy)
    assert module.spec["action"] == env.action_spec_unbatched
    batch = _collected(policy)
    q = policy.qnet(batch["observation"])
    assert torch.equal(batch["action_value"], q.detach())
    assert torch.equal(batch["chosen_action_value"].squeeze(-1), q.max(-1).values.detach())
    assert torch.equal(batch["action"], policy(batch["observation"]))
    loss = DQNLoss(module, delay_value=True, double_dqn=double)
    loss.make_value_estimator(gamma=0.9)
    out = loss(batch)["loss"]
    assert out.ndim == 0 and torch.isfinite(out) and out > 0
    out.backward()
    grads = [p.grad for p in policy.qnet.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


@pytest.mark.parametrize("make", [m for k, m in POLICIES.items() if not k.startswith("dqn")],
                         ids=[k for k in POLICIES if not k.startswith("dqn")])
def test_dqn_loss_refuses_a_policy_without_q_values(make):
    from torchrl.objectives import DQNLoss

    policy = make()
    with pytest.raises(ValueError, match=rf"^a {policy.name} policy has no Q-values: DQNLoss"):
        DQNLoss(as_td_module(policy))


def _planner():
    from fleet_torchrl.agents.planner import PlannerPolicy

    return PlannerPolicy(HeuristicPolicy(), rollouts=4, horizon=40)


def _guarded():
    from fleet_torchrl.agents.base import GuardedPolicy

    return GuardedPolicy(RulePolicy())


@pytest.mark.parametrize("make", [_planner, _guarded], ids=["planner", "guarded"])
def test_collector_runs_a_policy_that_decides_from_the_sites_state(make):
    """The planner and a guarded policy decide from the site's state: bound to the env they
    act in, they drive a Collector of that env with no warning, each action the policy's
    decision on the state the observation encodes; unbound, one line says to bind them."""
    from fleet_torchrl.sim.rollout import DecisionContext

    policy = make()
    with pytest.raises(ValueError, match=r"decides from the site's state.*env=env\)$"):
        as_td_module(policy)
    env = FleetChargingEnv(num_sites=SITES, seed=0)
    frames = SITES * 4
    decided = []
    real = policy.decide

    def decide(site, state, ctx):  # what the policy decided, and on which state
        act = real(site, state, ctx)
        decided.append((state.soc.clone(), act.clone()))
        return act

    policy.decide = decide
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        collector = Collector(env, as_td_module(policy, env=env), frames_per_batch=frames,
                              total_frames=frames)
        try:
            batch = next(iter(collector)).clone()
        finally:
            collector.shutdown()
    assert batch.numel() == frames and batch["next", "ticks"].gt(batch["ticks"]).all()
    assert len(decided) >= 4  # (the collector may call its policy once to learn its outputs)
    for t, (_, act) in enumerate(decided[-4:]):  # the collector's actions are the decisions
        assert torch.equal(batch["action"][:, t], act)
        assert set(act.tolist()) <= {0, 1}
    # and a decision equals the policy's own on that state (the planner is deterministic)
    site, state = env.site, env.state
    need = torch.ones(SITES, dtype=torch.bool)
    ctx = DecisionContext(need, torch.arange(SITES), env.fused)
    assert torch.equal(real(site, state, ctx), real(site, state, ctx))
    with pytest.raises(ValueError, match="decides for its env's sites"):
        as_td_module(policy, env=env)(env.reset()[:2])
