"""The training loop: learning, TensorBoard tags, checkpoints and resume."""

from __future__ import annotations

import glob

import pytest
import torch

from fleet_torchrl.agents import load_policy_file
from fleet_torchrl.config import compose_config

# ---------------------------------------------------------------------- training
TINY_TAB = ["agent=tabular", "agent.num_sites=32", "train.max_episodes=192", "train.eval_every=2",
            "train.eval_sims=32", "train.eval_ticks=1500", "train.checkpoint_every=1",
            "train.progress=false", "mdp.tau_e=1500"]


TINY_DQN = ["agent=dqn", "agent.num_sites=4", "agent.steps_per_round=40",
            "agent.updates_per_round=30", "agent.eps_decay_frames=400", "train.max_episodes=16",
            "train.eval_every=2", "train.eval_sims=16", "train.eval_ticks=600",
            "train.checkpoint_every=1", "train.progress=false", "mdp.tau_e=300"]


def _train(overrides, tmp, stop_after=None, resume=False):
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*overrides, f"train.out_dir={tmp}/policy",
                          f"resume={str(resume).lower()}"])
    tr = Trainer(RunSpec.of(cfg), tmp, resume=cfg.resume)
    return tr, tr.run(stop_after_rounds=stop_after)


@pytest.mark.slow
def test_tabular_training_learns_and_saves(tmp_path):
    tr, summary = _train(TINY_TAB, tmp_path)
    assert summary["rounds"] == 6 and summary["episodes"] == 192
    q = tr.learner.table.q.view(10, 10, 2, 2)  # soc_D bin, other bin, TC busy, action
    visited = tr.learner.table.visits.view(10, 10, 2, 2).sum(-1) > 20
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
                "loss/td", "eval/trips", "eval/queue", "eval/failure_rate",
                "eval/gain_over_rule_pct", "time/fps", "time/wall_s"):
        assert tag in tags, tag
    assert "policy_map/best" in ea.Tags()["images"]


@pytest.mark.slow
def test_tabular_resume_ends_where_an_uninterrupted_run_does(tmp_path):
    full, s_full = _train(TINY_TAB, tmp_path / "a")
    _train(TINY_TAB, tmp_path / "b", stop_after=3)  # "killed" after round 3's checkpoint
    res, s_res = _train(TINY_TAB, tmp_path / "b", resume=True)
    assert s_res["resumed"] and s_res["rounds"] == s_full["rounds"]
    assert torch.equal(res.learner.table.q, full.learner.table.q)
    assert torch.equal(res.learner.table.visits, full.learner.table.visits)
    assert [h["trips"] for h in s_res["history"]] == [h["trips"] for h in s_full["history"]]


def test_resume_with_another_config_is_refused(tmp_path):
    tiny = [*TINY_TAB, "train.max_episodes=64"]
    _train(tiny, tmp_path, stop_after=1)
    ckpt = tmp_path / "checkpoint.ckpt"
    assert ckpt.exists()
    with pytest.raises(ValueError, match=r"another configuration \(mdp.reward: 'thesis' -> "
                                         r"'throughput'\)"):
        _train([*tiny, "mdp.reward=throughput"], tmp_path, resume=True)
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
    assert res.learner.exploration() == full.learner.exploration()
    assert [h["trips"] for h in s_res["history"]] == [h["trips"] for h in s_full["history"]]


def test_untrainable_agent_is_refused(tmp_path):
    from fleet_torchrl.training import RunSpec, Trainer

    with pytest.raises(ValueError, match="not trainable"):
        Trainer(RunSpec.of(compose_config(["agent=rule"])), tmp_path)
    with pytest.raises(ValueError, match="state.name='all' is invalid for agent=tabular"):
        compose_config(["agent=tabular", "state=all"])


@pytest.mark.parametrize("objective", ["thesis", "throughput"])
@pytest.mark.parametrize("learner", ["tabular", "dqn"])
def test_every_learner_trains_with_every_objective(tmp_path, learner, objective):
    """A tiny run per learner and objective: it trains, evaluates, saves a loadable policy."""
    tiny = {"tabular": [*TINY_TAB, "train.max_episodes=64"],
            "dqn": [*TINY_DQN, "agent.n_steps=3", "network.lr_decay=cosine",
                    "network.tau=0.01"]}[learner]
    tr, summary = _train([*tiny, f"mdp.reward={objective}", "train.tensorboard=false"],
                         tmp_path)
    assert summary["best"] is not None and summary["frames"] > 0
    assert summary["fingerprint"]["mdp"]["reward"] == objective
    pol = load_policy_file(tmp_path / "policy")
    obs = torch.rand(32, 3)
    assert torch.equal(pol(obs), tr.best_policy(obs))


