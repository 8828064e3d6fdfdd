"""A content-addressed cache of evaluations: a result is stored under a key of everything it
depends on, so an experiment that adds a row recomputes that row only.

The key of an evaluation is the digest of

* the policy (:func:`policy_fingerprint`: the class of every module in it, their plain
  settings such as a planner's futures and horizon or a heuristic's thresholds, and the bytes
  of every tensor: weights, buffers, tables), never its display name;
* the site (its parameters, not its name: the default site reached by two sweeps is one
  site), the number of simulations, their ticks and the seed;
* the code that makes the numbers (:func:`code_fingerprint`: the source of ``sim/``,
  ``agents/``, ``evaluation/`` and the encodings): after any change there, every entry is
  stale and is recomputed, so a cached figure is always what this code computes.

Entries are JSON files ``<dir>/<key[:2]>/<key>.json`` written atomically. One that cannot be
read (cut short, edited by hand) is recomputed and rewritten, with a one-line warning; it
never stops an experiment. ``dir=None`` disables the cache (every call computes).
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from dataclasses import asdict
from functools import cache
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..sim import SiteConfig
from ..utils.runinfo import read_json, to_jsonable, write_json

#: the packages whose source decides an evaluation's numbers (relative to fleet_torchrl/)
CODE_PATHS = ("sim", "agents", "evaluation", "env/encodings.py")


def _log() -> logging.Logger:
    return logging.getLogger(__name__)


@cache
def code_fingerprint() -> str:
    """Digest of the source files that decide an evaluation's numbers (once per process)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for rel in CODE_PATHS:
        p = root / rel
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:24]


def _tensor_bytes(t: torch.Tensor) -> bytes:
    t = t.detach().cpu().contiguous()
    return t.view(torch.uint8).numpy().tobytes() if t.numel() else b""


_PLAIN = (bool, int, float, str)
_SKIP = frozenset({"name", "training"})  # a display name, the train/eval switch


def policy_fingerprint(policy: nn.Module) -> str:
    """What a policy decides with, hashed: every module's class, its plain settings (bools,
    numbers, strings other than ``name``) and the bytes of every tensor it holds (parameters,
    buffers, plain tensor attributes), in module order. Two policies with the same
    fingerprint take the same decisions; a renamed copy keeps its fingerprint."""
    h = hashlib.sha256()
    for path, m in policy.named_modules():
        h.update(f"<{path}:{type(m).__module__}.{type(m).__qualname__}>".encode())
        plain = {k: v for k, v in sorted(vars(m).items())
                 if not k.startswith("_") and k not in _SKIP and isinstance(v, _PLAIN)}
        h.update(json.dumps(plain, sort_keys=True).encode())
        tensors = {**{k: v for k, v in vars(m).items() if isinstance(v, torch.Tensor)},
                   **dict(m.named_parameters(recurse=False)),
                   **dict(m.named_buffers(recurse=False))}
        for k in sorted(tensors):
            t = tensors[k]
            if t is None:
                continue
            h.update(f"{k}:{t.dtype}:{tuple(t.shape)}".encode())
            h.update(_tensor_bytes(t))
    return h.hexdigest()[:32]


def site_identity(site: SiteConfig) -> dict[str, Any]:
    """A site's parameters without its display name."""
    return {**asdict(site), "name": ""}


def key_of(*parts: Any) -> str:
    """The digest of ``parts`` (JSON-able after :func:`to_jsonable`) and the code's."""
    blob = json.dumps([code_fingerprint(), to_jsonable(list(parts))], sort_keys=True,
                      default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:40]


class EvalCache:
    """``get_or_compute(parts, fn)``: the stored result of ``fn()`` under the key of
    ``parts``; ``evaluate(...)``: :func:`~fleet_torchrl.evaluation.evaluate_policy` through
    the cache. ``hits`` / ``misses`` count this object's lookups."""

    def __init__(self, folder: str | Path | None) -> None:
        self.folder = Path(folder) if folder else None
        self.hits = self.misses = 0

    def path(self, key: str) -> Path:
        assert self.folder is not None
        return self.folder / key[:2] / f"{key}.json"

    def get_or_compute(self, parts: list[Any], fn: Callable[[], dict[str, Any]]
                       ) -> dict[str, Any]:
        if self.folder is None:
            return fn()
        key = key_of(*parts)
        path = self.path(key)
        if path.is_file():
            try:
                entry = read_json(path)
                if isinstance(entry, dict) and entry.get("key") == key and "value" in entry:
                    self.hits += 1
                    return entry["value"]
                reason = "not an entry of this key"
            except (OSError, ValueError) as e:
                reason = str(e).splitlines()[0][:200]
            _log().warning("evaluation cache entry %s cannot be used (%s): recomputing it",
                           path, reason)
        self.misses += 1
        value = fn()
        write_json(path, {"key": key, "parts": to_jsonable(parts), "value": value})
        return value

    def evaluate(self, policy: nn.Module, site: SiteConfig, n_sims: int, ticks: int,
                 seed: int, evaluate: Callable[[], dict[str, Any]], name: str | None = None
                 ) -> dict[str, Any]:
        """An evaluation of ``policy`` (``evaluate()`` computes it) through the cache; the
        result's ``policy`` and ``site`` are this call's (a cached one may come from a
        renamed copy of the policy, or the same site under another name)."""
        parts = ["evaluation", policy_fingerprint(policy), site_identity(site), int(n_sims),
                 int(ticks), int(seed)]
        res = dict(self.get_or_compute(parts, evaluate))
        res["policy"] = name or getattr(policy, "name", res.get("policy"))
        res["site"] = asdict(site)
        return res


__all__ = ["CODE_PATHS", "EvalCache", "code_fingerprint", "key_of", "policy_fingerprint",
           "site_identity"]
