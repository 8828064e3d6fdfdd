"""A sweep point's candidates: what each row is, how it is built or trained, and how the
point's pick set ranks them (:mod:`fleet_torchrl.experiments.sweeps` runs the point).

The trainings arrive resolved: the sweep command composes each search, specialist and the
distilled recipe into a :class:`~fleet_torchrl.training.spec.RunSpec` on the point's site,
and the planner's settings, at its boundary (:class:`PointSettings`); nothing here composes
a config.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..agents import AGENTS, load_policy_file
from ..agents.base import GuardedPolicy, Policy
from ..agents.config import BASELINE_BASES
from ..agents.planner import PlannerPolicy
from ..agents.policy_files import policy_file_sha256
from ..agents.registry import base_policy
from ..agents.search import SearchPolicy, cell_centres, clone_policy, threshold_start
from ..evaluation import evaluate_policy
from ..evaluation.cache import EvalCache
from ..evaluation.config import EvalConfig
from ..sim import SiteConfig
from ..store import load_policies, saved_policy_path
from ..training import Trainer, result_fingerprint
from ..training.spec import RunSpec
from ..utils.checks import ConfigError
from ..utils.runinfo import read_json
from .config import SweepConfig, TableConfig
from .rows import Candidate
from .sweep_keys import digest, seed_paths
from .table import reusable

BEST_KNOWN = "best_known"  # the row of the best policy known at the point
PLANNER = "planner"  # the rollout planner over the heuristic
PLANNER_SEARCH = "planner_search"  # the rollout planner over the point's best search
DISTILLED = "specialist_distilled"  # the point's best planner distilled on its site

Key = tuple[str, int | None]  # a row and its seed (None: a single policy)


@dataclass
class PointSettings:
    """Everything a sweep point computes with, resolved at the command boundary: the sweep,
    the evaluation, the point's site, where the saved policies are, the run specs of its
    trainings on that site (``searches`` ``{row: spec}``; ``specialists`` ``{row: {seed:
    spec}}``, the distilled row's among them; ``distil_states`` ``{state: {seed: spec}}``:
    the distilled recipe reading another state), the planner's settings, the pick set's
    seed, and the run's provenance (``meta``)."""

    sweep: SweepConfig
    eval: EvalConfig
    site: SiteConfig
    table: TableConfig
    searches: dict[str, RunSpec]
    specialists: dict[str, dict[int, RunSpec]]
    planner: Any  # PlannerAgentConfig
    pick_seed: int
    distil_states: dict[str, dict[int, RunSpec]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class Pool:
    """The point's rows as they are built: every row's policies ``{(row, seed): policy}``,
    policy files (a teacher's base), pick-set keys and training summaries."""

    policies: dict[str, dict[int | None, Policy]] = field(default_factory=dict)
    files: dict[Key, Path] = field(default_factory=dict)
    keys: dict[Key, tuple[float, float]] = field(default_factory=dict)
    summaries: dict[str, Any] = field(default_factory=dict)
    planner_bases: dict[str, str] = field(default_factory=dict)  # base row -> planner row


def plan_candidates(p: PointSettings) -> list[Candidate]:
    """The point's rows, in order: the policies of ``sweep.policies`` (baselines by name,
    saved learned policies by their seeds' files), its searches and its specialists (trained
    at the point from their specs); the planner rows follow once the pick set is known."""
    out = []
    for name in p.sweep.policies:
        files = seed_paths(p.table, name)
        out.append(Candidate(name, "learned", files=dict(files)) if files
                   else Candidate(name, "baseline"))
    out += [Candidate(k, "search", specs={None: s}) for k, s in p.searches.items()]
    out += [Candidate(row, "specialist", specs=dict(runs))
            for row, runs in p.specialists.items()]
    return out


def load_saved(p: PointSettings, candidates: list[Candidate], pool: Pool) -> None:
    """The baselines and saved learned policies (guarded: ``sweep.guard``)."""
    names = [c.name for c in candidates if c.kind == "baseline"]
    for name, pol in load_policies(p.table.policies_dir, names, p.eval.device,
                                   p.table.follow_symlinks).items():
        pool.policies[name] = {None: pol}
    for c in candidates:
        if c.kind == "learned":
            pool.policies[c.name] = {s: guard(p, _named(load_policy_file(f, p.eval.device),
                                                        c.name))
                                     for s, f in c.files.items()}
            pool.files.update({(c.name, s): f for s, f in c.files.items()})


def guard(p: PointSettings, pol: Policy) -> Policy:
    return GuardedPolicy(pol) if p.sweep.guard else pol


def make_planner(agent: Any, base: Policy) -> PlannerPolicy:
    """The sweep's planner (``agent``: its settings) over ``base`` (and the parallel
    rollout's other bases, if its settings name any)."""
    return PlannerPolicy.from_config(agent, base, [base_policy(b) for b in agent.bases])


def on_pick_set(p: PointSettings, pol: Policy, cache: EvalCache | None = None
                ) -> tuple[float, float]:
    """``(failure rate, -mean trips)`` of a policy on the point's pick set: the searches'
    selection seed (``train.eval_seed``, apart from the evaluation's sites) with
    ``sweep.pick_sims`` x ``sweep.pick_ticks``; lower is better."""
    n, ticks, seed = p.sweep.pick_sims, p.sweep.pick_ticks, p.pick_seed
    res = (cache or EvalCache(None)).evaluate(
        pol, p.site, n, ticks, seed,
        lambda: evaluate_policy(pol, p.site, n, ticks, seed, p.eval.device))
    return res["failure_rate"], -res["trips_mean"]


def best_of(keys: dict[Any, tuple[float, float]]) -> Any:
    """The name with the best pick-set key (fewer failures, then more trips); on a tie the
    first in order (policies before searches before planners)."""
    return min(keys, key=lambda n: keys[n])


def is_learned(name: str) -> bool:
    """A learned row: a default-site learner or a specialist (not a baseline, a search, a
    planner or best_known)."""
    return (name not in AGENTS and not name.startswith(("search", PLANNER, BEST_KNOWN))) or \
        name.startswith("specialist")


def class_start(spec: RunSpec, pol: Policy) -> SearchPolicy:
    """What a search of ``spec``'s class starts from when started from ``pol``: its action
    table (table class), its thresholds (threshold class; the heuristic's for a policy
    without any), a network cloned from it (mlp class)."""
    a = spec.agent
    start = SearchPolicy(a.policy_class, a.hidden, a.depth, a.tc_bins)
    if a.policy_class == "table":
        start.charge.copy_(pol(cell_centres(a.tc_bins).to(_device(pol))).long().cpu())
    elif a.policy_class == "threshold":
        start.theta.copy_(threshold_start(pol))
    else:
        start.theta.copy_(clone_policy(pol.cpu(), start.sizes, spec.seed, spec.site))
    return start


def _device(pol: Policy):
    for t in (*pol.buffers(), *pol.parameters()):
        return t.device
    return "cpu"


def search_start(p: PointSettings, spec: RunSpec, policies: dict[str, Policy],
                 trained: dict[str, Path] | None = None) -> str:
    """The ``agent.init`` of a point's search: of the rule, the heuristic and the
    ``partial``-state policies of the point, the one whose start of the search (what its
    class can represent of it) does best on the point's pick set, as a baseline's name or a
    saved policy's path (``trained``: the policy files of the point's own earlier searches,
    which are not under ``table.policies_dir``)."""
    best: tuple[tuple[float, float], str] | None = None
    for name, pol in policies.items():
        if pol.encoding != "partial":
            continue
        key = on_pick_set(p, class_start(spec, pol))
        if best is None or key < best[0]:
            best = (key, name)
    if best is None:
        return spec.agent.init
    agent = AGENTS.get(best[1])
    if agent is not None and not agent.trainable:
        return best[1]
    if trained and best[1] in trained:
        return str(trained[best[1]])
    return str(saved_policy_path(p.table.policies_dir, best[1], p.table.follow_symlinks))


def point_training(p: PointSettings, spec: RunSpec, label: str
                   ) -> tuple[Policy, dict[str, Any], RunSpec]:
    """A policy trained on the point's site with ``spec`` (a search or a specialist), reused
    when its settings (and start) match; its summary and the spec as it ran (its
    ``train.out_dir`` the cache folder)."""
    start: Any = policy_file_sha256(getattr(spec.agent, "init", None))
    teacher = policy_file_sha256(getattr(getattr(spec.agent, "expert", None), "base", None))
    if teacher is not None:  # a teacher over a saved policy: its content, not just its path
        start = [start, teacher]
    out = Path(p.sweep.search_dir) / label / digest([result_fingerprint(spec), start])
    # the sweep's own folder: a policy there is a killed run's
    spec = replace(spec, train=replace(spec.train, out_dir=str(out), overwrite=True))
    if not reusable(out, spec):
        print(f"[sweep] {label}: training -> {out}", flush=True)
        Trainer(spec, out / "run").run()
    else:
        print(f"[sweep] {label}: reusing {out}", flush=True)
    return load_policy_file(out), read_json(out / "train_summary.json"), spec


def search_base(p: PointSettings, pool: Pool) -> str | None:
    """The base of row ``planner_search`` (``sweep.planner_search``): the point's best search
    on the pick set, if it decides inside the kernel (rollouts as cheap as the heuristic's)
    and is better there than the heuristic (the ``planner`` row's base); else None."""
    if not (p.sweep.planner and p.sweep.planner_search):
        return None
    cands = {k: v for k, v in pool.keys.items() if k[0].startswith("search") and k[1] is None
             and pool.policies[k[0]][None].kernel_policy() is not None}
    if not cands:
        return None
    best = best_of(cands)
    heuristic = pool.keys.get(("heuristic", None))
    if heuristic is not None and not cands[best] < heuristic:
        return None
    return best[0]


def distil_base(keys: dict[Key, tuple[float, float]], planner_bases: dict[str, str]
                ) -> Key | None:
    """The base of the teacher of row ``specialist_distilled``, as ``(row, seed)``: the base
    of the point's last planner row (``planner_search``'s search, else the heuristic), unless
    another row (neither a planner row nor this row itself) beats every planner row on the
    pick set: then the best such row (the planner over a policy better than every planner
    we have is the better teacher; measured at ``T_C`` = 10, docs/TRAINING.md section 14).
    None: no planner rows (the teacher is then the planner over the heuristic)."""
    if not planner_bases:
        return None
    base = next(reversed(planner_bases))
    rows = {PLANNER, PLANNER_SEARCH, *planner_bases.values()}
    planners = {k: v for k, v in keys.items() if k[0] in rows}
    others = {k: v for k, v in keys.items() if k[0] not in rows and k[0] != DISTILLED}
    if others and planners and min(others.values()) < min(planners.values()):
        return best_of(others)
    return (base, None)


def distil_teacher(planner: Any, base: Key | None, files: dict[Key, Path]) -> Any:
    """The teacher of row ``specialist_distilled``: the sweep's planner settings
    (``planner``) over the row ``base`` (:func:`distil_base`), by its policy file (the
    heuristic by name)."""
    if base is None or base == ("heuristic", None):
        return replace(planner, base="heuristic")
    if base in files:
        return replace(planner, base=str(files[base]))
    if base[0] in AGENTS and not AGENTS[base[0]].trainable:
        if base[0] not in BASELINE_BASES:
            raise ConfigError(f"the distilled planner's base {base[0]!r} cannot be a "
                              f"planner's base (allowed {', '.join(BASELINE_BASES)} or a "
                              "policy file)")
        return replace(planner, base=base[0])
    raise ConfigError(f"the distilled planner's base {base[0]!r} has no policy file")


def distil_state(recipe_state: str, policies: dict[str, dict[int | None, Policy]],
                 base: Key | None) -> str | None:
    """The state the distilled student reads, where it differs from its recipe's
    (``recipe_state``): the state its teacher's base reads (a student needs what its
    teacher's base decides on: a DQN reading every node orders the vehicles in a way the
    ``partial`` state cannot show), if the imitation learner accepts it; None keeps the
    recipe's."""
    if base is None:
        return None
    enc = getattr(policies.get(base[0], {}).get(base[1]), "encoding", None)
    states = AGENTS["imitation"].states or ()
    return enc if enc != recipe_state and enc in states else None


def _named(pol: Policy, name: str) -> Policy:
    pol.name = name
    return pol


__all__ = ["BEST_KNOWN", "DISTILLED", "PLANNER", "PLANNER_SEARCH", "PointSettings", "Pool",
           "best_of", "class_start", "distil_base", "distil_state", "distil_teacher",
           "is_learned", "make_planner", "on_pick_set", "plan_candidates", "point_training",
           "search_base", "search_start"]
