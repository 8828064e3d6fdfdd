"""Direct policy search: the batched population evaluation, the search itself, its seeds."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents import load_policy_file
from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.search import (
    SearchAgentConfig,
    SearchLearner,
    SearchPolicy,
    cell_centres,
    evaluate_population,
    generation_seed,
    rank_key,
)
from fleet_torchrl.config import compose_config
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import SiteConfig, rng


def _tables(k: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    rule = RulePolicy()(cell_centres())
    flips = torch.rand(k, 200, generator=g) < 0.3
    return torch.where(flips, 1 - rule, rule).long()


@pytest.mark.parametrize("fused", [True, False])
def test_population_rows_are_separate_evaluations_tables(fused):
    site = SiteConfig()
    cand = _tables(5)
    rec = evaluate_population("table", cand, site, sites=12, ticks=1500, seed=4, fused=fused)
    assert rec["failed"].any() and not rec["failed"].all()  # both kinds of candidate present
    for k in range(5):
        pol = SearchPolicy("table")
        pol.charge.copy_(cand[k])
        alone = simulate(pol, site, n_sims=12, ticks=1500, seed=4, fused=fused)
        for key in ("trips", "queue", "failed", "ticks_survived"):
            assert torch.equal(rec[key][k], alone[key]), (k, key)


def test_population_rows_are_separate_evaluations_networks():
    site = SiteConfig(n_vehicles=4, p_c=0.5)
    learner = SearchLearner(SearchAgentConfig(policy_class="mlp", hidden=8, population=4,
                                              elite=2), site, seed=0)
    torch.manual_seed(3)
    cand = learner.sample()
    rec = evaluate_population("mlp", cand, site, sites=10, ticks=1000, seed=9,
                              sizes=learner.sizes)
    for k in range(4):
        pol = SearchPolicy("mlp", hidden=8)
        pol.theta.copy_(cand[k])
        alone = simulate(pol, site, n_sims=10, ticks=1000, seed=9)
        assert torch.equal(rec["trips"][k], alone["trips"]), k
        assert torch.equal(rec["failed"][k], alone["failed"]), k


def test_start_tables_are_the_named_policies():
    obs = cell_centres()
    learner = SearchLearner(SearchAgentConfig(init="heuristic"), SiteConfig(), 0,
                            HeuristicPolicy())
    assert torch.equal(learner.policy()(obs), HeuristicPolicy()(obs))
    p = learner.agent.p_min
    assert torch.allclose(learner.mean.min(), torch.tensor(p))
    assert torch.allclose(learner.mean.max(), torch.tensor(1 - p))
    # the rule's table: charge in every cell with soc_D below 40, whatever else
    rule = SearchLearner(SearchAgentConfig(), SiteConfig(), 0, RulePolicy()).policy()
    table = rule.charge.view(10, 10, 2)
    assert table[:4].all() and not table[4:].any()


def test_rank_puts_any_failure_below_every_safe_candidate():
    failed = torch.tensor([[False, True], [False, False], [False, False]])
    trips = torch.tensor([[500, 500], [300, 300], [310, 290]])
    order = rank_key(failed, trips).argsort(descending=True).tolist()
    assert order[-1] == 0 and order[0] in (1, 2)


def test_generation_seeds_are_pure_and_apart_from_evaluation():
    a = [generation_seed(0, g) for g in range(50)]
    assert a == [generation_seed(0, g) for g in range(50)]
    assert len(set(a)) == 50 and not set(a) & {0, 1_000_003}
    assert generation_seed(1, 0) != a[0]
    assert a[0] == int(rng.hash_ints(rng.training_seed(0), 0, rng.STREAM_SEARCH))


def test_tiny_search_improves_on_its_start():
    """From the uniform distribution (mode: always pass, which fails every site) a few
    generations find a table that is safe on the search's sites."""
    torch.manual_seed(0)
    agent = SearchAgentConfig(init="uniform", population=32, elite=4, sites=8, ticks=800,
                              generations=6)
    site = SiteConfig()
    learner = SearchLearner(agent, site, seed=0)
    start = learner.policy().charge.clone()
    seed = generation_seed(0, 99)
    before = evaluate_population("table", start[None], site, 8, 800, seed)
    for _ in range(agent.generations):
        stats = learner.update()
    after = evaluate_population("table", learner.policy().charge[None], site, 8, 800, seed)
    assert before["failed"].all()
    assert after["failed"].sum() < before["failed"].sum()
    assert float(rank_key(after["failed"], after["trips"])[0]) > float(
        rank_key(before["failed"], before["trips"])[0])
    assert 0 < stats["train/safe_share"] <= 1 and int(learner.generation) == 6


