"""Distillation of the planner (agent=imitation): the labels are the planner's decisions on
the environment's states, the DAgger mixing follows its schedule, a short run learns a
policy that agrees with the planner and beats the rule, the policy file round-trips, and a
resumed run ends where an uninterrupted one does."""

from __future__ import annotations

import glob

import pytest
import torch

from fleet_torchrl.agents import load_policy_file, save_policy
from fleet_torchrl.agents.base import guard_actions
from fleet_torchrl.agents.baselines import HeuristicPolicy, RulePolicy
from fleet_torchrl.agents.imitation import (
    ImitationAgentConfig,
    ImitationLearner,
    ImitationPolicy,
)
from fleet_torchrl.agents.planner import PlannerAgentConfig, PlannerPolicy
from fleet_torchrl.agents.policy_files import policy_bytes
from fleet_torchrl.config import compose_config
from fleet_torchrl.env import FleetChargingEnv, MDPConfig
from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import Site, SiteConfig
from fleet_torchrl.sim.rollout import DecisionContext
from fleet_torchrl.utils.checks import ConfigError

FIVE = SiteConfig(n_vehicles=5)
SMALL_EXPERT = PlannerAgentConfig(rollouts=4, horizon=60)


def learner(env, **kw) -> ImitationLearner:
    agent = ImitationAgentConfig(**{"expert": SMALL_EXPERT, "hidden": 16, **kw}).validate()
    expert = PlannerPolicy.from_config(agent.expert, HeuristicPolicy())
    return ImitationLearner(agent, expert, env, env.encoding.size(env.site), env.encoding.name,
                            seed=0)


def test_labels_are_the_planners_decisions_on_the_environments_states():
    """Each label is the planner's decision on that site's full state, with the site's
    index in the training stream as its label (new every episode); labelling leaves the
    sites alone, and the stored observation is the encoding of the labelled state."""
    b = 6
    env = FleetChargingEnv(FIVE, num_sites=b, seed=3, mdp=MDPConfig(tau_e=40))
    lrn = learner(env, num_sites=b, beta_start=1.0, beta_end=1.0)
    planner = PlannerPolicy.from_config(SMALL_EXPERT, HeuristicPolicy())
    td = env.reset()
    lrn.start_round(0)
    seen_index = set()
    for _ in range(8):
        before = env.state.clone()
        assert torch.equal(td["observation"], get_encoding("partial")(env.site, env.state))
        td = lrn.act(td)
        label = lrn._label.clone()
        for k in ("pos", "soc", "left", "tick"):  # the planner worked on copies
            assert torch.equal(getattr(env.state, k), getattr(before, k)), k
        index = (env.episodes - 1) * b + torch.arange(b)
        seen_index.update(index.tolist())
        for s in range(b):  # one site at a time: the same decision as in the batch
            one = torch.tensor([s])
            alone = planner.decide(env.site, env.state.select(one),
                                   DecisionContext(torch.ones(1, dtype=torch.bool),
                                                   index[one], True))
            assert int(alone[0]) == int(label[s]), s
        assert torch.equal(td["action"], label)  # beta = 1: the expert acts
        obs = td["observation"].clone()
        td, root = env.step_and_maybe_reset(td)
        learn = torch.ones(b, dtype=torch.bool)
        lrn.observe(td, learn)
        assert torch.equal(lrn._obs[-1], obs) and torch.equal(lrn._labels[-1], label)
        td = root
    assert len(seen_index) > b  # sites whose episode ended got a new label
    out = lrn.update()
    assert out["train/dataset_size"] == 8 * b and out["train/beta"] == 1.0
    assert 0.0 <= out["train/agreement"] <= 1.0 and out["loss/imitation"] > 0
    assert planner.stats["changed"] > 0  # the labels are not just the heuristic's


def test_beta_decays_linearly_and_sets_who_acts():
    agent = ImitationAgentConfig(beta_start=1.0, beta_end=0.1, beta_rounds=4)
    assert [round(agent.beta(r), 6) for r in range(7)] == [1.0, 0.775, 0.55, 0.325, 0.1, 0.1,
                                                           0.1]
    assert ImitationAgentConfig(beta_rounds=5).beta(2) == pytest.approx(0.6)
    b = 64
    env = FleetChargingEnv(FIVE, num_sites=b, seed=1)
    lrn = learner(env, num_sites=b, beta_start=0.8, beta_end=0.0, beta_rounds=2)
    td = env.reset()
    for r, beta in [(0, 0.8), (1, 0.4), (2, 0.0), (5, 0.0)]:
        lrn.start_round(r)
        assert lrn.exploration() == pytest.approx(beta)
        draws = torch.Generator().set_state(lrn.mix_gen.get_state())
        expert_acts = torch.rand(b, generator=draws) < beta
        with torch.no_grad():
            student = lrn.student(td["observation"])
        td = lrn.act(td)
        want = torch.where(expert_acts, lrn._label, student)
        assert torch.equal(td["action"], want), r
        assert lrn.update()["train/beta"] == pytest.approx(beta)


