"""The rollout planner (agent=planner): its own futures, repeatable, an improvement over its
base, the same decisions on both backends."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
from fleet_torchrl.agents.planner import PlannerAgentConfig, PlannerPolicy
from fleet_torchrl.config import compose_config
from fleet_torchrl.evaluate import policy_of
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import Site, SiteConfig, rng
from fleet_torchrl.sim.rollout import DecisionContext
from fleet_torchrl.utils.checks import ConfigError


def planner(base=None, **kw) -> PlannerPolicy:
    kw = {"rollouts": 6, "horizon": 80, **kw}
    return PlannerPolicy(base or HeuristicPolicy(), **kw)


def test_a_decision_does_not_read_the_sites_own_future():
    """Two copies of one site whose closures agree up to tick t and differ after it: the
    planner decides the same at every decision up to t (it would not, if its futures were
    the site's own), and the runs part after t."""
    site, t_split, ticks = Site(SiteConfig(n_vehicles=4)), 300, 700
    idx = torch.tensor([3, 3])
    s, needs = site.init_state(0, idx)
    pol = planner()
    ctx = lambda need: DecisionContext(need, idx, True)  # noqa: E731 (same label: same site)
    site.decide(s, needs, pol.decide(site, s, ctx(needs)))
    h = site.site_hash(0, idx)
    h_after = site.site_hash(1, idx)  # another stream for copy 1 after the split
    decisions = [[], []]
    for t in range(ticks):
        closed = site.closures_hashed(h, torch.full((2,), t), s.params)
        if t >= t_split:
            closed[1] = site.closures_hashed(h_after[1:], torch.tensor([t]), s.params.select(
                torch.tensor([1])))[0]
        out = site.tick(s, closed)
        if bool(out.arrived.any()):
            act = pol.decide(site, s, ctx(out.arrived))
            site.decide(s, out.arrived, act)
            for b in range(2):
                if out.arrived[b]:
                    decisions[b].append((t, int(act[b])))
    before = [[d for d in run if d[0] < t_split] for run in decisions]
    assert len(before[0]) > 10 and before[0] == before[1]
    assert decisions[0] != decisions[1]  # the futures after t_split did differ


def test_seeded_runs_repeat_exactly():
    cfg = SiteConfig(n_vehicles=4)
    a = simulate(planner(seed=3), cfg, 24, 600, 1)
    b = simulate(planner(seed=3), cfg, 24, 600, 1)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    p = planner(seed=3)
    simulate(p, cfg, 24, 600, 1)
    q = planner(seed=4)
    simulate(q, cfg, 24, 600, 1)
    assert p.stats["decisions"] > 0 and p.stats != q.stats  # its own streams: the seed counts


def test_a_tiny_planner_improves_on_a_poor_base():
    """The rule never charges early; one step of lookahead over it gains trips (and loses
    no site), as one step of policy improvement should."""
    cfg = SiteConfig(n_vehicles=4)
    base = simulate(RulePolicy(), cfg, 48, 2000, 0)
    pol = planner(RulePolicy(), rollouts=8, horizon=150)
    better = simulate(pol, cfg, 48, 2000, 0)
    gain = better["trips"].float().mean() / base["trips"].float().mean() - 1
    assert gain > 0.02, float(gain)
    assert int(better["failed"].sum()) <= int(base["failed"].sum())
    assert 0 < pol.stats["changed"] < pol.stats["decisions"]


@pytest.mark.parametrize("base", ["heuristic", "network"])
def test_fused_and_eager_backends_decide_the_same(base):
    torch.manual_seed(0)
    pol_base = HeuristicPolicy() if base == "heuristic" else DQNPolicy(
        NetworkConfig(width=8, depth=1), 3, "partial")
    cfg = SiteConfig(n_vehicles=3, p_c=0.9)
    runs, stats = [], []
    for fused in (True, False):
        p = planner(pol_base, rollouts=4, horizon=40)
        runs.append(simulate(p, cfg, 12, 300, 2, fused=fused))
        stats.append(dict(p.stats))
    for k in runs[0]:  # every decision of a counted tick alike, or the trips would part
        assert torch.equal(runs[0][k], runs[1][k]), k
    # (the eager loop also decides for failed sites and at the last tick: more calls)
    assert 0 < stats[0]["changed"] and stats[0]["decisions"] <= stats[1]["decisions"]


def test_its_futures_use_their_own_stream():
    """The rollout hash is the planner's stream, not the closure stream of any site."""
    h = rng.hash_ints(0, torch.tensor([5]), torch.tensor([10]), torch.tensor([0]),
                      rng.STREAM_PLANNER)
    assert rng.STREAM_PLANNER not in (rng.STREAM_CLOSURE, rng.STREAM_INIT_POS,
                                      rng.STREAM_INIT_SOC, rng.STREAM_TRAINING,
                                      rng.STREAM_SEARCH, rng.STREAM_SITE)
    assert int(h) != int(Site(SiteConfig()).site_hash(0, torch.tensor([5])))


def test_config_builds_the_planner_and_rejects_bad_values(tmp_path):
    pol = policy_of(compose_config(["agent=planner", "agent.rollouts=4"]))
    assert isinstance(pol, PlannerPolicy) and isinstance(pol.base, HeuristicPolicy)
    assert pol.rollouts == 4
    with pytest.raises(ConfigError, match="agent.base"):
        PlannerAgentConfig(base=str(tmp_path / "missing")).validate()
    with pytest.raises(ConfigError, match="agent.rollouts"):
        PlannerAgentConfig(rollouts=1).validate()
    with pytest.raises(TypeError, match="site's state"):
        pol(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="cannot be a planner"):
        PlannerPolicy(pol)


# --------------------------------------------------------- several bases (parallel rollout)
def test_a_repeated_base_decides_as_the_one_base():
    """With its own base repeated in ``bases`` the futures, the reference and the other
    action's best base are the first one's: the very decisions of the one-base planner."""
    cfg = SiteConfig(n_vehicles=4)
    one, two = planner(), planner(bases=[HeuristicPolicy()])
    a, b = simulate(one, cfg, 16, 800, 0), simulate(two, cfg, 16, 800, 0)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert one.stats["decisions"] == two.stats["decisions"] and two.stats["other_base"] == 0


def test_several_bases_start_from_the_better_one_where_it_is_better():
    """Over the rule and the heuristic on a crowded site, the reference is often the
    heuristic (the rule waits for the battery to run low), and the planner does at least as
    well as the planner over the rule alone, with no more failures."""
    cfg = SiteConfig(n_vehicles=5)
    over_rule = planner(RulePolicy(), rollouts=8, horizon=150)
    both = planner(RulePolicy(), rollouts=8, horizon=150, bases=[HeuristicPolicy()])
    r1, r2 = simulate(over_rule, cfg, 24, 1500, 0), simulate(both, cfg, 24, 1500, 0)
    assert 0 < both.stats["other_base"] < both.stats["decisions"]
    assert r2["trips"].float().mean() >= r1["trips"].float().mean()
    assert int(r2["failed"].sum()) <= int(r1["failed"].sum())
    assert len(both.bases) == 2 and isinstance(both.bases[1], HeuristicPolicy)
    assert [m for m in dict(over_rule.named_modules())] == ["", "base"]  # nothing registered


def test_config_names_each_extra_base_and_keeps_old_fingerprints(tmp_path):
    from fleet_torchrl.agents.config import ImitationAgentConfig
    from fleet_torchrl.training.checkpoint import without_neutral

    pol = policy_of(compose_config(["agent=planner", "agent.rollouts=4",
                                      "agent.bases=[rule,heuristic]"]))
    assert [type(b) for b in pol.bases] == [HeuristicPolicy, RulePolicy, HeuristicPolicy]
    with pytest.raises(ConfigError, match=r"agent.bases\[1\]"):
        PlannerAgentConfig(bases=["rule", str(tmp_path / "missing")]).validate()
    with pytest.raises(ConfigError, match="agent.bases has 9 entries"):
        PlannerAgentConfig(bases=["rule"] * 9).validate()
    assert PlannerAgentConfig(bases=["rule"]).sites_per_simulation() == 1 + 2 * 32 * 2
    # a setting added with its neutral value leaves saved runs' fingerprints as they were,
    # in a teacher's settings nested in a learner's too
    plain = without_neutral(ImitationAgentConfig())
    assert "bases" not in plain["expert"] and "iterate_from" not in plain
    multi = ImitationAgentConfig(expert=PlannerAgentConfig(bases=["rule"]))
    assert without_neutral(multi)["expert"]["bases"] == ["rule"]
    assert multi.run_suffix(None).startswith("_over_bases-")
    assert ImitationAgentConfig().run_suffix(None) == ""


def test_the_reference_stays_the_first_base_unless_another_is_significantly_better():
    """Picking the best mean among bases would follow noise: the first base stays the
    reference unless another base's own action fails less or scores better by the
    confidence bound of the paired difference (then the best such base)."""
    p = planner(bases=[HeuristicPolicy(), HeuristicPolicy()], rollouts=4, confidence=1.5)
    own = torch.tensor([[0, 1, 0], [1, 1, 0], [0, 0, 1]])  # [bases, sites]
    score = torch.zeros(3, 2, 4, 3, dtype=torch.float64)  # [bases, action, future, site]
    base0 = torch.tensor([10.0, 12.0, 11.0, 13.0], dtype=torch.float64)
    score[0, 0, :, 0] = base0
    score[1, 1, :, 0] = base0 + 2.0  # site 0: base 1 better in every future
    score[2, 0, :, 0] = base0 + 1.0  # ... base 2 too, by less
    score[0, 1, :, 1] = base0
    score[1, 1, :, 1] = base0 + torch.tensor([3.0, -3.0, 2.0, -1.5], dtype=torch.float64)
    score[2, 0, :, 1] = base0 + torch.tensor([0.6, -0.4, 0.5, -0.3], dtype=torch.float64)
    # site 1: bases 1 and 2 better on average, within the noise
    fails = torch.zeros(3, 2, 3, dtype=torch.long)
    score[:, :, :, 2] = 5.0
    fails[0, 0, 2] = 1  # site 2: the first base's action fails once, the others' never
    assert p._reference(own, score, fails).tolist() == [1, 0, 1]


def test_the_other_action_is_scored_under_the_reference_unless_another_base_is_better():
    """other_under=gated: action a stays scored under the reference base unless another
    base scores it in fewer failed futures or better by the confidence bound; the best mean
    alone (other_under=best) takes noise for a better base."""
    p = planner(bases=[HeuristicPolicy(), HeuristicPolicy()], rollouts=4, confidence=1.5)
    a = torch.tensor([1, 1, 0])  # the other action, per site
    start = torch.tensor([0, 2, 1])  # the reference base, per site
    score = torch.zeros(3, 2, 4, 3, dtype=torch.float64)
    base = torch.tensor([10.0, 12.0, 11.0, 13.0], dtype=torch.float64)
    score[0, 1, :, 0] = base
    score[1, 1, :, 0] = base + 2.0  # site 0: base 1 scores it better in every future
    score[2, 1, :, 1] = base
    score[0, 1, :, 1] = base + torch.tensor([3.0, -3.0, 2.0, -1.5], dtype=torch.float64)
    # site 1: base 0 better on average, within the noise: the reference (2) stays
    fails = torch.zeros(3, 2, 3, dtype=torch.long)
    fails[1, 0, 2] = 1  # site 2: under the reference (1) it fails once, under 0 and 2 never
    score[0, 0, :, 2] = 1.0
    assert p._gated(a, start, score, fails).tolist() == [1, 2, 0]
    # a repeated base changes nothing, whichever way the other action is scored
    cfg = SiteConfig(n_vehicles=4)
    ref = simulate(planner(), cfg, 8, 600, 0)
    for mode in ("best", "reference", "gated"):
        two = planner(bases=[HeuristicPolicy()])
        two.other_under = mode
        out = simulate(two, cfg, 8, 600, 0)
        for k in ref:
            assert torch.equal(ref[k], out[k]), (mode, k)


def test_last_gap_holds_each_decisions_stake():
    """After a decision, last_gap is 0 for the sites that did not decide, the absolute
    difference of the two actions' mean scores for the others, and infinite where one action
    fails in more futures: a vehicle at D with a battery that cannot finish another lap."""
    site = Site(SiteConfig(n_vehicles=3))
    idx = torch.arange(5)
    s, _ = site.init_state(0, idx)
    assert bool((s.pos[1:] != 0).all())
    s.pos[0] = 0  # vehicle 0 at D in every site, the last two nearly empty
    s.soc[0, 3:] = site.soc_low + 1.0
    needs = torch.ones(5, dtype=torch.bool)
    need = needs.clone()
    need[1] = False
    pol = planner(RulePolicy())
    pol.decide(site, s, DecisionContext(need, idx, True))
    gap = pol.last_gap
    assert gap.shape == (5,) and gap.dtype == torch.float64
    assert float(gap[1]) == 0.0
    assert bool(torch.isinf(gap[3:]).all())  # passing fails: charging is worth everything
    assert bool(torch.isfinite(gap[[0, 2]]).all()) and bool((gap[[0, 2]] >= 0).all())


def test_scoring_under_the_reference_runs_fewer_futures_for_the_same_decisions():
    """other_under=reference runs each base's own action and the other action under the
    reference's base only (m + 1 sets of futures instead of 2 m): the same paired gains,
    failed futures, references and stakes as scoring both actions under every base."""
    site = Site(SiteConfig(n_vehicles=5, t_c=50))
    idx = torch.arange(64)
    s, _ = site.init_state(3, idx)
    s.pos[0] = 0  # vehicle 0 at D in every site, at charges from nearly empty to full
    s.soc[0] = torch.linspace(site.soc_low + 2.0, 100.0, 64).to(s.soc.dtype)
    ctx = DecisionContext(torch.ones(64, dtype=torch.bool), idx, True)
    pol = planner(RulePolicy(), bases=[HeuristicPolicy(), RulePolicy()], rollouts=8)
    pol.other_under = "reference"
    d = torch.arange(64)
    own = torch.stack([b.decide(site, s, ctx).long() for b in pol.bases])
    fast = pol._under_reference(site, s, ctx, d, own)
    slow = pol._under_any(site, s, ctx, d, own)
    ref = fast[3]
    assert bool((ref == 0).any()) and bool((ref != 0).any())  # both kinds of reference
    assert bool((own[1] != own[0]).any())  # and bases that disagree
    for a, b in zip(fast, slow, strict=True):
        assert torch.equal(a, b)
    # and whole runs: the same records as the both-actions path
    cfg = SiteConfig(n_vehicles=4)
    runs = {}
    for fast_path in (True, False):
        p = planner(RulePolicy(), bases=[HeuristicPolicy()], rollouts=4)
        p.other_under = "reference"
        if not fast_path:
            p._under_reference = p._under_any
        runs[fast_path] = simulate(p, cfg, 8, 600, 0)
    for k in runs[True]:
        assert torch.equal(runs[True][k], runs[False][k]), k
