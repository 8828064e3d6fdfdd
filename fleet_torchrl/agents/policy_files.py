"""Saved-policy files: one ``policy.pt`` (written atomically) holding a plain dict.

Keys: ``format``, ``kind`` (the agent's registry name), ``encoding``, ``spec`` (the
constructor arguments of the policy class, :meth:`Policy.policy_spec`), ``state_dict`` and
``meta`` (provenance). The key stays ``spec`` although the method was renamed (it shadowed
TorchRL's ``spec`` attribute): files written before and after read alike, and a retrained
policy's bytes, whose hash the table and the sweeps compare, do not change.
:func:`~fleet_torchrl.agents.registry.load_policy_file` rebuilds the policy through the
registry.
"""

from __future__ import annotations

import hashlib
import io
from pathlib import Path
from typing import Any

import torch

from ..utils.runinfo import atomic_write
from .base import Policy

FORMAT = "fleet_torchrl.policy/2"
POLICY_FILE = "policy.pt"


def policy_bytes(policy: Policy, kind: str, meta: dict[str, Any] | None = None) -> bytes:
    """The bytes of the policy file of ``policy`` (of registry agent ``kind``)."""
    bundle = {
        "format": FORMAT,
        "kind": kind,
        "encoding": policy.encoding,
        "spec": policy.policy_spec(),
        "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "meta": meta or {},
    }
    buf = io.BytesIO()
    torch.save(bundle, buf)
    return buf.getvalue()


def save_policy(path: str | Path, policy: Policy, kind: str,
                meta: dict[str, Any] | None = None) -> tuple[Path, str]:
    """Write ``policy`` (of registry agent ``kind``) to ``path`` atomically; returns the path
    and the SHA-256 of the bytes written."""
    data = policy_bytes(policy, kind, meta)
    out = atomic_write(path, lambda f: f.write(data), mode="wb")
    return out, hashlib.sha256(data).hexdigest()


def read_policy_file(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """The checked bundle of ``policy.pt`` (or of a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / POLICY_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no saved policy at {path}; train it first with `make policies` "
                                "or `make train ARGS=\"agent=... state=...\"`")
    try:
        bundle = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # truncated or foreign file
        raise ValueError(
            f"{path} is not a readable policy file ({type(e).__name__}: {e})") from None
    if not isinstance(bundle, dict) or bundle.get("format") != FORMAT:
        raise ValueError(f"{path} is not a fleet_torchrl policy file (format {FORMAT} expected)")
    return path, bundle
