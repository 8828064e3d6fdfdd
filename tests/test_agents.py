"""Learned agents: tabular update rule, DQN learning, saved policies, training, resume."""

from __future__ import annotations

import glob
import math

import pytest
import torch
from conftest import make_cfg

from fleet_torchrl.agents import load_policy_file, save_policy
from fleet_torchrl.agents.tabular import N_STATES, TabularLearner, state_index


# ---------------------------------------------------------------------- tabular
def test_state_index_bins():
    obs = torch.tensor([[0.0, 0.0, 0.0], [0.35, 0.99, 0.4], [1.0, 1.0, 0.0], [0.099, 0.1, 0.0]])
    assert state_index(obs).tolist() == [0, (3 * 10 + 9) * 2 + 1, (9 * 10 + 9) * 2, 1 * 2]
    # exact multiples of 10 land in their own bin despite float32 scaling (40 -> bin 4)
    from fleet_torchrl.encodings import get_encoding
    from fleet_torchrl.sim import Site, SiteState

    site = Site(make_cfg([]).site)
    socs = torch.arange(0, 101, dtype=torch.float32)
    s = SiteState(pos=torch.zeros(1, 101, dtype=torch.int64), soc=socs[None, :],
                  left=torch.zeros(1, 101, dtype=torch.int64),
                  charge=torch.zeros(101, dtype=torch.bool), tick=torch.zeros(101))
    bins = state_index(get_encoding("partial")(site, s)) // 20
    assert torch.equal(bins, (socs // 10).long().clamp(max=9))
    grid = torch.rand(1000, 3)
    idx = state_index(grid)
    assert idx.min() >= 0 and idx.max() < N_STATES == 200


def test_tabular_update_uses_k_over_t_plus_k():
    lrn = TabularLearner(k=100.0, gamma=0.9)
    obs = torch.tensor([[0.35, 0.8, 0.0]])
    nxt = torch.tensor([[0.75, 0.6, 0.5]])
    s, s2 = state_index(obs).item(), state_index(nxt).item()
    lrn.policy.q[s2] = torch.tensor([-2.0, -1.0])
    one = torch.tensor([True])
    lrn.update(obs, torch.tensor([1]), torch.tensor([-0.5]), nxt, torch.tensor([False]), one)
    assert lrn.policy.q[s, 1].item() == pytest.approx(-0.5 + 0.9 * -1.0)  # alpha = 1 first
    assert lrn.policy.visits[s, 1].item() == 1
    lrn.update(obs, torch.tensor([1]), torch.tensor([-3.0]), nxt, torch.tensor([True]), one)
    # second visit: alpha = 100/101, no bootstrap on termination
    assert lrn.policy.q[s, 1].item() == pytest.approx(-1.4 + 100 / 101 * (-3.0 + 1.4))
    assert lrn.policy.q[s, 0].item() == 0.0  # untouched
    lrn.update(obs, torch.tensor([0]), torch.tensor([-9.0]), nxt, torch.tensor([False]),
               torch.tensor([False]))  # masked out
    assert lrn.policy.q[s, 0].item() == 0.0 and lrn.policy.visits[s, 0].item() == 0


def test_tabular_batched_visits_average_into_one_update():
    lrn = TabularLearner(k=100.0, gamma=0.0)
    obs = torch.tensor([[0.55, 0.8, 0.0]] * 3)
    lrn.update(obs, torch.tensor([0, 0, 0]), torch.tensor([-1.0, -2.0, -3.0]), obs,
               torch.zeros(3, dtype=torch.bool), torch.ones(3, dtype=torch.bool))
    s = state_index(obs[:1]).item()
    assert lrn.policy.q[s, 0].item() == pytest.approx(-2.0)
    assert lrn.policy.visits[s, 0].item() == 3


# ---------------------------------------------------------------------- DQN
def test_dqn_loss_falls_on_a_fixed_buffer():
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv

    torch.manual_seed(0)
    cfg = make_cfg(["agent=dqn", "network.target_update=100000"])
    env = FleetChargingEnv(num_sites=8, seed=0)
    lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, 0.9, "cpu")
    lrn.observe(env.rollout(60, lrn.explore, break_when_any_done=False))
    first = lrn.update(20)
    for _ in range(10):
        last = lrn.update(40)
    assert math.isfinite(first) and last < 0.5 * first
    assert lrn.epsilon < 1.0  # epsilon annealed by the observed frames


def test_dqn_grad_clip_bounds_the_step():
    """``network.grad_clip`` caps the gradient norm the optimiser sees (SGD: step = lr * g)."""
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv

    env = FleetChargingEnv(num_sites=8, seed=0)
    batch = None
    steps = {}
    for clip in (0.0, 1e-3):
        torch.manual_seed(0)
        cfg = make_cfg(["agent=dqn", f"network.grad_clip={clip}", "network.weight_decay=0"])
        lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, 0.9, "cpu")
        params = lrn.loss.value_network_params
        lrn.optimizer = torch.optim.SGD(params.values(True, True), lr=1.0)
        if batch is None:
            batch = env.rollout(60, lrn.explore, break_when_any_done=False)
        lrn.observe(batch)
        lrn.buffer.sample = lambda b=lrn.buffer[:64]: b  # same sample for both runs
        before = params.clone().detach()
        lrn.update(1)
        delta = (params.detach() - before).flatten_keys()
        steps[clip] = float(torch.cat([v.flatten() for v in delta.values()]).norm())
    assert steps[0.0] > 1e-3  # unclipped gradients are larger than the cap here
    assert steps[1e-3] == pytest.approx(1e-3, rel=1e-3)