def test_policy_file_round_trip(tmp_path):
    torch.manual_seed(0)
    pol = ImitationPolicy(6, "partial_site", hidden=8, depth=3)
    save_policy(tmp_path / "policy.pt", pol, "imitation")
    back = load_policy_file(tmp_path)
    assert isinstance(back, ImitationPolicy) and back.encoding == "partial_site"
    assert back.policy_spec() == pol.policy_spec()
    obs = torch.rand(500, 6)
    assert torch.equal(back.logits(obs), pol.logits(obs))
    assert torch.equal(back(obs), (pol.logits(obs) > 0).long())
    # a zero logit passes
    zero = ImitationPolicy(3, "partial", hidden=4, depth=1)
    for p in zero.parameters():
        p.data.zero_()
    assert zero(torch.rand(5, 3)).eq(0).all()


@pytest.mark.parametrize("override, field", [
    ("agent.beta_end=1.5", "agent.beta_end"),
    ("agent.beta_start=-0.1", "agent.beta_start"),
    ("agent.beta_rounds=0", "agent.beta_rounds"),
    ("agent.batch_size=0", "agent.batch_size"),
    ("agent.capacity=0", "agent.capacity"),
    ("agent.lr=0", "agent.lr"),
    ("agent.expert.rollouts=1", "agent.expert.rollouts"),
    ("agent.expert.base=/nowhere", "agent.expert.base"),
    ("agent.label_weight=regret", "agent.label_weight"),
    ("agent.gap_cap=0", "agent.gap_cap"),
    ("agent.gap_floor=1.5", "agent.gap_floor"),  # above gap_cap = 1
    ("agent.expert.other_under=max", "agent.expert.other_under"),
])
def test_bad_values_are_one_line_config_errors(override, field):
    with pytest.raises(ConfigError) as e:
        compose_config(["agent=imitation", override])
    msg = str(e.value)
    assert msg.startswith(f"{field}=") and "allowed" in msg and "\n" not in msg, msg


def test_config_and_names():
    cfg = compose_config(["agent=imitation"])
    assert cfg.agent.expert == PlannerAgentConfig()  # the planner's defaults
    assert cfg.agent.training_rounds(cfg.train) == cfg.agent.rounds
    from fleet_torchrl.store import policy_name

    assert policy_name(cfg) == "imitation_partial"
    assert policy_name(compose_config(["agent=imitation", "state=partial_site",
                                       "site=five_vehicles", "mdp.reward=throughput"])) \
        == "imitation_partial_site_five_vehicles"
    assert policy_name(compose_config(["agent=imitation", "agent.expert.base=rule"])) \
        == "imitation_partial_over_rule"
    assert policy_name(compose_config(["agent=imitation", "state=all"])) == "imitation_all"
    with pytest.raises(ConfigError, match="agent.iterate_from=41 is invalid"):
        compose_config(["agent=imitation", "agent.iterate_from=41"])  # rounds = 40


def test_a_neutral_new_setting_keeps_the_saved_runs_fingerprint():
    """agent.iterate_from (added after runs were saved) at its neutral 0 is left out of the
    training fingerprint: those runs stay reusable and resumable; any other value is in it,
    and a resume across the change is refused with the field named."""
    from fleet_torchrl.training import training_fingerprint
    from fleet_torchrl.training.checkpoint import fingerprint_diff

    plain = training_fingerprint(compose_config(["agent=imitation"]))
    assert "iterate_from" not in plain["agent"] and plain["agent"]["rounds"] == 40
    other = training_fingerprint(compose_config(["agent=imitation", "agent.iterate_from=5"]))
    assert other["agent"]["iterate_from"] == 5
    assert fingerprint_diff(plain, other) == ["agent.iterate_from: None -> 5"]
    for k in ("label_weight", "gap_cap", "gap_floor"):
        assert k not in plain["agent"]
    assert "other_under" not in plain["agent"]["expert"]
    gap = training_fingerprint(compose_config(["agent=imitation", "agent.label_weight=gap"]))
    assert fingerprint_diff(plain, gap) == ["agent.label_weight: None -> 'gap'"]


