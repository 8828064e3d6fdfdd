"""The training loop: one loop for every learner (MODEL §3), with explicit setup stages.

Schedule. Training runs in ``agent.training_rounds(train)`` *rounds* over a batched
environment of ``agent.num_sites`` sites: ``train.max_episodes / agent.num_sites`` (the
budget counts one episode per site and round; a round starts from fresh resets unless the
learner lets episodes run on, see below), ``agent.generations`` for the direct search.
A round is ``learner.start_round``, then environment steps (``learner.act`` -> ``env`` ->
``learner.observe``), then ``learner.update``:

* a learner with ``steps_per_round = None`` (tabular) plays exactly one episode per site:
  a site whose episode is done stops learning, and the round ends when all are done;
* a learner with ``steps_per_round = n`` (DQN) plays ``n`` steps of all sites, a site whose
  episode ends starting its next one at once (``env.step_and_maybe_reset``, as TorchRL's
  collectors do); a learner that ``collects`` (DQN) gets these steps from TorchRL's
  ``Collector`` (:meth:`Trainer.collect_round`, :mod:`fleet_torchrl.training.collect`);
* a learner with ``steps_per_round = 0`` (the direct search) takes no environment step: its
  ``update`` simulates what it needs (a generation).

Starting every round from fresh resets makes a round boundary a clean checkpoint: the
environment's whole state there is its seed and episode counters. A learner with
``reset_each_round = False`` lets episodes run on from one round into the next; the
checkpoint then also holds the sites in flight (the environment's ``state_dict``) and where
the next round starts (:class:`LoopState`), so a resumed run still ends exactly where an
uninterrupted one does.
Steps truncated by the tick budget end between two decisions, so their next observation is
no decision state; no learner learns from them.

Every ``eval_every`` rounds the greedy policy is evaluated with the protocol of MODEL §4 on a
fixed common-random-numbers set (``train.eval_*``), next to the rule on the same set. Policies
rank by failure rate first, then by :func:`~fleet_torchrl.training.progress.selection_score`
(``train.select``); the best policy is saved at once (atomically) into the run folder, and
published with its summary to its publish folder (``train.out_dir``, by default
``<table.policies_dir>/<name>/seed<s>``) only when the run ends, never over another policy
and, to the default folder, only if it failed no site (:meth:`Trainer.promote`).
Training stops after ``patience`` evaluations without improvement. A checkpoint (learner and
its extra components, best policy, environment counters, RNG states, progress) is written
atomically every ``checkpoint_every`` rounds and at the end.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from ..agents.base import Policy
from ..agents.baselines import HeuristicPolicy, RulePolicy
from ..agents.policy_files import POLICY_FILE, first_non_finite, save_policy
from ..agents.registry import LearnerContext, get_agent
from ..env import FleetChargingEnv
from ..evaluation import evaluate_policy, gain_over, site_strata, strata_below, worst_stratum_gain
from ..store import policy_name
from ..utils.monitor import Monitor
from ..utils.numerics import flush_denormals
from ..utils.paths import hold_run_dir, release_run_dir
from ..utils.plotting import plot_policy_map
from ..utils.runinfo import run_info, write_json
from .checkpoint import (
    CHECKPOINT,
    UNREADABLE,
    check_resumable,
    result_fingerprint,
    training_fingerprint,
)
from .progress import EvalEntry, Progress, selection_score
from .spec import RunSpec

log = logging.getLogger(__name__)


def training_hparams(spec: RunSpec) -> dict[str, Any]:
    """The TensorBoard hparams of a run: what shapes what it learns, the settings its
    checkpoint must match (:func:`~fleet_torchrl.training.checkpoint.training_fingerprint`:
    site, state, mdp, agent, network, train and seed), without run control (out_dir,
    progress, tensorboard, device, threads, checkpoint_every) and without the policy file an
    evaluation would load (``agent.policy``)."""
    fp = training_fingerprint(spec)
    fp["agent"] = {k: v for k, v in fp["agent"].items() if k != "policy"}
    return fp


class EpisodeStats:
    """Per-round statistics of the episodes that end, from the environment's counters."""

    def __init__(self, n: int, device: torch.device, reward: torch.Tensor | None = None) -> None:
        # running reward of each site's episode (carried over when episodes span rounds)
        self.reward = torch.zeros(n, device=device) if reward is None else reward
        self.ended: dict[str, list[torch.Tensor]] = {k: [] for k in
                                                     ("reward", "trips", "queue", "failed")}
        self.frames = 0

    def add(self, td: TensorDictBase, live: torch.Tensor) -> None:
        nxt = td["next"]
        self.frames += int(live.sum())
        self.reward += nxt["reward"].squeeze(-1) * live
        end = nxt["done"].squeeze(-1) & live
        if bool(end.any()):
            self.ended["reward"].append(self.reward[end])
            self.ended["trips"].append(nxt["trips"].squeeze(-1)[end].float())
            self.ended["queue"].append(nxt["queue_ticks"].squeeze(-1)[end].float())
            self.ended["failed"].append(nxt["terminated"].squeeze(-1)[end].float())
            self.reward = self.reward.masked_fill(end, 0.0)

    def summary(self) -> dict[str, float]:
        if not self.ended["trips"]:
            return {"episodes": 0}
        cat = {k: torch.cat(v) for k, v in self.ended.items()}
        return {"episodes": int(cat["trips"].numel()),
                "train/episode_reward": float(cat["reward"].mean()),
                "train/trips": float(cat["trips"].mean()),
                "train/queue_ticks": float(cat["queue"].mean()),
                "train/failures": float(cat["failed"].mean())}


