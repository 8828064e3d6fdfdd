"""Throughput benchmark: ``make bench`` (``python -m fleet_torchrl.bench --help``).

Measures, for batch sizes ``B`` in {1, 64, 1024, 8192} (median of ``--repeats`` runs):

* ``sim``: bare :meth:`Site.tick` calls (closures pre-drawn), ticks/s and site-ticks/s;
* ``eval``: the evaluation loop with the rule policy deciding in the loop, site-ticks/s;
* ``env``: TorchRL environment steps (decision epochs) per second with the rule policy;

and the wall time of the thesis protocol for one policy (1000 sims x 10 000 ticks).
Results print as Markdown (paste into docs/BENCHMARKS.md) and, with ``--out``, as JSON.
"""

from __future__ import annotations

import argparse
import platform

import torch

from .agents import RulePolicy
from .evaluation import simulate
from .experiments.bench import bench_env, bench_eval, bench_sim, median_time
from .sim import SiteConfig
from .utils.runinfo import package_versions, write_json


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    p.add_argument("--site-ticks", type=float, default=4e6,
                   help="site-ticks per measurement (ticks = site_ticks / B, 200..10000)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--device", default="cpu")
    p.add_argument("--skip-protocol", action="store_true")
    p.add_argument("--out", default=None, help="also write the figures as JSON")
    a = p.parse_args(argv)

    rows = []
    for b in a.batches:
        ticks = int(min(10_000, max(200, a.site_ticks / b)))
        t_sim = bench_sim(b, ticks, a.repeats, a.device)
        t_eval = bench_eval(b, ticks, a.repeats, a.device)
        steps = 50 if b >= 1024 else 200
        t_env = bench_env(b, steps, max(1, a.repeats // 2), a.device)
        rows.append({"B": b, "ticks": ticks, "sim_ticks_per_s": ticks / t_sim,
                     "sim_site_ticks_per_s": b * ticks / t_sim,
                     "eval_site_ticks_per_s": b * ticks / t_eval,
                     "env_steps_per_s": steps / t_env,
                     "env_site_steps_per_s": b * steps / t_env})
        r = rows[-1]
        print(f"B={b:5d}  sim {r['sim_ticks_per_s']:9.0f} ticks/s "
              f"{r['sim_site_ticks_per_s'] / 1e6:7.2f} M site-ticks/s | eval "
              f"{r['eval_site_ticks_per_s'] / 1e6:6.2f} M site-ticks/s | env "
              f"{r['env_site_steps_per_s']:9.0f} site-steps/s", flush=True)
    result = {"machine": {"platform": platform.platform(), "cpus": torch.get_num_threads(),
                          "device": a.device}, "packages": package_versions(), "rows": rows}
    if not a.skip_protocol:
        t = median_time(lambda: simulate(RulePolicy(), SiteConfig(), 1000, 10_000, 0, a.device),
                         max(1, a.repeats // 2 + 1))
        result["protocol_1000x10000_s"] = t
        print(f"thesis protocol (rule, 1000 sims x 10 000 ticks): {t:.2f} s "
              f"({1e7 / t / 1e6:.2f} M site-ticks/s)")
    print("\n| B | sim ticks/s | sim M site-ticks/s | eval M site-ticks/s (rule in loop) "
          "| env site-steps/s |\n|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['B']} | {r['sim_ticks_per_s']:.0f} | {r['sim_site_ticks_per_s'] / 1e6:.2f} | "
              f"{r['eval_site_ticks_per_s'] / 1e6:.2f} | {r['env_site_steps_per_s']:.0f} |")
    if a.out:
        write_json(a.out, result)
    return result


if __name__ == "__main__":
    main()