def _weighted_round(label_weight, after_act, b=8, steps=6):
    """One DAgger round of ``steps`` steps on ``b`` five-vehicle sites with stakes clipped
    to [0.1, 0.5]; ``after_act(learner)`` runs after each step's labels."""
    env = FleetChargingEnv(FIVE, num_sites=b, seed=4, mdp=MDPConfig(tau_e=40))
    lrn = learner(env, num_sites=b, label_weight=label_weight, gap_cap=0.5, gap_floor=0.1,
                  batch_size=steps * b, updates_per_round=0)
    td = env.reset()
    lrn.start_round(0)
    for _ in range(steps):
        td = lrn.act(td)
        after_act(lrn)
        td, root = env.step_and_maybe_reset(td)
        lrn.observe(td, torch.ones(b, dtype=torch.bool))
        td = root
    return lrn, lrn.update()


def test_gap_weighted_labels_weigh_by_the_planners_stakes():
    """Under label_weight=gap each stored pair carries the planner's stake of that decision
    (last_gap, clipped to [gap_floor, gap_cap], over gap_cap), and the loss is the pairs'
    cross-entropy weighted by it: a pair of weight 0 does not move the student."""
    gaps = []

    def check(lrn):
        gap = lrn.expert.last_gap.clone()
        assert gap.shape == (8,) and bool((gap >= 0).all())
        gaps.append(gap)
        assert torch.equal(lrn._weight, (gap.clamp(0.1, 0.5) / 0.5).float())

    lrn, out = _weighted_round("gap", check)
    gap = torch.cat(gaps)
    assert bool((gap < 0.1).any()) and bool((gap > 0.5).any())  # both clips are exercised
    assert 0.0 <= out["train/weighted_agreement"] <= 1.0
    data = lrn.data[:]
    assert torch.equal(data["weight"], (gap.clamp(0.1, 0.5) / 0.5).float())
    # the loss: the weighted mean of the pairs' cross-entropy
    per = torch.nn.functional.binary_cross_entropy_with_logits(
        lrn.student.logits(data["observation"]), data["label"].float(), reduction="none")
    w = data["weight"]
    assert float(lrn.loss(data)) == pytest.approx(float((w * per).sum() / w.sum()), rel=1e-6)
    one = data.clone()
    one["weight"][1:] = 0.0  # only the first pair counts, whatever the others say
    one["label"][1:] = 1 - one["label"][1:]
    assert float(lrn.loss(one)) == pytest.approx(float(per[0]), rel=1e-6)
    # uniform weights: the plain mean, as label_weight=uniform computes it
    lrn.agent.label_weight = "uniform"
    assert float(lrn.loss(data)) == pytest.approx(float(per.mean()), rel=1e-6)


def test_site_normalised_weights_keep_each_sites_share_of_the_loss():
    """label_weight=site_gap: a pair's clipped stake over the mean clipped stake of the
    round's pairs from the same site, so each site's pairs weigh as many as they are and
    the stakes only move the loss between one site's decisions."""
    w = torch.tensor([0.2, 0.6, 1.0, 1.0, 0.1, 0.4])
    site = torch.tensor([7, 7, 3, 3, 9, 7])
    out = ImitationLearner.site_normalised(w, site)
    assert torch.allclose(out, torch.tensor([0.5, 1.5, 1.0, 1.0, 1.0, 1.0]))
    raw, index = [], []

    def record(lrn):
        raw.append(lrn._weight.clone())
        index.append(lrn._index.clone())

    lrn, _ = _weighted_round("site_gap", record)
    raw, index = torch.cat(raw), torch.cat(index)
    assert index.unique().numel() > 8  # some slots started a new site this round
    w = lrn.data[:]["weight"]
    for i in index.unique():
        mine = index == i
        assert float(w[mine].sum()) == pytest.approx(int(mine.sum()), rel=1e-5)
        assert torch.allclose(w[mine], raw[mine] / raw[mine].mean())
    assert not torch.allclose(w, torch.ones_like(w))  # the stakes still differ within sites