class LoopState:
    """Where the next round starts when episodes run across rounds: the root tensordict of
    the next step and each site's running episode reward (a checkpoint component)."""

    def __init__(self, trainer: Trainer) -> None:
        self.trainer = trainer

    def state_dict(self) -> dict[str, Any]:
        t = self.trainer
        if t._next is None:
            return {"present": False}
        return {"present": True, "reward": t._episode_reward.clone(),
                "next": {k: v.clone() for k, v in
                         t._next.flatten_keys(".").to_dict().items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        t = self.trainer
        if not state["present"]:
            t._next, t._episode_reward = None, None
            return
        dev = t.device
        t._episode_reward = state["reward"].to(dev)
        t._next = TensorDict({k: v.to(dev) for k, v in state["next"].items()},
                             batch_size=t.env.batch_size, device=dev).unflatten_keys(".")


class Trainer:
    """Setup stages: environment, learner, evaluation, monitoring, checkpoint; then :meth:`run`.

    Trains the run ``spec`` (``self.cfg``) in ``run_dir``; publishes its policy to
    ``publish_dir`` (by default ``spec.train.out_dir``; the train command passes
    :func:`~fleet_torchrl.training.publish.publish_dir`); ``resume``: continue from the
    checkpoint in ``run_dir``."""

    def __init__(self, spec: RunSpec, run_dir: str | Path,
                 publish_dir: str | Path | None = None, resume: bool = False) -> None:
        if not isinstance(spec, RunSpec):
            raise TypeError(f"Trainer takes a RunSpec (RunSpec.of(config)), not "
                            f"{type(spec).__name__}")
        self.spec = get_agent(spec.agent.name)
        if not self.spec.trainable:
            raise ValueError(f"agent.name={spec.agent.name!r} is not trainable: use one of "
                             + ", ".join(_trainable_names()))
        publish_dir = publish_dir if publish_dir is not None else spec.train.out_dir
        if not publish_dir:
            raise ValueError("a Trainer needs a publish folder: publish_dir, or train.out_dir "
                             "in its spec")
        cfg = self.cfg = spec
        self.resume = resume
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        hold_run_dir(self.run_dir)  # one process per run folder (released when run() ends)
        self.name = policy_name(cfg)
        self.out_dir = Path(publish_dir)
        self.device = torch.device(cfg.train.device)
        self.n_rounds = cfg.agent.training_rounds(cfg.train)
        self._say_budget()
        self.progress = Progress()
        self._next: TensorDictBase | None = None
        self._episode_reward: torch.Tensor | None = None
        self._collected = None  # the Collector of collect_round, built at its first round
        torch.manual_seed(cfg.seed)
        flush_denormals()  # weight decay drives dead units' weights subnormal: 10x slower
        self.setup_env()
        self.setup_learner()
        self.setup_evaluation()
        self.setup_monitor()
        self.setup_checkpoint()

    def _say_budget(self) -> None:
        """Say so when ``train.max_episodes`` is not what runs: the budget is whole rounds
        of ``agent.num_sites`` episodes, so ``train.max_episodes=1`` trains 256 episodes."""
        from ..agents.config import AgentConfig

        c = self.cfg
        if type(c.agent).training_rounds is not AgentConfig.training_rounds:
            return  # a learner with a budget of its own (generations, rounds)
        episodes = self.n_rounds * c.agent.num_sites
        if episodes != c.train.max_episodes:
            log.warning("train.max_episodes=%d is not a multiple of agent.num_sites=%d: "
                        "training runs %d round(s) = %d episodes", c.train.max_episodes,
                        c.agent.num_sites, self.n_rounds, episodes)

    # ------------------------------------------------------------------ setup stages
    def setup_env(self) -> None:
        c = self.cfg
        self.env = FleetChargingEnv(site=c.site, encoding=c.state.name,
                                    num_sites=c.agent.num_sites, mdp=c.mdp, seed=c.seed,
                                    device=self.device)

    def setup_learner(self) -> None:
        c, env = self.cfg, self.env
        self.learner = self.spec.make_learner(LearnerContext(
            agent=c.agent, network=c.network, mdp=c.mdp, site=c.site, state=c.state.name,
            seed=c.seed, rounds=self.n_rounds, device=env.device,
            n_obs=env.observation_spec["observation"].shape[-1], action_spec=env.action_spec,
            env=env))
        self.best_policy = copy.deepcopy(self.policy()).cpu()

    def setup_evaluation(self) -> None:
        t = self.cfg.train
        self.eval_args = dict(site_cfg=self.cfg.site, n_sims=t.eval_sims, ticks=t.eval_ticks,
                              seed=t.eval_seed, device=t.device)
        self.rule_eval = evaluate_policy(RulePolicy(), **self.eval_args)
        if self.cfg.train.select in ("robust", "guarded"):  # every stratum's reference
            self.heuristic_eval = evaluate_policy(HeuristicPolicy(), **self.eval_args)
            self.strata = site_strata(self.cfg.site, t.eval_sims, t.eval_seed)

    def setup_monitor(self) -> None:
        self.monitor = Monitor(self.run_dir / "tb" if self.cfg.train.tensorboard else None)

    def setup_checkpoint(self) -> None:
        from torchrl.checkpoint import Checkpoint, GlobalRNGState

        self.checkpoint = Checkpoint(format="archive", learner=self.learner,
                                     best_policy=self.best_policy, env=self.env,
                                     loop=LoopState(self), rng=GlobalRNGState(),
                                     progress=self.progress)
        for name, component in self.learner.checkpoint_components().items():
            self.checkpoint.register(name, component)
        self.checkpoint_path = self.run_dir / CHECKPOINT

    # ------------------------------------------------------------------ helpers
    def policy(self) -> Policy:
        pol = self.learner.policy()
        pol.name = self.name
        return pol

    def save_checkpoint(self) -> None:
        self.checkpoint.save(self.checkpoint_path,
                             metadata={"run": self.name,
                                       "config": training_fingerprint(self.cfg)})

    def load_checkpoint(self) -> bool:
        from torchrl.checkpoint import CheckpointError

        check_resumable(self.checkpoint_path, self.cfg)
        try:
            self.checkpoint.load(self.checkpoint_path, map_location=self.device)
        except (CheckpointError, *UNREADABLE) as e:
            raise ValueError(f"cannot resume from {self.checkpoint_path}: {e}") from None
        return True

    # ------------------------------------------------------------------ one round
    def play_round(self) -> dict[str, float]:
        """One round of the learner in the environment (see the module docstring)."""
        env, learner = self.env, self.learner
        learner.start_round(self.progress.round)
        steps = learner.steps_per_round
        if steps == 0:  # a learner that simulates its own sites (direct policy search)
            out = {"episodes": 0, **learner.update()}
            out["frames"] = int(out.get("frames", 0))
            out[learner.exploration_tag] = learner.exploration()
            return out
        if steps is not None and learner.collects:  # through TorchRL's Collector
            return self.collect_round()
        fresh = steps is None or learner.reset_each_round or self._next is None
        td = env.reset() if fresh else self._next
        live = torch.ones(env.num_sites, dtype=torch.bool, device=self.device)
        stats = EpisodeStats(env.num_sites, self.device,
                             None if fresh else self._episode_reward)
        t = 0
        while (steps is None and bool(live.any())) or (steps is not None and t < steps):
            td = learner.act(td)
            if steps is None:  # the sites whose episode is over stay as they are
                td = env.step(td.set("_step", live))
                root = env.step_mdp(td)
            else:
                td, root = env.step_and_maybe_reset(td)
            learner.observe(td, live & ~td["next", "truncated"].squeeze(-1))
            stats.add(td, live)
            if steps is None:
                live = live & ~td["next", "done"].squeeze(-1)
            td = root
            t += 1
        self._next = td  # where the next round goes on when episodes run across rounds
        return self._finish_round(stats)

    def collect_round(self) -> dict[str, float]:
        """A round of ``steps_per_round`` steps collected by TorchRL's ``Collector``
        (:mod:`fleet_torchrl.training.collect`): the steps and numbers of :meth:`play_round`'s
        own loop, and the same checkpoint (:class:`LoopState`)."""
        from .collect import CollectedRounds

        learner = self.learner
        fresh = learner.reset_each_round or self._next is None
        if self._collected is None:  # built after any checkpoint was loaded
            self._collected = CollectedRounds(self.env, learner, None if fresh else self._next)
        stats = EpisodeStats(self.env.num_sites, self.device,
                             None if fresh else self._episode_reward)
        self._collected.play(stats, fresh)
        self._next = self._collected.next_root  # where the next round goes on
        return self._finish_round(stats)

    def _finish_round(self, stats: EpisodeStats) -> dict[str, float]:
        """A round's scalars once its steps are played: the episodes' summary, the learner's
        update, frames and exploration; the episodes' running reward carries over."""
        learner = self.learner
        self._episode_reward = stats.reward
        out = stats.summary()
        out.update(learner.update())
        out["frames"] = stats.frames
        out[learner.exploration_tag] = learner.exploration()
        return out

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, step: int) -> EvalEntry:
        pol, c = self.policy(), self.cfg
        self.check_finite(pol)
        res = evaluate_policy(pol, name=self.name, **self.eval_args)
        gain = gain_over(res, self.rule_eval)["gain_pct"]
        p = self.progress
        worst = None
        if c.train.select == "robust":
            worst, where = worst_stratum_gain(res, self.heuristic_eval, self.strata)
            self.monitor.scalars({"eval/worst_stratum_gain_vs_heuristic_pct": worst}, step)
            log.info("round %d: worst stratum %s, %+.3f %% vs the heuristic", self.progress.round,
                     where, worst)
        below: list[str] = []
        if c.train.select == "guarded":
            below = strata_below(res, self.heuristic_eval, self.strata)
            self.monitor.scalars({"eval/strata_below_heuristic": len(below)}, step)
            if below:
                log.info("round %d: significantly below the heuristic in %s (ranks below "
                         "every snapshot that is not)", p.round, ", ".join(below))
        score = selection_score(c.train.select, c.agent.objective(c.mdp), res, worst, below)
        improved = p.is_better(res["failure_rate"], score)
        if improved:
            p.best, p.best_round, p.evals_since_best = ((res["failure_rate"], score),
                                                        p.round, 0)
            self.best_policy.load_state_dict({k: v.detach().cpu()
                                              for k, v in pol.state_dict().items()})
            self.save_best()
        else:
            p.evals_since_best += 1
        entry = EvalEntry(round=p.round, frames=p.frames, trips=res["trips_mean"],
                          queue=res["queue_mean"], failure_rate=res["failure_rate"],
                          gain_pct=gain, wall_s=p.wall_s)
        p.history.append(entry)
        log.info("round %d: eval %.1f trips (%+.2f %% vs rule), queue %.1f, failure rate %.3f%s",
                 p.round, entry.trips, gain, entry.queue, entry.failure_rate,
                 " (new best)" if improved else "")
        self.monitor.scalars({"eval/trips": res["trips_mean"], "eval/queue": res["queue_mean"],
                              "eval/failure_rate": res["failure_rate"],
                              "eval/gain_over_rule_pct": gain,
                              "eval/best_trips": p.best_entry().trips},
                             step)
        if improved and pol.encoding == "partial" and self.monitor.enabled:
            # the map of each new best policy (drawing one takes about a second)
            import matplotlib.pyplot as plt

            fig = plot_policy_map(pol, title=f"{self.name}, round {p.round}")
            self.monitor.figure("policy_map/best", fig, step)
            plt.close(fig)
        return entry

    def check_finite(self, pol: Policy) -> None:
        """Stop a training whose policy's weights hold NaN or inf (an overflowing reward, a
        learning rate too large): its evaluations would rank garbage and its best snapshot
        could be published. Raises ``ValueError`` (one line: the commands' exit code 2);
        nothing is published, the checkpoint of the last good round stays."""
        bad = first_non_finite(pol.state_dict())
        if bad is not None:
            raise ValueError(
                f"training {self.name} diverged by round {self.progress.round}: the policy's "
                f"weights hold NaN or inf ({bad}); nothing is published. Lower the rewards' "
                "scale (mdp.p_f, mdp.p_q, agent.reward_scale) or the learning rate")

    def save_best(self, path: Path | None = None) -> str:
        """Write the best policy so far (default: into the run's own folder); returns the
        SHA-256 of the file written."""
        pol = self.best_policy
        pol.encoding = self.cfg.state.name
        return save_policy(path or self.run_dir / POLICY_FILE, pol, self.cfg.agent.name,
                           meta=run_info(self.cfg, seed=self.cfg.seed))[1]

    def promote(self, summary: dict[str, Any]) -> dict[str, Any]:
        """At the successful end of a run: publish the best policy to ``out_dir``
        (``results/policies/<name>/seed<s>/`` by default) and its summary beside it, each
        written atomically; the summary records the policy file's hash, so a reader can tell
        a matching pair (``experiments.table.reusable``) from one left by a killed or a
        concurrent run. While a run trains, ``out_dir`` is never touched.

        Nothing is published (``published: false`` in the run folder's summary, one log
        line saying why; the policy stays in the run folder) when the best policy failed
        sites and ``out_dir`` is the default one, or when ``out_dir`` came to hold another
        policy while this run trained (checked under :func:`~fleet_torchrl.training.
        publish.publish_lock`; ``train.overwrite=true`` replaces it)."""
        from .publish import check_publish, publish_lock

        if self.cfg.train.defer != "none":
            summary = {**summary, "deferral": self.calibrate_deferral()}
        rate = (summary.get("best") or {}).get("failure_rate", 0.0)
        if rate > 0 and not self.cfg.train.out_dir:
            return self.keep_in_run_dir(summary, f"its best policy failed {rate:.1%} of the "
                                        "evaluation sites")
        with publish_lock(self.out_dir):
            try:
                check_publish(self.cfg, self.out_dir, self.run_dir, self.resume)
            except ValueError:
                return self.keep_in_run_dir(summary, "another run published a policy there "
                                            "while this one trained (train.overwrite=true "
                                            "replaces it)")
            summary = {**summary, "published": True,
                       "policy_sha256": self.save_best(self.out_dir / POLICY_FILE)}
            write_json(self.run_dir / "train_summary.json", summary)
            write_json(self.out_dir / "train_summary.json", summary)
        return summary

    def keep_in_run_dir(self, summary: dict[str, Any], why: str) -> dict[str, Any]:
        """End a run without publishing: its best policy and summary stay in the run folder,
        and one log line says so and why."""
        path = self.run_dir / POLICY_FILE
        summary = {**summary, "published": False, "policy": str(path),
                   "policy_sha256": self.save_best(path)}
        write_json(self.run_dir / "train_summary.json", summary)
        log.warning("%s: not published to %s: %s; the policy stays in %s", self.name,
                    self.out_dir, why, path)
        return summary

    def calibrate_deferral(self) -> dict[str, Any]:
        """Set the best snapshot's deferral margin to the heuristic, calibrated on validation
        sites (:mod:`fleet_torchrl.training.deferral`); returns the calibration's record."""
        from .deferral import calibrate_deferral

        t = self.cfg.train
        self.best_policy.set_defer_margin(0.0)  # calibrated from the plain student
        rec = calibrate_deferral(self.best_policy, self.cfg.site, list(t.defer_margins),
                                 t.defer_sims, t.defer_ticks, t.eval_seed, t.defer_points,
                                 t.device)
        self.best_policy.set_defer_margin(rec["margin"])
        self.monitor.scalars({"eval/defer_margin": rec["margin"]}, self.progress.frames)
        log.info("deferral to the heuristic: margin %g (%s)", rec["margin"],
                 "no validation point below it" if rec["clear"] else
                 "below it at " + ", ".join(next(c["below"] for c in rec["candidates"]
                                                 if c["margin"] == rec["margin"])))
        return rec

    # ------------------------------------------------------------------ main loop
    def run(self, stop_after_rounds: int | None = None) -> dict[str, Any]:
        """Train to the end (or for ``stop_after_rounds`` more rounds, for tests of resume)."""
        c = self.cfg
        resumed = self.resume and self.load_checkpoint()
        p = self.progress
        bar = None
        redirect = contextlib.nullcontext()
        if c.train.progress:
            from tqdm.auto import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            bar = tqdm(total=self.n_rounds, initial=p.round, desc=f"train {self.name}",
                       unit="round")
            redirect = logging_redirect_tqdm()  # log lines above the bar, not through it
        try:
            with redirect:
                return self._run_rounds(stop_after_rounds, resumed, bar)
        finally:
            release_run_dir(self.run_dir)

    def _run_rounds(self, stop_after_rounds: int | None, resumed: bool, bar: Any
                    ) -> dict[str, Any]:
        c, p = self.cfg, self.progress
        t_start = time.perf_counter() - p.wall_s
        rounds_done = 0
        if p.round == 0 and not p.history and self.learner.evaluate_start:
            self.evaluate(0)  # the start policy competes for the best snapshot
        while p.round < self.n_rounds and not p.stopped_early:
            if stop_after_rounds is not None and rounds_done >= stop_after_rounds:
                break
            t0 = time.perf_counter()
            stats = self.play_round()
            dt = time.perf_counter() - t0
            p.round += 1
            rounds_done += 1
            n_frames = stats.pop("frames")
            p.frames += n_frames
            p.episodes += stats.pop("episodes")
            p.wall_s = time.perf_counter() - t_start
            step = p.frames
            self.monitor.scalars({**stats, "train/episodes": p.episodes,
                                  "time/fps": n_frames / max(dt, 1e-9),
                                  "time/wall_s": p.wall_s, "time/round_s": dt}, step)
            postfix = {"frames": step, self.learner.exploration_tag.split("/")[-1]:
                       f"{self.learner.exploration():.2f}"}
            if p.round % c.train.eval_every == 0 or p.round == self.n_rounds:
                entry = self.evaluate(step)
                postfix["eval_trips"] = f"{entry.trips:.1f}"
                if c.train.patience and p.evals_since_best >= c.train.patience:
                    p.stopped_early = True
            if p.best is not None:
                postfix["best"] = f"{p.best_entry().trips:.1f}"
            if bar is not None:
                bar.update(1)
                bar.set_postfix(postfix)
            if p.round % c.train.checkpoint_every == 0:
                self.save_checkpoint()
        if bar is not None:
            bar.close()
        finished = p.round >= self.n_rounds or p.stopped_early
        if finished and not p.history:
            self.evaluate(p.frames)
        self.save_checkpoint()
        summary = self.summary(resumed)
        if finished:
            summary = self.promote(summary)
            best = summary["best"]
            self.monitor.hparams(training_hparams(c),
                                 {"hparam/eval_trips": best["trips"],
                                  "hparam/gain_pct": best["gain_pct"],
                                  "hparam/failure_rate": best["failure_rate"]})
        self.monitor.close()
        return summary

    def summary(self, resumed: bool) -> dict[str, Any]:
        p = self.progress
        best = p.best_entry()
        return {"name": self.name, "rounds": p.round, "frames": p.frames,
                "episodes": p.episodes, "wall_s": p.wall_s, "resumed": resumed,
                "stopped_early": p.stopped_early, "best": asdict(best) if best else None,
                "rule_on_eval_set": {k: self.rule_eval[k] for k in ("trips_mean", "queue_mean",
                                                                    "failure_rate")},
                "policy": str(self.out_dir / POLICY_FILE), "run_dir": str(self.run_dir),
                "history": [asdict(h) for h in p.history],
                "fingerprint": result_fingerprint(self.cfg),
                "meta": run_info(self.cfg, seed=self.cfg.seed)}


def _trainable_names() -> list[str]:
    from ..agents.registry import AGENTS

    return [name for name, spec in AGENTS.items() if spec.trainable]
