"""Checkpoint identity: which settings a run's checkpoint belongs to.

Every checkpoint stores the *training fingerprint* of its run spec
(:class:`~fleet_torchrl.training.spec.RunSpec`: everything that decides what the run
computes); resuming under another fingerprint would splice two runs, so it is refused with
the list of fields that differ.
"""

from __future__ import annotations

import pickle
import zipfile
import zlib
from dataclasses import asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

from ..agents.policy_files import policy_file_sha256
from ..utils.runinfo import to_jsonable
from .config import DEFERRAL_SETTINGS
from .spec import RunSpec

CHECKPOINT = "checkpoint.ckpt"

# what reading a damaged checkpoint raises: a truncated or garbled archive, a member whose
# CRC fails, a tensor file torch cannot unpickle
UNREADABLE = (OSError, ValueError, KeyError, EOFError, RuntimeError, zipfile.BadZipFile,
              zlib.error, pickle.UnpicklingError)

# settings a resumed run may change: they steer the run, not what it learns
RUN_CONTROL = {"out_dir", "overwrite", "device", "threads", "tensorboard", "progress",
               "checkpoint_every"}


def training_fingerprint(spec: RunSpec) -> dict[str, Any]:
    """What a training run of ``spec`` computes, as JSON-ready values. An agent
    setting added after runs were saved, declared with ``field(metadata={"neutral": v})``,
    is left out while it is ``v``, the value that computes what the runs before it did: the
    saved runs keep their fingerprint (and stay reusable and resumable)."""
    train = {k: v for k, v in asdict(spec.train).items()
             if k not in RUN_CONTROL and k not in DEFERRAL_SETTINGS}
    agent = without_neutral(spec.agent)
    expert = agent.get("expert") if isinstance(agent, dict) else None
    if isinstance(expert, dict) and expert.get("bases"):  # a parallel rollout's teacher:
        expert["bases"] = [_with_content(b) for b in expert["bases"]]  # its files' content
    return to_jsonable({"site": spec.site, "state": spec.state, "mdp": spec.mdp,
                        "agent": agent, "network": spec.network, "train": train,
                        "seed": spec.seed})


def result_fingerprint(spec: RunSpec) -> dict[str, Any]:
    """What a published policy is: the training fingerprint and, when the policy defers to
    the heuristic (``train.defer``), the deferral settings its margin was calibrated with. A
    saved policy is reused only under the same result fingerprint; its run's checkpoint
    resumes under the training fingerprint alone (the deferral changes no training)."""
    fp = training_fingerprint(spec)
    if spec.train.defer != "none":
        fp["deferral"] = to_jsonable({k: getattr(spec.train, k) for k in DEFERRAL_SETTINGS})
    return fp


def _with_content(base: str) -> str:
    """A teacher's base as ``<path>#<sha256 of its policy file>`` (a name as it is): a saved
    run is reused, or resumed, only over the very policies it was taught over."""
    sha = policy_file_sha256(base)
    return base if sha is None else f"{base}#{sha[:16]}"


def without_neutral(obj: Any) -> Any:
    """A config dataclass as a JSON-ready dict without the fields declared
    ``metadata={"neutral": v}`` that hold ``v``, in nested dataclasses too (a teacher's
    settings inside a learner's); anything else as :func:`to_jsonable` has it."""
    if not (is_dataclass(obj) and not isinstance(obj, type)):
        return to_jsonable(obj)
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        plain = to_jsonable(v)
        if "neutral" in f.metadata and plain == to_jsonable(f.metadata["neutral"]):
            continue
        out[f.name] = without_neutral(v) if is_dataclass(v) else plain
    return out


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


def checkpoint_mismatch(path: str | Path, spec: RunSpec) -> list[str]:
    """Why the checkpoint at ``path`` cannot continue a run of ``spec`` (empty if it can).

    Raises ``ValueError`` if the file is not a readable checkpoint.
    """
    from torchrl.checkpoint import Checkpoint, CheckpointError

    try:
        meta = Checkpoint.manifest(path).get("metadata") or {}
    except (CheckpointError, *UNREADABLE) as e:
        raise ValueError(f"cannot resume from {path}: not a readable checkpoint ({e})") from None
    stored = meta.get("config")
    if stored is None:
        return ["the checkpoint records no configuration (written by an older version)"]
    return fingerprint_diff(stored, training_fingerprint(spec))


def check_resumable(path: str | Path, spec: RunSpec) -> None:
    """Raise unless the checkpoint at ``path`` can continue a run of ``spec``: missing
    (``FileNotFoundError``), unreadable or of other settings (``ValueError``, naming the
    fields that differ). What a resume checks before it writes anything."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"resume=true, but there is no checkpoint at {path}: point "
                                "hydra.run.dir at the run to continue, or start a new run "
                                "without resume=true")
    diff = checkpoint_mismatch(path, spec)
    if diff:
        raise ValueError(f"cannot resume from {path}: it belongs to another configuration "
                         f"({'; '.join(diff[:5])}); resume with the same settings or start a "
                         "new run directory")
