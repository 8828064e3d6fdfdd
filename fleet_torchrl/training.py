"""Training loops for the learned agents (SPEC §3), with explicit setup stages.

Schedule. Training runs in *rounds*: every round resets all ``agent.num_sites`` sites of the
batched environment, so ``train.max_episodes / num_sites`` rounds in all (the budget counts
one full episode per site and round). Starting every round from fresh resets makes a
round boundary a clean checkpoint: the environment's whole state there is its seed and episode
counters, and a resumed run continues exactly where an uninterrupted one would.

Steps truncated by the tick budget end between two decisions, so their next observation is
not a decision state; neither agent learns from them (one transition per episode).

* Tabular: a round plays exactly one episode per site (``mdp.tau_e`` ticks, or until
  failure); online Q-learning, one batched update per environment step, epsilon decayed
  exponentially per episode (round) to ``eps_end``.
* DQN: a TorchRL ``Collector`` (``reset_at_each_iter=True``) collects
  ``num_sites x steps_per_round`` decisions with the epsilon-greedy actor: one full episode
  per site (450 decisions cover ``tau_e = 3000`` ticks), and sites whose episode ended
  early start a new one that the round's end cuts off (``train/episodes`` counts every
  episode that ended). The batch goes to the replay buffer, then ``updates_per_round``
  gradient steps.

Every ``eval_every`` rounds the greedy policy is evaluated with the protocol of SPEC §4 on a
fixed common-random-numbers set (``train.eval_*``), next to the rule on the same set. Policies
rank by failure rate first, then mean trips; the best policy is saved at once (atomically) and
training stops after ``patience`` evaluations without improvement. A checkpoint (learner,
optimiser, target network, replay buffer, epsilon, RNG states, counters, best policy) is
written atomically every ``checkpoint_every`` rounds and at the end.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from .agents import POLICY_FILE, default_policy_dir, run_name, save_policy
from .config import Config
from .env import FleetChargingEnv
from .evaluation import evaluate_policy, gain_over
from .monitor import Monitor
from .plotting import TC_DQN, TC_TABULAR, plot_policy_map
from .policies import Policy, RulePolicy
from .runinfo import run_info, to_jsonable, write_json

CHECKPOINT = "checkpoint.ckpt"

# settings a resumed run may change: they steer the run, not what it learns
_RUN_CONTROL = {"out_dir", "device", "threads", "tensorboard", "progress", "checkpoint_every"}


def training_fingerprint(cfg: Config) -> dict[str, Any]:
    """The part of the config that determines what a training run computes.

    Stored in every checkpoint; resuming with a different one would splice two runs.
    """
    train = {k: v for k, v in asdict(cfg.train).items() if k not in _RUN_CONTROL}
    return to_jsonable({"site": cfg.site, "state": cfg.state, "mdp": cfg.mdp,
                        "agent": cfg.agent, "network": cfg.network, "train": train,
                        "seed": cfg.seed})


def fingerprint_diff(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """``key: old -> new`` for every leaf that differs."""
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += fingerprint_diff(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}: {a!r} -> {b!r}")
    return out


def checkpoint_mismatch(path: str | Path, cfg: Config) -> list[str]:
    """Why the checkpoint at ``path`` cannot continue a run of ``cfg`` (empty if it can).

    Raises ``ValueError`` if the file is not a readable checkpoint.
    """
    from torchrl.checkpoint import Checkpoint, CheckpointError

    try:
        meta = Checkpoint.manifest(path).get("metadata") or {}
    except (CheckpointError, OSError, ValueError, KeyError) as e:
        raise ValueError(f"cannot resume from {path}: not a readable checkpoint ({e})") from None
    stored = meta.get("config")
    if stored is None:
        return ["the checkpoint records no configuration (written by an older version)"]
    return fingerprint_diff(stored, training_fingerprint(cfg))


def better(result: dict[str, Any], best: list[float] | None) -> bool:
    """Lower failure rate wins; at equal failure rate, more trips."""
    if best is None:
        return True
    return (-result["failure_rate"], result["trips_mean"]) > (-best[0], best[1])


class Trainer:
    """Setup stages: environment, agent, evaluation, monitoring, checkpoint; then :meth:`run`."""

    def __init__(self, cfg: Config, run_dir: str | Path) -> None:
        if cfg.agent.name not in ("tabular", "dqn"):
            raise ValueError(f"agent.name={cfg.agent.name!r} is not trainable: use agent=tabular "
                             "or agent=dqn")
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.name = run_name(cfg)
        self.out_dir = default_policy_dir(cfg)
        self.device = torch.device(cfg.train.device)
        self.n_rounds = math.ceil(cfg.train.max_episodes / cfg.agent.num_sites)
        self.progress: dict[str, Any] = {"round": 0, "frames": 0, "episodes": 0, "best": None,
                                         "best_round": None, "evals_since_best": 0,
                                         "stopped_early": False, "env_episodes": None,
                                         "history": [], "wall_s": 0.0}
        torch.manual_seed(cfg.seed)
        self.setup_env()
        self.setup_agent()
        self.setup_evaluation()
        self.setup_monitor()
        self.setup_checkpoint()

    # ------------------------------------------------------------------ setup stages
    def setup_env(self) -> None:
        c = self.cfg
        self.env = FleetChargingEnv(site=c.site, encoding=c.state.name,
                                    num_sites=c.agent.num_sites, mdp=c.mdp, seed=c.seed,
                                    device=self.device)
        self.n_obs = self.env.observation_spec["observation"].shape[-1]

    def setup_agent(self) -> None:
        c = self.cfg
        if c.agent.name == "tabular":
            from .agents.tabular import TabularLearner

            self.learner = TabularLearner(k=c.agent.k, gamma=c.mdp.gamma).to(self.device)
            self.collector = None
        else:
            from torchrl.collectors import Collector

            from .agents.dqn import DQNLearner

            self.learner = DQNLearner(c.agent, c.network, self.n_obs, c.state.name,
                                      self.env.action_spec, c.mdp.gamma, self.device)
            fpb = c.agent.num_sites * c.agent.steps_per_round
            self.collector = Collector(self.env, self.learner.explore, frames_per_batch=fpb,
                                       total_frames=fpb * (self.n_rounds + 1),
                                       reset_at_each_iter=True, device=self.device,
                                       auto_register_policy_transforms=False)
            self._collector_iter = iter(self.collector)
        self.best_policy = copy.deepcopy(self.policy()).cpu()

    def setup_evaluation(self) -> None:
        t = self.cfg.train
        self.eval_args = dict(site_cfg=self.cfg.site, n_sims=t.eval_sims, ticks=t.eval_ticks,
                              seed=t.eval_seed, device=t.device)
        self.rule_eval = evaluate_policy(RulePolicy(), **self.eval_args)

    def setup_monitor(self) -> None:
        self.monitor = Monitor(self.run_dir / "tb" if self.cfg.train.tensorboard else None)

    def setup_checkpoint(self) -> None:
        from torchrl.checkpoint import Checkpoint, GlobalRNGState

        self.checkpoint = Checkpoint(format="archive", learner=self.learner,
                                     best_policy=self.best_policy, rng=GlobalRNGState(),
                                     progress=self.progress)
        if self.collector is not None:
            self.checkpoint.register("replay_buffer", self.learner.buffer)
        self.checkpoint_path = self.run_dir / CHECKPOINT

    # ------------------------------------------------------------------ helpers
    def policy(self) -> Policy:
        if self.cfg.agent.name == "tabular":
            return self.learner.policy
        pol = self.learner.policy()
        pol.name = self.name
        return pol

    def epsilon(self) -> float:
        a = self.cfg.agent
        if a.name == "dqn":
            return self.learner.epsilon
        r = self.progress["round"]
        if a.eps_end <= 0.0:
            return a.eps_start if r == 0 else 0.0
        return max(a.eps_end, a.eps_start * (a.eps_end / a.eps_start) ** (r / a.eps_decay_episodes))

    def save_checkpoint(self) -> None:
        self.progress["env_episodes"] = self.env._episodes.tolist()
        self.checkpoint.save(self.checkpoint_path,
                             metadata={"run": self.name,
                                       "config": training_fingerprint(self.cfg)})

    def load_checkpoint(self) -> bool:
        if not self.checkpoint_path.exists():
            return False
        from torchrl.checkpoint import CheckpointError

        diff = checkpoint_mismatch(self.checkpoint_path, self.cfg)
        if diff:
            raise ValueError(f"cannot resume from {self.checkpoint_path}: it belongs to another "
                             f"configuration ({'; '.join(diff[:5])}); resume with the same "
                             "settings or start a new run directory")

        try:
            self.checkpoint.load(self.checkpoint_path, map_location=self.device)
        except (CheckpointError, OSError, ValueError, KeyError) as e:
            raise ValueError(f"cannot resume from {self.checkpoint_path}: {e}") from None
        self.env._episodes.copy_(torch.tensor(self.progress["env_episodes"]))
        return True

    # ------------------------------------------------------------------ one round
    def _tabular_round(self) -> dict[str, float]:
        env, learner = self.env, self.learner
        eps = self.epsilon()
        td = env.reset()
        b = env.num_sites
        live = torch.ones(b, dtype=torch.bool, device=self.device)
        ep_reward = torch.zeros(b, device=self.device)
        # per-site counters at the end of each site's episode
        final = {k: torch.zeros(b, dtype=torch.int64, device=self.device)
                 for k in ("trips", "queue_ticks", "ticks")}
        final["failed"] = torch.zeros(b, dtype=torch.bool, device=self.device)
        td_err, n_upd, frames = 0.0, 0, 0
        while bool(live.any()):
            obs = td["observation"]
            action = learner.act(obs, eps)
            td = env.step(td.set("action", action))
            nxt = td["next"]
            reward = nxt["reward"].squeeze(-1)
            term, done = nxt["terminated"].squeeze(-1), nxt["done"].squeeze(-1)
            # a truncated step ends between decisions: its next observation is no decision
            # state, so it is not learned from (one transition per episode)
            learn = live & ~nxt["truncated"].squeeze(-1)
            td_err += learner.update(obs, action, reward, nxt["observation"], term, learn)
            n_upd += 1
            frames += int(live.sum())
            ep_reward += reward * live
            ending = live & done
            for key in ("trips", "queue_ticks", "ticks"):
                final[key] = torch.where(ending, nxt[key].squeeze(-1), final[key])
            final["failed"] = torch.where(ending, term, final["failed"])
            live &= ~done
            td = env.step_mdp(td)
        return {"frames": frames, "episodes": b, "train/episode_reward": float(ep_reward.mean()),
                "train/trips": float(final["trips"].float().mean()),
                "train/queue_ticks": float(final["queue_ticks"].float().mean()),
                "train/failures": float(final["failed"].float().mean()),
                "train/epsilon": eps, "loss/td_error": td_err / max(n_upd, 1)}

    def _dqn_round(self) -> dict[str, float]:
        eps = self.epsilon()
        batch = next(self._collector_iter)
        self.learner.observe(batch)
        loss = self.learner.update(self.cfg.agent.updates_per_round)
        done = batch["next", "done"].squeeze(-1)
        out = {"frames": batch.numel(), "episodes": int(done.sum()), "train/epsilon": eps,
               "loss/td": loss, "train/buffer_size": len(self.learner.buffer)}
        if done.any():
            nxt = batch["next"]
            # episode reward: sum of step rewards of each trajectory that ended in this batch
            traj = batch["collector", "traj_ids"]
            ended = traj[done]
            rew = batch["next", "reward"].squeeze(-1)
            per_traj = torch.zeros(int(traj.max()) + 1, device=rew.device).index_add_(
                0, traj.flatten(), rew.flatten())
            out.update({"train/episode_reward": float(per_traj[ended].mean()),
                        "train/trips": float(nxt["trips"].squeeze(-1)[done].float().mean()),
                        "train/queue_ticks": float(nxt["queue_ticks"].squeeze(-1)[done]
                                                   .float().mean()),
                        "train/failures": float(nxt["terminated"].squeeze(-1)[done]
                                                .float().mean())})
        return out

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, step: int) -> dict[str, Any]:
        pol = self.policy()
        res = evaluate_policy(pol, name=self.name, **self.eval_args)
        gain = gain_over(res, self.rule_eval)["gain_pct"]
        p = self.progress
        if better(res, p["best"]):
            p.update(best=[res["failure_rate"], res["trips_mean"]], best_round=p["round"],
                     evals_since_best=0)
            self.best_policy.load_state_dict({k: v.detach().cpu()
                                              for k, v in pol.state_dict().items()})
            self.save_best()
        else:
            p["evals_since_best"] += 1
        entry = {"round": p["round"], "frames": p["frames"], "trips": res["trips_mean"],
                 "queue": res["queue_mean"], "failure_rate": res["failure_rate"],
                 "gain_pct": gain}
        p["history"].append(entry)
        self.monitor.scalars({"eval/trips": res["trips_mean"], "eval/queue": res["queue_mean"],
                              "eval/failure_rate": res["failure_rate"],
                              "eval/gain_over_rule_pct": gain, "eval/best_trips": p["best"][1]},
                             step)
        if pol.encoding == "partial":
            tcs = TC_TABULAR if self.cfg.agent.name == "tabular" else TC_DQN
            fig = plot_policy_map(pol, tcs, title=f"{self.name}, round {p['round']}")
            self.monitor.figure("policy_map", fig, step)
            import matplotlib.pyplot as plt

            plt.close(fig)
        return entry

    def save_best(self) -> None:
        kind = self.cfg.agent.name
        net = self.cfg.network if kind == "dqn" else None
        pol = self.best_policy
        pol.encoding = self.cfg.state.name
        save_policy(self.out_dir / POLICY_FILE, pol, kind, self.n_obs, net,
                    meta=run_info(self.cfg, seed=self.cfg.seed))

    # ------------------------------------------------------------------ main loop
    def run(self, stop_after_rounds: int | None = None) -> dict[str, Any]:
        """Train to the end (or for ``stop_after_rounds`` more rounds, for tests of resume)."""
        c = self.cfg
        resumed = c.resume and self.load_checkpoint()
        p = self.progress
        bar = None
        if c.train.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=self.n_rounds, initial=p["round"], desc=f"train {self.name}",
                       unit="round")
        t_start = time.perf_counter() - p["wall_s"]
        rounds_done = 0
        while p["round"] < self.n_rounds and not p["stopped_early"]:
            if stop_after_rounds is not None and rounds_done >= stop_after_rounds:
                break
            t0 = time.perf_counter()
            stats = self._tabular_round() if self.collector is None else self._dqn_round()
            dt = time.perf_counter() - t0
            p["round"] += 1
            rounds_done += 1
            n_frames = stats.pop("frames")
            p["frames"] += n_frames
            p["episodes"] += stats.pop("episodes")
            p["wall_s"] = time.perf_counter() - t_start
            step = p["frames"]
            self.monitor.scalars({**stats, "train/episodes": p["episodes"],
                                  "time/fps": n_frames / max(dt, 1e-9),
                                  "time/wall_s": p["wall_s"], "time/round_s": dt}, step)
            postfix = {"frames": step, "eps": f"{self.epsilon():.2f}"}
            if p["round"] % c.train.eval_every == 0 or p["round"] == self.n_rounds:
                entry = self.evaluate(step)
                postfix["eval_trips"] = f"{entry['trips']:.1f}"
                if c.train.patience and p["evals_since_best"] >= c.train.patience:
                    p["stopped_early"] = True
            if p["best"] is not None:
                postfix["best"] = f"{p['best'][1]:.1f}"
            if bar is not None:
                bar.update(1)
                bar.set_postfix(postfix)
            if p["round"] % c.train.checkpoint_every == 0:
                self.save_checkpoint()
        if bar is not None:
            bar.close()
        finished = p["round"] >= self.n_rounds or p["stopped_early"]
        if finished and not p["history"]:
            self.evaluate(p["frames"])
        self.save_checkpoint()
        summary = self.summary(resumed)
        if finished:
            write_json(self.out_dir / "train_summary.json", summary)
            write_json(self.run_dir / "train_summary.json", summary)
            best = summary["best"]
            self.monitor.hparams(asdict(c), {"hparam/eval_trips": best["trips"],
                                             "hparam/gain_pct": best["gain_pct"],
                                             "hparam/failure_rate": best["failure_rate"]})
        self.monitor.close()
        if self.collector is not None and finished:
            self.collector.shutdown()
        return summary

    def summary(self, resumed: bool) -> dict[str, Any]:
        p = self.progress
        best = None
        if p["history"] and p["best_round"] is not None:
            best = next(h for h in p["history"] if h["round"] == p["best_round"])
        return {"name": self.name, "rounds": p["round"], "frames": p["frames"],
                "episodes": p["episodes"], "wall_s": p["wall_s"], "resumed": resumed,
                "stopped_early": p["stopped_early"], "best": best,
                "rule_on_eval_set": {k: self.rule_eval[k] for k in ("trips_mean", "queue_mean",
                                                                    "failure_rate")},
                "policy": str(self.out_dir / POLICY_FILE), "run_dir": str(self.run_dir),
                "history": p["history"], "meta": run_info(self.cfg, seed=self.cfg.seed)}