@pytest.mark.slow
def test_search_trains_saves_and_resumes_through_the_loop(tmp_path):
    from fleet_torchrl.training import RunSpec, Trainer

    over = ["agent=search", "agent.population=16", "agent.elite=4", "agent.sites=8",
            "agent.ticks=600", "agent.generations=4", "train.eval_every=2",
            "train.eval_sims=16", "train.eval_ticks=600", "train.checkpoint_every=1",
            "train.progress=false", "train.tensorboard=false",
            f"train.out_dir={tmp_path}/policy"]
    full = Trainer(RunSpec.of(compose_config(over)), tmp_path / "full").run()
    assert full["rounds"] == 4 and full["name"] == "search" and full["frames"] > 0
    pol = load_policy_file(tmp_path / "policy")
    assert isinstance(pol, SearchPolicy) and pol.charge.shape == (200,)
    # killed after 2 generations, resumed: the same distribution and the same best policy
    over2 = [o.replace("/policy", "/policy2") for o in over]
    Trainer(RunSpec.of(compose_config(over2)), tmp_path / "part").run(stop_after_rounds=2)
    tr = Trainer(RunSpec.of(compose_config(over2)), tmp_path / "part", resume=True)
    resumed = tr.run()
    assert resumed["rounds"] == 4
    assert [h["trips"] for h in resumed["history"]] == [h["trips"] for h in full["history"]]
    assert torch.equal(load_policy_file(tmp_path / "policy2").charge, pol.charge)


def test_search_seeded_with_a_saved_policy_keeps_at_least_its_start(tmp_path):
    """``agent.init=<saved policy>``: the table starts at that policy's actions, the start is
    evaluated before the first generation, and the kept snapshot is never worse than it on
    the selection set."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.tabular import TabularQPolicy
    from fleet_torchrl.training import RunSpec, Trainer

    tab = TabularQPolicy()
    tab.q[:, 1] = 1.0  # always charge
    tab.q[cell_centres()[:, 0] > 0.6, 1] = -1.0  # ... unless soc_D > 60
    save_policy(tmp_path / "start" / "policy.pt", tab, "tabular")
    over = ["agent=search", f"agent.init={tmp_path / 'start'}", "agent.population=8",
            "agent.elite=2", "agent.sites=4", "agent.ticks=400", "agent.generations=2",
            "train.eval_every=1", "train.eval_sims=8", "train.eval_ticks=400",
            "train.progress=false", "train.tensorboard=false", f"train.out_dir={tmp_path}/out"]
    cfg = compose_config(over)
    tr = Trainer(RunSpec.of(cfg), tmp_path / "run")
    assert torch.equal(tr.learner.policy().charge, tab(cell_centres()))
    summary = tr.run()
    first = summary["history"][0]
    assert first["round"] == 0 and len(summary["history"]) == 3
    assert (summary["best"]["failure_rate"], -summary["best"]["trips"]) <= (
        first["failure_rate"], -first["trips"])
    with pytest.raises(ValueError, match="agent.init"):
        compose_config(["agent=search", f"agent.init={tmp_path / 'nowhere'}"])
