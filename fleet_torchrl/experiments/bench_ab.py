"""Environment collection of two source trees, A/B in one sitting (docs/BENCHMARKS.md).

    python -m fleet_torchrl.experiments.bench_ab OLD_TREE NEW_TREE [ROUNDS] [B]

Each round runs, in a fresh process per tree (its ``PYTHONPATH`` the tree, alternating the
trees so that a drift of the machine hits both), the rule's rollout of 50 steps at ``B`` sites
(median of 5 after a warm-up) and the numpy reference's env steps, and prints decisions per
second and their ratio; then the medians over the rounds. An old tree is any checkout of this
project with ``fleet_torchrl/experiments/bench.py`` (``git worktree add /tmp/old <commit>``).
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


def run_tree(root: str, b: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": os.path.abspath(root)}
    r = subprocess.run([sys.executable, "-c", _SNIPPET.format(b=b)], capture_output=True,
                       text=True, env=env, cwd=root, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    trees, rounds = args[:2], int(args[2]) if len(args) > 2 else 5
    b = int(args[3]) if len(args) > 3 else 1024
    out: list[list[dict[str, float]]] = [[], []]
    for _ in range(rounds):
        for tree, got in zip(trees, out, strict=True):
            d = run_tree(tree, b)
            got.append(d)
            print(f"{tree}: {d['env']:.0f} decisions/s, numpy reference {d['ref']:.0f} "
                  f"({d['env'] / d['ref']:.2f}x)", flush=True)
    for tree, v in zip(trees, out, strict=True):
        print(f"{tree}: median {statistics.median(x['env'] for x in v):.0f} decisions/s, "
              f"median ratio {statistics.median(x['env'] / x['ref'] for x in v):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
