"""Throughput benchmark: ``make bench`` (``fleet-bench``, ``python -m fleet_torchrl.bench``;
settings ``bench.*``, e.g. ``fleet-bench bench.repeats=3 bench.training=false``).

Measures, for batch sizes ``B`` in {1, 64, 1024, 8192} (median of ``bench.repeats`` runs):

* ``sim``: bare :meth:`Site.tick` calls (closures pre-drawn), ticks/s and site-ticks/s;
* ``eval``: the evaluation loop with the rule policy deciding in the loop, site-ticks/s;
* ``env``: TorchRL environment steps (decision epochs) per second with the rule policy;

``eval`` and ``env`` with the eager tick loop and with the compiled kernel (sim/kernel.py via
sim/fused.py; numba on every CPU core, or CUDA); ``kernel``: one kernel call with the rule
deciding inside it (site-ticks/s); and the wall time of the thesis protocol for one policy
(1000 sims x 10 000 ticks): eager, fused and the numpy reference, as ratios to the
reference, with the compile time apart; and the training throughput of every recipe
(``conf/recipes/``: what ``make table`` trains).
Results print as Markdown (paste into docs/BENCHMARKS.md) and, with ``bench.out``, as JSON.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config
    from .experiments.config import BenchConfig


# the groups the benchmark reads (the recipes it times, the table's policies their teachers
# plan over)
GROUPS = ("table", "recipes", "bench")


def run(cfg: Config) -> dict:
    """Every measurement of ``cfg.bench``; prints Markdown tables, returns the figures."""
    import platform

    import torch

    from .sim import fused
    from .utils.runinfo import package_versions, write_json

    a = cfg.bench
    has_fused = fused.available(a.device)
    rows = [measure_batch(a, b, has_fused) for b in a.batches]
    result = {"machine": {"platform": platform.platform(), "cpus": torch.get_num_threads(),
                          "device": a.device}, "packages": package_versions(), "rows": rows}
    if a.protocol:  # the protocol on the CPU
        result["protocol_1000x10000_s"] = measure_protocol(a)
    print_tables(result, has_fused)
    if a.training:
        result["training"] = measure_training(cfg)
    if a.out:
        write_json(a.out, result)
    return result


def measure_batch(a: BenchConfig, b: int, has_fused: bool) -> dict:
    """The row of batch size ``b``: the simulator, the evaluation loop, the environment (and
    their fused forms where the kernel runs, the kernel alone), printed as it is measured."""
    from .experiments.bench import (
        bench_env,
        bench_env_reference,
        bench_eval,
        bench_kernel,
        bench_sim,
    )

    ticks = int(min(10_000, max(200, a.site_ticks / b)))
    t_sim = bench_sim(b, ticks, a.repeats, a.device)
    t_eval = bench_eval(b, ticks, a.repeats, a.device, use_fused=False)
    steps = a.env_steps or (50 if b >= 1024 else 200)
    env_repeats = max(1, a.repeats // 2)
    t_env = bench_env(b, steps, env_repeats, a.device, use_fused=False)
    t_env_ref = bench_env_reference(b, steps, env_repeats)
    r = {"B": b, "ticks": ticks, "sim_ticks_per_s": ticks / t_sim,
         "sim_site_ticks_per_s": b * ticks / t_sim,
         "eval_site_ticks_per_s": b * ticks / t_eval,
         "env_steps_per_s": steps / t_env,
         "env_site_steps_per_s": b * steps / t_env,
         "env_reference_site_steps_per_s": b * steps / t_env_ref}
    if has_fused:
        t_eval_f = bench_eval(b, ticks, a.repeats, a.device, use_fused=True)
        t_env_f = bench_env(b, steps, env_repeats, a.device, use_fused=True)
        t_kernel = bench_kernel(b, ticks, a.repeats, a.device)
        r.update(eval_fused_site_ticks_per_s=b * ticks / t_eval_f,
                 env_fused_steps_per_s=steps / t_env_f,
                 env_fused_site_steps_per_s=b * steps / t_env_f,
                 kernel_site_ticks_per_s=b * ticks / t_kernel)
    fast = (f" (fused {r['eval_fused_site_ticks_per_s'] / 1e6:6.2f})" if has_fused else "",
            f" (fused {r['env_fused_site_steps_per_s']:9.0f})" if has_fused else "")
    print(f"B={b:5d}  numpy reference env {r['env_reference_site_steps_per_s']:9.0f} "
          "decisions/s", flush=True)
    print(f"B={b:5d}  sim {r['sim_ticks_per_s']:9.0f} ticks/s "
          f"{r['sim_site_ticks_per_s'] / 1e6:7.2f} M site-ticks/s | eval "
          f"{r['eval_site_ticks_per_s'] / 1e6:6.2f}{fast[0]} M site-ticks/s | env "
          f"{r['env_site_steps_per_s']:9.0f}{fast[1]} decisions/s", flush=True)
    return r


def measure_protocol(a: BenchConfig) -> dict:
    """The wall times of the thesis protocol (1000 sims x 10 000 ticks) on the CPU."""
    from .experiments.bench import bench_protocol

    t = bench_protocol(max(1, a.repeats // 2 + 1))
    ref = t["reference"]
    print(f"thesis protocol (rule, 1000 sims x 10 000 ticks, CPU): numpy reference "
          f"{ref:.2f} s | eager {t['eager']:.2f} s ({t['eager'] / ref:.3f} x reference) "
          f"| fused {t['fused']:.3f} s ({ref / t['fused']:.1f}x faster than the reference, "
          f"{t['eager'] / t['fused']:.1f}x than eager) | compile once "
          f"{t['compile']:.2f} s")
    return t


def print_tables(result: dict, has_fused: bool) -> None:
    """The Markdown tables of the batch rows and the protocol (docs/BENCHMARKS.md)."""
    print("\n| B | sim ticks/s | sim M site-ticks/s | eval M site-ticks/s (rule) "
          "eager / fused | kernel M site-ticks/s | env decisions/s numpy reference / eager / "
          "fused |\n|---:|---:|---:|---:|---:|---:|")
    for r in result["rows"]:
        ev_f = f"{r['eval_fused_site_ticks_per_s'] / 1e6:.2f}" if has_fused else "-"
        env_f = f"{r['env_fused_site_steps_per_s']:.0f}" if has_fused else "-"
        ker = f"{r['kernel_site_ticks_per_s'] / 1e6:.2f}" if has_fused else "-"
        print(f"| {r['B']} | {r['sim_ticks_per_s']:.0f} | {r['sim_site_ticks_per_s'] / 1e6:.2f} | "
              f"{r['eval_site_ticks_per_s'] / 1e6:.2f} / {ev_f} | {ker} | "
              f"{r['env_reference_site_steps_per_s']:.0f} / {r['env_site_steps_per_s']:.0f} / "
              f"{env_f} |")
    if "protocol_1000x10000_s" in result:
        t = result["protocol_1000x10000_s"]
        print("\n| thesis protocol (CPU) | wall s | x numpy reference |\n|---|---:|---:|")
        for k in ("reference", "eager", "fused_stepwise", "fused", "fused_randomized"):
            print(f"| {k} | {t[k]:.3f} | {t[k] / t['reference']:.3f} |")
        print(f"| fused: compile once | {t['compile']:.2f} | |")


def measure_training(cfg: Config) -> dict:
    """The training throughput of every recipe (``conf/recipes/``), printed as a table."""
    from .config import compose_config
    from .experiments.bench import bench_training
    from .training.spec import RunSpec

    specs = {n: RunSpec.of(compose_config([
        *r.overrides, *saved_teacher_bases(cfg, n), f"train.device={cfg.bench.device}",
        "train.progress=false", "train.tensorboard=false"])) for n, r in cfg.recipes.items()}
    tr = bench_training(specs)
    print("\n| learner (defaults) | sites | decisions/s | s per round |\n|---|---:|---:|---:|")
    for name, r in tr.items():
        print(f"| {name} | {r['sites']} | {r['decisions_per_s']:.0f} | {r['round_s']:.2f} |")
    return tr


def saved_teacher_bases(cfg: Config, name: str) -> list[str]:
    """A recipe's teacher bases (``Recipe.bases``: other recipes' policies) where the table
    has saved them all; else none (its teacher then plans over its own base only)."""
    from .agents.policy_files import POLICY_FILE
    from .experiments.table import recipe_seed_dir, teacher_bases

    if all((recipe_seed_dir(cfg, b, cfg.seed) / POLICY_FILE).is_file()
           for b in cfg.recipes[name].bases):
        return teacher_bases(cfg, name)
    print(f"[bench] {name}: its teacher's bases {cfg.recipes[name].bases} are not trained "
          "yet (make policies): measured over its own base only", flush=True)
    return []


def preflight(cfg: Config, run_dir: str | None) -> None:
    """Before anything is measured: ``bench.out`` can be written (not only after the run)."""
    from .utils.paths import check_output

    if cfg.bench.out:
        check_output("bench.out", cfg.bench.out, "file")


def task(dcfg: DictConfig) -> None:
    """Measure and print (``bench.out``: also as JSON)."""
    with user_errors():
        cfg = validated(dcfg, GROUPS)
        preflight(cfg, None)
        run(cfg)


main = hydra_command(task)

if __name__ == "__main__":
    main()
