"""Publishing a trained policy without replacing another.

A finished run publishes its best policy and summary (``policy.pt``, ``train_summary.json``)
to its publish folder: ``<table.policies_dir>/<name>/seed<s>/`` by default, else
``train.out_dir``. A folder that already holds a policy is never replaced silently:

* before the run trains (:func:`check_publish`, the command's preflight), a folder holding the
  policy of this very training (same settings and seed: the summary's fingerprint and the
  policy file's hash match) or of another one is refused in one line naming the folder and
  what to do: another seed, another ``train.out_dir``, or ``train.overwrite=true``;
* when the run ends (:meth:`~fleet_torchrl.training.trainer.Trainer.promote`) the folder is
  checked again under an exclusive lock on it (:func:`publish_lock`): a policy another run
  published meanwhile stays, and this run's stays in its run folder.

A run's own folder (``train.out_dir`` equal to the run folder) is the run's: its best policy
is saved there while it trains. So is what the run itself published before: a finished run
resumed in its run folder (``resume=true``, e.g. to calibrate its deferral again) replaces
the policy whose summary names that run folder.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from ..agents.policy_files import POLICY_FILE
from ..store import policy_name, seed_dir
from ..utils.checks import ConfigError
from ..utils.runinfo import file_sha256, read_json
from .checkpoint import fingerprint_diff, result_fingerprint
from .spec import RunSpec

SUMMARY = "train_summary.json"


def holds_policy(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds a published policy or its summary (a dangling link counts)."""
    return any(os.path.lexists(Path(folder) / name) for name in (POLICY_FILE, SUMMARY))


def publish_dir(spec: RunSpec, policies_dir: str | os.PathLike,
                follow_symlinks: bool = False) -> Path:
    """Where a training of ``spec`` publishes its policy: ``train.out_dir`` if set, else
    ``<policies_dir>/<name>/seed<seed>`` (:func:`~fleet_torchrl.store.seed_dir`, inside
    ``policies_dir`` unless ``follow_symlinks``)."""
    if spec.train.out_dir:
        return Path(spec.train.out_dir)
    return seed_dir(policies_dir, policy_name(spec), spec.seed, follow_symlinks)


def published_diff(folder: str | os.PathLike, spec: RunSpec) -> list[str] | None:
    """How the policy published in ``folder`` differs from a training of ``spec``: an empty
    list for the very same training (its summary records ``spec``'s result fingerprint and
    the policy file's hash), ``key: old -> new`` lines for another one, None when nothing is
    published there."""
    folder = Path(folder)
    if not holds_policy(folder):
        return None
    try:
        rec = read_json(folder / SUMMARY)
    except (OSError, ValueError):
        return ["its train_summary.json is missing or unreadable"]
    if not isinstance(rec, dict) or not isinstance(rec.get("fingerprint"), dict):
        return ["its train_summary.json records no training settings"]
    diff = fingerprint_diff(rec["fingerprint"], result_fingerprint(spec))
    if diff:
        return diff
    try:
        same_file = rec.get("policy_sha256") == file_sha256(folder / POLICY_FILE)
    except OSError:
        same_file = False
    return [] if same_file else ["its policy.pt is not the one its summary records"]


def same_folder(a: str | os.PathLike, b: str | os.PathLike | None) -> bool:
    return b is not None and Path(os.path.abspath(a)) == Path(os.path.abspath(b))


def published_by(folder: str | os.PathLike) -> str | None:
    """The run folder the summary in ``folder`` names (``run_dir``), or None."""
    try:
        rec = read_json(Path(folder) / SUMMARY)
    except (OSError, ValueError):
        return None
    run = rec.get("run_dir") if isinstance(rec, dict) else None
    return run if isinstance(run, str) and run else None


def check_publish(spec: RunSpec, out_dir: str | os.PathLike,
                  run_dir: str | os.PathLike | None = None, resume: bool = False) -> None:
    """Raise :class:`ConfigError` (one line naming the folder) if a training of ``spec``
    would replace a policy published in ``out_dir`` (see the module docstring); nothing to
    check with ``train.overwrite=true`` or when ``out_dir`` is the run's own folder, nor
    when ``resume`` continues the run in ``run_dir`` that published it."""
    if spec.train.overwrite or same_folder(out_dir, run_dir):
        return
    if resume and run_dir is not None and same_folder(run_dir, published_by(out_dir)):
        return  # this run's own publication, resumed
    diff = published_diff(out_dir, spec)
    if diff is None:
        return
    where = f"train.out_dir={out_dir}" if spec.train.out_dir else str(out_dir)
    if not diff:
        raise ConfigError(
            f"{where} already holds the policy of this same training (same settings, seed "
            f"{spec.seed}): it is kept and there is nothing to train; evaluate it, or pass "
            "train.overwrite=true to train it again and replace it")
    raise ConfigError(
        f"{where} already holds a policy of another training ({'; '.join(diff[:3])}): it is "
        "kept; choose another seed, another train.out_dir, or pass train.overwrite=true to "
        "replace it")


@contextlib.contextmanager
def publish_lock(folder: str | os.PathLike) -> Iterator[None]:
    """An exclusive lock on the publish folder itself (created if missing) while a run
    checks and writes it, so that two runs ending together publish one after the other, the
    second seeing the first's policy. A no-op where there are no locks."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        with contextlib.suppress(OSError):  # a file system without locks
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


__all__ = ["SUMMARY", "check_publish", "holds_policy", "publish_dir", "publish_lock",
           "published_diff"]