def test_expert_iteration_teaches_with_the_planner_over_the_student():
    """From round iterate_from on, the labels are the planner's decisions over a frozen copy
    of the student as it stood when the round began (the configured planner's settings);
    before it, over the configured base. The copy does not follow the student's updates."""
    b = 8
    env = FleetChargingEnv(FIVE, num_sites=b, seed=2, mdp=MDPConfig(tau_e=40))
    lrn = learner(env, num_sites=b, iterate_from=2, updates_per_round=5, batch_size=8)
    first = lrn.expert
    td = env.reset()
    for r in range(4):
        lrn.start_round(r)
        if r < 2:
            assert lrn.expert is first and isinstance(first.base, HeuristicPolicy)
        else:
            teacher = lrn.expert
            assert isinstance(teacher, PlannerPolicy) and teacher is not first
            assert isinstance(teacher.base, ImitationPolicy) and teacher.base is not lrn.student
            assert (teacher.rollouts, teacher.horizon, teacher.seed) == \
                (first.rollouts, first.horizon, first.seed)
            for p, q in zip(teacher.base.parameters(), lrn.student.parameters(), strict=True):
                assert torch.equal(p, q) and not p.requires_grad
            # its labels are the planner over that student, on the environment's states
            index = (env.episodes - 1) * b + torch.arange(b)
            want = PlannerPolicy(teacher.base, first.rollouts, first.horizon, first.energy_value,
                                 first.confidence, first.seed).decide(
                env.site, env.state, DecisionContext(torch.ones(b, dtype=torch.bool), index,
                                                     True))
            td = lrn.act(td)
            assert torch.equal(lrn._label, want.long())
            td, root = env.step_and_maybe_reset(td)
            lrn.observe(td, torch.ones(b, dtype=torch.bool))
            td = root
        for _ in range(3):
            td = lrn.act(td)
            td, root = env.step_and_maybe_reset(td)
            lrn.observe(td, torch.ones(b, dtype=torch.bool))
            td = root
        lrn.update()  # the student moves; a frozen copy taken before it does not
        if r >= 2:
            assert any(not torch.equal(p, q) for p, q in zip(
                teacher.base.parameters(), lrn.student.parameters(), strict=True))


# ---------------------------------------------------------------------- training runs
TINY = ["agent=imitation", "site.n_vehicles=5", "agent.num_sites=16", "agent.steps_per_round=6",
        "agent.rounds=4", "agent.beta_rounds=2", "agent.hidden=16", "agent.updates_per_round=20",
        "agent.batch_size=32", "agent.expert.rollouts=4", "agent.expert.horizon=40",
        "train.eval_every=2", "train.eval_sims=16", "train.eval_ticks=500",
        "train.checkpoint_every=1", "train.progress=false", "train.tensorboard=false",
        "mdp.tau_e=400"]


def _train(overrides, tmp, stop_after=None, resume=False):
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*overrides, f"train.out_dir={tmp}/policy",
                          f"resume={str(resume).lower()}"])
    tr = Trainer(RunSpec.of(cfg), tmp, resume=cfg.resume)
    return tr, tr.run(stop_after_rounds=stop_after)


@pytest.mark.parametrize("extra", [["agent.capacity=500000"], ["agent.capacity=150"],
                                   ["agent.iterate_from=2"], ["agent.label_weight=site_gap"],
                                   ["state=all_site", "site=randomized"]])
def test_resume_ends_where_an_uninterrupted_run_does(tmp_path, extra):
    """Killed after round 2's checkpoint and resumed: the same data set, the same student,
    the same evaluations and the same policy bytes as a run that was never stopped (also
    when the data set has wrapped around: 96 labels a round, capacity 150; and under expert
    iteration, whose teacher after the resume is the planner over the resumed student; and
    a generalist reading every node and its site)."""
    tiny = [*TINY, *extra]
    capacity = 150 if "agent.capacity=150" in extra else 500_000
    full, s_full = _train(tiny, tmp_path / "a")
    _train(tiny, tmp_path / "b", stop_after=2)
    res, s_res = _train(tiny, tmp_path / "b", resume=True)
    assert s_res["resumed"] and s_res["rounds"] == s_full["rounds"] == 4
    assert len(res.learner.data) == len(full.learner.data) == min(4 * 6 * 16, capacity)
    a, b = full.learner.data[:], res.learner.data[:]
    assert torch.equal(a["observation"], b["observation"]) and torch.equal(a["label"],
                                                                         b["label"])
    assert ("weight" in a.keys()) == ("agent.label_weight=site_gap" in extra)
    if "weight" in a.keys():  # the stakes, normalised within each site of each round
        assert torch.equal(a["weight"], b["weight"])
    assert policy_bytes(res.learner.student, "imitation") == \
        policy_bytes(full.learner.student, "imitation")
    assert policy_bytes(res.best_policy, "imitation") == \
        policy_bytes(full.best_policy, "imitation")
    assert [h["trips"] for h in s_res["history"]] == [h["trips"] for h in s_full["history"]]
    assert torch.equal(res.learner.mix_gen.get_state(), full.learner.mix_gen.get_state())
    assert isinstance(load_policy_file(tmp_path / "b" / "policy"), ImitationPolicy)