def test_episodes_run_on_across_rounds_when_asked(tmp_path):
    """agent.reset_each_round=false: a round goes on from where the last one stopped."""
    tiny = [*TINY_DQN, "agent.reset_each_round=false", "agent.steps_per_round=5",
            "train.tensorboard=false"]
    tr, _ = _train(tiny, tmp_path / "on", stop_after=1)
    ticks1, episodes1 = tr._next["ticks"].squeeze(-1).clone(), tr.env.episodes.clone()
    tr.run(stop_after_rounds=1)
    ticks2 = tr._next["ticks"].squeeze(-1)
    same_episode = tr.env.episodes == episodes1  # no reset of the site in round 2
    assert same_episode.any()
    assert (ticks2[same_episode] > ticks1[same_episode]).all()  # its episode went on


@pytest.mark.parametrize("reset", ["true", "false"])
def test_dqn_collects_through_torchrl_collector_with_the_loops_numbers(tmp_path, monkeypatch,
                                                                       reset):
    """A DQN round comes from TorchRL's Collector (training/collect.py): the same steps,
    random draws and learning as the training loop stepping the environment itself, bit for
    bit, with rounds that restart every site and rounds whose episodes run on."""
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.training.collect import CollectedRounds

    tiny = [*TINY_DQN, f"agent.reset_each_round={reset}", "agent.steps_per_round=5",
            "train.tensorboard=false"]
    col, s_col = _train(tiny, tmp_path / "collector")
    assert isinstance(col._collected, CollectedRounds)
    monkeypatch.setattr(DQNLearner, "collects", False)
    loop, s_loop = _train(tiny, tmp_path / "loop")
    assert loop._collected is None and s_loop["frames"] == s_col["frames"] == 4 * 4 * 5
    for (k, a), (_, b) in zip(col.learner.qnet.state_dict().items(),
                              loop.learner.qnet.state_dict().items(), strict=True):
        assert torch.equal(a, b), k
    assert col.learner.exploration() == loop.learner.exploration() < 1.0
    stored = [lrn.buffer[: len(lrn.buffer)] for lrn in (col.learner, loop.learner)]
    assert len(col.learner.buffer) > 0 and (stored[0] == stored[1]).all()
    assert torch.equal(col.env.episodes, loop.env.episodes)
    assert torch.equal(col._next["observation"], loop._next["observation"])
    evals = [[(h["trips"], h["queue"], h["failure_rate"]) for h in s["history"]]
             for s in (s_col, s_loop)]
    assert evals[0] == evals[1] and len(evals[0]) == 2


def test_resume_without_a_checkpoint_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="resume=true, but there is no checkpoint"):
        _train([*TINY_TAB, "train.max_episodes=32"], tmp_path / "empty", resume=True)


def test_snapshot_selection_follows_train_select():
    from fleet_torchrl.training.progress import Progress, selection_score

    early = {"trips_mean": 350.0, "queue_mean": 40.0, "failure_rate": 0.0}
    late = {"trips_mean": 349.0, "queue_mean": 8.0, "failure_rate": 0.0}
    unsafe = {"trips_mean": 360.0, "queue_mean": 1.0, "failure_rate": 0.002}
    for select, reward, winner in [("trips", "thesis", early), ("objective", "thesis", late),
                                   ("objective", "throughput", early),
                                   ("objective", "trips", early)]:  # the direct search
        p = Progress()
        for res in (unsafe, early, late):
            score = selection_score(select, reward, res)
            if p.is_better(res["failure_rate"], score):
                p.best, kept = (res["failure_rate"], score), res
        assert kept is winner, (select, reward)
    # the search reports "trips" as its objective whatever mdp.reward is
    search = compose_config(["agent=search"])
    assert search.agent.objective(search.mdp) == "trips"


def test_policy_is_promoted_only_at_a_successful_end(tmp_path):
    """A killed run leaves results/policies untouched; a finished one publishes its policy
    with a summary that names the policy file's hash (make table checks the pair)."""
    from fleet_torchrl.experiments.table import reusable
    from fleet_torchrl.utils.runinfo import file_sha256

    over = [*TINY_TAB, "train.tensorboard=false"]
    _train(over, tmp_path, stop_after=2)
    assert (tmp_path / "policy.pt").is_file()  # the run's own folder has its best so far
    assert not (tmp_path / "policy").exists()  # nothing published yet
    cfg = compose_config([*over, f"train.out_dir={tmp_path}/policy", "resume=true"])
    from fleet_torchrl.training import RunSpec, Trainer

    summary = Trainer(RunSpec.of(cfg), tmp_path, resume=True).run()
    pub = tmp_path / "policy"
    assert summary["policy_sha256"] == file_sha256(pub / "policy.pt")
    assert reusable(pub, cfg)
    # another run's policy beside this summary (a concurrent writer): not reused
    other = tmp_path / "other"
    _train([*over, "seed=5"], other)
    (other / "policy" / "policy.pt").replace(pub / "policy.pt")
    assert not reusable(pub, cfg)