def test_policy_files_round_trip_and_reject_bad_input(tmp_path):
    from fleet_torchrl.agents.dqn import DQNPolicy, make_qnet

    cfg = make_cfg(["agent=dqn"])
    pol = DQNPolicy(make_qnet(cfg.network, 3), "partial")
    save_policy(tmp_path / "p" / "policy.pt", pol, "dqn", 3, cfg.network)
    back = load_policy_file(tmp_path / "p")
    obs = torch.rand(50, 3)
    assert torch.equal(back(obs), pol(obs)) and back.encoding == "partial"
    tab = TabularLearner().policy
    tab.q.uniform_(-1, 1)
    save_policy(tmp_path / "t.pt", tab, "tabular", 3)
    assert torch.equal(load_policy_file(tmp_path / "t.pt").q, tab.q)
    with pytest.raises(FileNotFoundError, match="no saved policy"):
        load_policy_file(tmp_path / "nothing")
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not a readable policy file"):
        load_policy_file(tmp_path / "bad.pt")
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a fleet_torchrl policy file"):
        load_policy_file(tmp_path / "foreign.pt")


# ---------------------------------------------------------------------- training
TINY_TAB = ["agent=tabular", "agent.num_sites=32", "train.max_episodes=192", "train.eval_every=2",
            "train.eval_sims=32", "train.eval_ticks=1500", "train.checkpoint_every=1",
            "train.progress=false", "mdp.tau_e=1500"]
TINY_DQN = ["agent=dqn", "agent.num_sites=4", "agent.steps_per_round=40",
            "agent.updates_per_round=30", "agent.eps_decay_frames=400", "train.max_episodes=16",
            "train.eval_every=2", "train.eval_sims=16", "train.eval_ticks=600",
            "train.checkpoint_every=1", "train.progress=false", "mdp.tau_e=300"]


def _train(overrides, tmp, stop_after=None, resume=False):
    from fleet_torchrl.training import Trainer

    cfg = make_cfg(overrides + [f"train.out_dir={tmp}/policy", f"resume={str(resume).lower()}"])
    tr = Trainer(cfg, tmp)
    return tr, tr.run(stop_after_rounds=stop_after)


