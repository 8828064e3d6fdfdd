"""Environment collection of two source trees, A/B in one sitting (docs/BENCHMARKS.md); a
development tool of this repository, not part of the package.

    python benchmarks/bench_ab.py OLD_TREE NEW_TREE [ROUNDS] [B] [CASE]

Each round runs, in a fresh process per tree (its ``PYTHONPATH`` the tree, alternating the
trees so that a drift of the machine hits both), one case, and prints decisions per second;
then the medians over the rounds. Cases:

* ``env`` (default): the rule's rollout of 50 steps at ``B`` sites (median of 5 after a
  warm-up) and the numpy reference's env steps, with their ratio;
* ``planner``: the rollout planner (32 futures of 200 ticks) over a network base of the
  generalist's shape (``partial_all_site``, 3 x 128, deferral), weights drawn from seed 0, on
  ``B`` sites at ``N_V`` = 4 for 500 ticks, one thread (median of 3 after a warm-up): the
  planner's decisions per second, what the distilled planner over a network teacher and the
  sweeps' planner rows over networks spend their time on.

An old tree is any checkout of this project with ``fleet_torchrl/experiments/bench.py``
(``git worktree add /tmp/old <commit>``).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys

_SNIPPET = """
import json
from fleet_torchrl.experiments.bench import bench_env, bench_env_reference
b, steps = {b}, 50
bench_env(b, steps, 1, "cpu", use_fused=True)
t = bench_env(b, steps, 5, "cpu", use_fused=True)
r = bench_env_reference(b, steps, 3)
print(json.dumps({{"env": b * steps / t, "ref": b * steps / r}}))
"""


_PLANNER = """
import json, statistics, time
import torch
from fleet_torchrl.agents.imitation import ImitationPolicy
from fleet_torchrl.agents.planner import PlannerPolicy
from fleet_torchrl.env.encodings import get_encoding
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import Site, SiteConfig
torch.set_num_threads(1)
torch.manual_seed(0)
cfg = SiteConfig(n_vehicles=4)
net = ImitationPolicy(get_encoding("partial_all_site").size(Site(cfg)), "partial_all_site",
                      defer_margin=0.3)
pl = PlannerPolicy(net, rollouts=32, horizon=200)
simulate(pl, cfg, 4, 50, 0)
times = []
for _ in range(3):
    pl.stats["decisions"] = 0
    t0 = time.perf_counter()
    simulate(pl, cfg, {b}, 500, 0)
    times.append(time.perf_counter() - t0)
print(json.dumps({{"env": pl.stats["decisions"] / statistics.median(times)}}))
"""
CASES = {"env": _SNIPPET, "planner": _PLANNER}


def run_tree(root: str, b: int, case: str = "env") -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": os.path.abspath(root)}
    r = subprocess.run([sys.executable, "-c", CASES[case].format(b=b)], capture_output=True,
                       text=True, env=env, cwd=root, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    trees, rounds = args[:2], int(args[2]) if len(args) > 2 else 5
    case = args[4] if len(args) > 4 else "env"
    if case not in CASES:
        print(f"case {case!r} is unknown: allowed one of {', '.join(CASES)}", file=sys.stderr)
        return 2
    b = int(args[3]) if len(args) > 3 else (1024 if case == "env" else 50)
    out: list[list[dict[str, float]]] = [[], []]
    for _ in range(rounds):
        for tree, got in zip(trees, out, strict=True):
            d = run_tree(tree, b, case)
            got.append(d)
            ref = (f", numpy reference {d['ref']:.0f} ({d['env'] / d['ref']:.2f}x)"
                   if "ref" in d else "")
            print(f"{tree}: {d['env']:.0f} decisions/s{ref}", flush=True)
    for tree, v in zip(trees, out, strict=True):
        ratio = (f", median ratio {statistics.median(x['env'] / x['ref'] for x in v):.2f}x"
                 if "ref" in v[0] else "")
        print(f"{tree}: median {statistics.median(x['env'] for x in v):.0f} decisions/s{ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
