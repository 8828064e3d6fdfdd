"""One launcher path for every multi-run experiment: Hydra's sweepers and launchers.

* :class:`JobProgress` (``hydra.callbacks.progress`` in ``conf/config.yaml``) prints, as each
  job of any multirun ends (the grid, the sweeps, the table's trainings), ``k of N`` jobs
  done, what the job was and how long it took. Jobs may run in other processes (joblib), on
  other machines (Slurm, Ray): they count in files of the sweep folder, under a lock.
* :func:`sweep_jobs`, :func:`progress_callback`, :func:`torch_threads`: what a sweeper of
  this project reads of Hydra's (the table's, :mod:`fleet_torchrl.table_sweep`, resolves
  the table's trainings into run specs and launches them).
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


@dataclass
class JobFailed:
    """What a task returns for a job that failed without stopping the others (a sweep point
    writes its ``.error`` and returns this): :class:`JobProgress` counts it like a job that
    raised, and the multirun exits with code 1 once every job has run."""

    label: str
    reason: str


def sweep_jobs(config: Any) -> tuple[list[list[str]], list[str]] | None:
    """The jobs Hydra's basic sweeper makes of a multirun's config (its ``sweeper.params``
    and the command line's overrides) and the keys that vary; None for another sweeper or a
    sweep it cannot expand ahead (glob, ranges it rejects)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    if OmegaConf.select(config, "hydra.sweeper._target_") != BASIC_SWEEPER:
        return None
    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    args = [f"{k}={v}" for k, v in params.items()]
    args += list(OmegaConf.select(config, "hydra.overrides.task") or [])
    try:
        overrides = OverridesParser.create().parse_overrides(args)
        batches = BasicSweeper.split_arguments(overrides, None)
    except Exception:  # noqa: BLE001 (a sweep Hydra will report itself)
        return None
    varying = [o.get_key_element() for o in overrides if o.is_sweep_override()]
    return [job for batch in batches for job in batch], varying


class JobProgress(Callback):
    """``k of N`` jobs done for every multirun (see the module docstring)."""

    def __init__(self) -> None:
        self.folder: str | None = None  # <sweep dir>/.progress/<this multirun>
        self.name = ""
        self.keys: list[str] = []  # the overrides that tell the jobs apart
        self._t0 = 0.0

    # ---------------------------------------------------------------- the launching process
    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        stamp = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
        self.folder = str(Path(str(config.hydra.sweep.dir)) / ".progress" / stamp)
        self.name = str(config.hydra.job.name)
        jobs = sweep_jobs(config)
        if jobs is not None:
            self.keys = jobs[1]
            self.set_total(len(jobs[0]))

    def set_total(self, total: int, name: str | None = None) -> None:
        """How many jobs this multirun launches (a sweeper that knows says so); a launcher
        that runs its jobs in several waves (the table) sets each wave's total, and its count
        starts again (it printed "33 of 1 jobs done" for the one job of the table's second
        wave)."""
        if self.folder is None:
            return
        self.name = name or self.name
        folder = Path(self.folder)
        folder.mkdir(parents=True, exist_ok=True)
        with _locked(folder / "lock"):
            (folder / "done").unlink(missing_ok=True)
            (folder / "total").write_text(str(total))

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        """Clean up the counters; if a job failed (raised, or returned :class:`JobFailed`),
        say which in one line and exit with code 1: the other jobs ran, but the multirun did
        not do what it was asked."""
        import shutil

        failed: list[str] = []
        if self.folder is not None:
            record = Path(self.folder) / "failed"
            if record.is_file():
                failed = [ln for ln in record.read_text().splitlines() if ln.strip()]
            total = Path(self.folder) / "total"
            total = total.read_text().strip() if total.is_file() else "?"
            shutil.rmtree(self.folder, ignore_errors=True)
            parent = Path(self.folder).parent
            if parent.is_dir() and not any(parent.iterdir()):
                parent.rmdir()
        if failed:
            print(f"error: {len(failed)} of {total} jobs failed: {'; '.join(failed)}",
                  file=sys.stderr, flush=True)
            sys.exit(1)

    # ---------------------------------------------------------------- each job's process
    def on_job_start(self, config: Any, **kwargs: Any) -> None:
        self._t0 = time.perf_counter()

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        if self.folder is None or not Path(self.folder).is_dir():
            return  # a single run, or a multirun whose size nobody knows
        folder = Path(self.folder)
        failure = None
        value = getattr(job_return, "_return_value", None)  # never re-raises a job's error
        if getattr(job_return.status, "name", str(job_return.status)) != "COMPLETED":
            failure = f"{self.label(config)} ({type(value).__name__})"
        elif isinstance(value, JobFailed):
            failure = f"{self.label(config)} ({value.reason})"
        with _locked(folder / "lock"):
            with open(folder / "done", "a") as f:
                f.write(f"{config.hydra.job.num}\n")
            if failure is not None:
                with open(folder / "failed", "a") as f:
                    f.write(failure.replace("\n", " ") + "\n")
            done = len((folder / "done").read_text().split())
        total = (folder / "total").read_text().strip() if (folder / "total").exists() else "?"
        status = "failed" if failure is not None else \
            getattr(job_return.status, "name", str(job_return.status)).lower()
        print(f"[{self.name}] {done} of {total} jobs done: {self.label(config)} ({status}, "
              f"{time.perf_counter() - self._t0:.0f} s)", flush=True)

    def label(self, config: Any) -> str:
        """What tells this job apart: its swept overrides, else its folder's name."""
        task = [o for o in config.hydra.overrides.task
                if o.split("=", 1)[0].lstrip("+~") in self.keys]
        return " ".join(task) or Path(str(config.hydra.runtime.output_dir)).name


class _locked:
    """An exclusive lock on ``path`` (``fcntl.flock``; a no-op where there is none): two jobs
    that end together count as two."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        self.f = open(self.path, "a")  # noqa: SIM115 (closed in __exit__)
        try:
            import fcntl

            fcntl.flock(self.f, fcntl.LOCK_EX)
        except (ImportError, OSError):
            pass

    def __exit__(self, *exc: Any) -> None:
        self.f.close()


def progress_callback(hydra_context: Any) -> JobProgress | None:
    callbacks = getattr(getattr(hydra_context, "callbacks", None), "callbacks", [])
    return next((c for c in callbacks if isinstance(c, JobProgress)), None)


def torch_threads(n: int | None = None) -> int | None:
    """torch's CPU thread count (set it to ``n``), if torch is loaded."""
    torch = sys.modules.get("torch")
    if torch is None:
        return None
    if n is not None:
        torch.set_num_threads(n)
    return torch.get_num_threads()


__all__ = ["JobFailed", "JobProgress", "progress_callback", "sweep_jobs", "torch_threads"]