def test_checkpoint_with_a_corrupted_member_is_a_clear_error(tmp_path):
    import zipfile

    tiny = [*TINY_TAB, "train.max_episodes=64", "train.tensorboard=false"]
    _train(tiny, tmp_path, stop_after=1)
    ckpt = tmp_path / "checkpoint.ckpt"
    with zipfile.ZipFile(ckpt) as z:
        infos = [(i.filename, i.header_offset, i.compress_size) for i in z.infolist()]
    raw = bytearray(ckpt.read_bytes())
    name, offset, size = max(infos, key=lambda t: t[2])  # the largest member's data
    start = offset + 30 + len(name.encode())  # local header (no extra field in these files)
    for k in range(start + 10, start + min(size, 200)):
        raw[k] ^= 0xFF
    ckpt.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="cannot resume from .*checkpoint.ckpt"):
        _train(tiny, tmp_path, resume=True)


def test_robust_selection_keeps_a_snapshot_that_never_loses_to_the_heuristic(tmp_path):
    """``train.select=robust`` ranks snapshots by their worst paired gain over the heuristic
    in any stratum of the selection set: an anchored DQN with an unreachable margin is the
    heuristic itself, worst gain exactly 0 in every stratum."""
    from fleet_torchrl.evaluation import site_strata

    tr, out = _train([*TINY_DQN, "site=randomized", "agent.anchor=heuristic",
                      "agent.anchor_margin=1e9", "train.select=robust",
                      "train.tensorboard=false"], tmp_path)
    assert set(tr.strata) == set(site_strata(tr.cfg.site, 16, tr.cfg.train.eval_seed))
    assert tr.progress.best == (0.0, 0.0)
    assert out["best"]["trips"] == pytest.approx(tr.heuristic_eval["trips_mean"])


def test_guarded_selection_judges_every_stratum_against_the_heuristic(tmp_path):
    """``train.select=guarded`` evaluates the heuristic on the selection set once and logs,
    per evaluation, in how many strata the snapshot is significantly below it: the heuristic
    itself (an unreachable anchor margin) is below it in none."""
    from fleet_torchrl.evaluation import site_strata

    tr, out = _train([*TINY_DQN, "site=randomized", "agent.anchor=heuristic",
                      "agent.anchor_margin=1e9", "train.select=guarded"], tmp_path)
    assert set(tr.strata) == set(site_strata(tr.cfg.site, 16, tr.cfg.train.eval_seed))
    assert out["best"]["trips"] == pytest.approx(tr.heuristic_eval["trips_mean"])
    assert tr.progress.best[1] > -1e6  # no snapshot took the guard's penalty
    assert "eval/strata_below_heuristic" in _scalar_tags(tmp_path)


def _scalar_tags(run_dir) -> set[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(glob.glob(str(run_dir / "tb"))[0])
    ea.Reload()
    return set(ea.Tags()["scalars"])


def test_dqn_logs_learning_rate_q_values_and_gradient_norm(tmp_path, monkeypatch):
    """DQN's TensorBoard scalars say how the optimisation goes; the run's hparams are what
    shapes what it learns, not how it is run."""
    from fleet_torchrl.utils.monitor import Monitor

    logged = {}
    monkeypatch.setattr(Monitor, "hparams", lambda self, cfg, metrics: logged.update(cfg))
    _train([*TINY_DQN, "network.lr_decay=cosine"], tmp_path)
    tags = _scalar_tags(tmp_path)
    assert {"train/lr", "train/q_mean", "loss/grad_norm", "loss/td", "train/epsilon"} <= tags
    assert "train/spread" not in tags
    assert logged["agent"]["n_steps"] == 3 and logged["network"]["lr_decay"] == "cosine"
    assert logged["seed"] == 0 and "eval_sims" in logged["train"]
    run_control = {"out_dir", "progress", "tensorboard", "device", "threads",
                   "checkpoint_every"}
    assert not run_control & set(logged["train"]) and "policy" not in logged["agent"]


def test_the_search_logs_its_spread_under_its_own_name(tmp_path):
    _train(["agent=search", "agent.generations=2", "agent.population=8", "agent.elite=2",
            "agent.sites=4", "agent.ticks=200", "train.eval_every=1", "train.eval_sims=8",
            "train.eval_ticks=300", "train.progress=false"], tmp_path)
    tags = _scalar_tags(tmp_path)
    assert "train/spread" in tags and "train/epsilon" not in tags


def test_log_lines_go_above_the_progress_bar(tmp_path, capsys):
    """With train.progress, a log line clears the bar and takes a line of its own (tqdm's
    logging redirect); without it, it would be written onto the bar's line."""
    import logging
    import sys

    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)  # a console handler, as Hydra's job logging
    level = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        _train([*TINY_TAB, "train.max_episodes=128", "train.eval_every=1",
                "train.progress=true", "train.tensorboard=false"], tmp_path)
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
    err = capsys.readouterr().err
    assert "train tabular" in err  # the bar ran
    logs = [ln for ln in err.split("\n") if ": eval " in ln and "vs rule" in ln]
    assert len(logs) >= 4
    assert all(ln.split("\r")[-1].startswith("round ") for ln in logs), logs