@pytest.mark.slow
def test_a_short_dagger_run_learns_the_planners_decisions(tmp_path):
    """At N_V = 5 (the planner +8 % over the rule, the heuristic +3 %): a short run agrees
    with the planner on most held-out states its own policy visits and beats the rule
    clearly, without failures; TensorBoard gets the learner's tags."""
    over = ["agent=imitation", "site.n_vehicles=5", "agent.num_sites=128",
            "agent.steps_per_round=20", "agent.rounds=8", "agent.beta_rounds=3",
            "train.eval_every=4", "train.eval_sims=64", "train.eval_ticks=2000",
            "train.progress=false"]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # (as make train does with train.threads=1: the planner's
    try:  # kernel on one core is fastest on a busy 2-core machine)
        _train(over, tmp_path)
    finally:
        torch.set_num_threads(threads)
    pol = load_policy_file(tmp_path / "policy")
    assert isinstance(pol, ImitationPolicy)
    # held-out states: other training sites, visited by the student, labelled by the planner
    env = FleetChargingEnv(FIVE, num_sites=64, seed=99)
    expert = PlannerPolicy.from_config(PlannerAgentConfig(), HeuristicPolicy())
    td, agree, n = env.reset(), 0, 0
    for t in range(60):
        index = (env.episodes - 1) * 64 + torch.arange(64)
        label = expert.decide(env.site, env.state,
                              DecisionContext(torch.ones(64, dtype=torch.bool), index, True))
        act = pol(td["observation"])
        if t >= 20:  # after the start of the episodes
            agree += int((act == label).sum())
            n += 64
        td, td = env.step_and_maybe_reset(td.set("action", act))
    assert agree / n > 0.85, agree / n
    test = {name: simulate(p, FIVE, 64, 3000, 0) for name, p in
            [("rule", RulePolicy()), ("imitation", pol)]}
    gain = float(test["imitation"]["trips"].double().mean()
                 / test["rule"]["trips"].double().mean() - 1)
    assert gain > 0.04, gain
    assert int(test["imitation"]["failed"].sum()) == 0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(glob.glob(str(tmp_path / "tb"))[0])
    ea.Reload()
    tags = set(ea.Tags()["scalars"])
    for tag in ("loss/imitation", "train/agreement", "train/beta", "train/dataset_size",
                "eval/gain_over_rule_pct"):
        assert tag in tags, tag


def test_a_network_decides_only_the_deciding_sites():
    """Policy.decide forwards the deciding sites' rows alone (a planner's rollouts over a
    network base: half the batch has finished its horizon): the same actions there as one
    forward over the whole batch, *pass* elsewhere (both under the reserve floor's guard),
    and a forward of that many rows."""
    site = Site(SiteConfig(n_vehicles=4))
    idx = torch.arange(40)
    s, _ = site.init_state(2, idx)
    s.pos[0] = 0
    s.soc[0] = torch.linspace(site.soc_low + 1.0, 100.0, 40).to(s.soc.dtype)
    torch.manual_seed(0)
    pol = ImitationPolicy(get_encoding("partial_site").size(site), "partial_site", hidden=16)
    with torch.no_grad():  # a logit spread over both signs: both actions among the sites
        pol.net[-1].bias.sub_(pol.logits(get_encoding("partial_site")(site, s)).median())
    full = pol(get_encoding("partial_site")(site, s))
    assert bool((full == 1).any()) and bool((full == 0).any())
    assert bool((guard_actions(site, s, full) == full).any())  # the network's own decisions
    need = torch.arange(40) % 3 == 0
    rows: list[int] = []
    pol.net.register_forward_hook(lambda m, i, o: rows.append(i[0].shape[0]))
    act = pol.decide(site, s, DecisionContext(need, idx, True))
    assert rows == [int(need.sum())]
    assert torch.equal(act, guard_actions(site, s, torch.where(need, full, 0)))