@pytest.mark.slow
def test_tabular_training_learns_and_saves(tmp_path):
    tr, summary = _train(TINY_TAB, tmp_path)
    assert summary["rounds"] == 6 and summary["episodes"] == 192
    q = tr.learner.policy.q.view(10, 10, 2, 2)  # soc_D bin, other bin, TC busy, action
    visited = tr.learner.policy.visits.view(10, 10, 2, 2).sum(-1) > 20
    # learning happened: with the charger busy and a nearly full battery, charging only
    # queues, so every well-visited such state must prefer passing
    busy_full = visited[8:, 4:, 1]
    assert busy_full.sum() >= 5
    assert (q[8:, 4:, 1, 0] > q[8:, 4:, 1, 1])[busy_full].all()
    pol = load_policy_file(tmp_path / "policy")
    assert pol.q.shape == (200, 2) and pol.q.abs().sum() > 0
    assert (tmp_path / "train_summary.json").exists()
    # TensorBoard's own reader sees the namespaced tags
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(glob.glob(str(tmp_path / "tb"))[0])
    ea.Reload()
    tags = set(ea.Tags()["scalars"])
    for tag in ("train/episode_reward", "train/trips", "train/queue_ticks", "train/epsilon",
                "loss/td_error", "eval/trips", "eval/queue", "eval/failure_rate",
                "eval/gain_over_rule_pct", "time/fps", "time/wall_s"):
        assert tag in tags, tag
    assert "policy_map" in ea.Tags()["images"]


@pytest.mark.slow
def test_tabular_resume_ends_where_an_uninterrupted_run_does(tmp_path):
    full, s_full = _train(TINY_TAB, tmp_path / "a")
    _train(TINY_TAB, tmp_path / "b", stop_after=3)  # "killed" after round 3's checkpoint
    res, s_res = _train(TINY_TAB, tmp_path / "b", resume=True)
    assert s_res["resumed"] and s_res["rounds"] == s_full["rounds"]
    assert torch.equal(res.learner.policy.q, full.learner.policy.q)
    assert torch.equal(res.learner.policy.visits, full.learner.policy.visits)
    assert [h["trips"] for h in s_res["history"]] == [h["trips"] for h in s_full["history"]]


def test_resume_with_another_config_is_refused(tmp_path):
    tiny = [*TINY_TAB, "train.max_episodes=64"]
    _train(tiny, tmp_path, stop_after=1)
    ckpt = tmp_path / "checkpoint.ckpt"
    assert ckpt.exists()
    with pytest.raises(ValueError, match=r"another configuration \(mdp.r_trip: 0.0 -> 1.0\)"):
        _train([*tiny, "mdp.r_trip=1.0"], tmp_path, resume=True)
    # run-control settings may change on resume; the checkpoint is untouched by the refusal
    _, summary = _train([*tiny, "train.checkpoint_every=2"], tmp_path, resume=True)
    assert summary["resumed"] and summary["rounds"] == 2
    ckpt.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        _train(tiny, tmp_path, resume=True)


@pytest.mark.slow
def test_dqn_training_and_resume(tmp_path):
    full, s_full = _train(TINY_DQN, tmp_path / "a")
    assert s_full["rounds"] == 4 and s_full["best"] is not None
    assert load_policy_file(tmp_path / "a" / "policy").encoding == "partial"
    _train(TINY_DQN, tmp_path / "b", stop_after=2)
    res, s_res = _train(TINY_DQN, tmp_path / "b", resume=True)
    assert s_res["resumed"] and s_res["rounds"] == 4
    for (k, a), (_, b) in zip(full.learner.qnet.state_dict().items(),
                              res.learner.qnet.state_dict().items(), strict=True):
        assert torch.equal(a, b), k
    assert len(res.learner.buffer) == len(full.learner.buffer)
    assert res.learner.epsilon == full.learner.epsilon
    assert [h["trips"] for h in s_res["history"]] == [h["trips"] for h in s_full["history"]]


def test_untrainable_agent_is_refused(tmp_path):
    from fleet_torchrl.training import Trainer

    with pytest.raises(ValueError, match="not trainable"):
        Trainer(make_cfg(["agent=rule"]), tmp_path)
    with pytest.raises(ValueError, match="state.name='all' is invalid for agent=tabular"):
        make_cfg(["agent=tabular", "state=all"])
