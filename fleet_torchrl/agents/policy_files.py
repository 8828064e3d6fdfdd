"""Saved-policy files: one ``policy.pt`` (written atomically) holding a plain dict.

Keys: ``format``, ``kind`` (the agent's registry name), ``encoding``, ``spec`` (the
constructor arguments of the policy class, :meth:`Policy.policy_spec`), ``state_dict``,
``meta`` (provenance), ``tensors_sha256`` (:func:`tensors_sha256` of the state dict) and
``content_sha256`` (:func:`content_sha256`: the format, kind, encoding, spec, metadata and
tensors together, everything a decision of the policy depends on).

Integrity: a file whose content does not match the hashes it records (a flipped byte that
still unpickles would otherwise load and evaluate as another policy, or as the same
weights read through another spec) is refused, as is a policy with a NaN or an infinite
weight, at load and at save (so a diverged training publishes nothing). Older files still
load, each with a one-line warning once per process: one that records no hash at all
(loaded unchecked), and one that records the hash of its tensors only (its tensors are
checked; its kind, spec and metadata are not covered, and are checked only as every spec
is, by :func:`~fleet_torchrl.agents.registry.load_policy_file`);
:func:`~fleet_torchrl.agents.registry.upgrade_policy_file` rewrites such a file with both
hashes. The kind, encoding, spec and metadata must have the types a policy file gives
them (the kind a string naming a known agent, checked by the registry; the encoding a
string, the spec and metadata dicts) whatever the hashes say.

The key stays ``spec`` although the method was renamed (it shadowed TorchRL's ``spec``
attribute): files written before and after read alike.
:func:`~fleet_torchrl.agents.registry.load_policy_file` rebuilds the policy through the
registry.
"""

from __future__ import annotations

import hashlib
import io
import logging
import pickle
from pathlib import Path
from typing import Any

import torch

from ..utils.checks import exception_line
from ..utils.runinfo import atomic_write, file_sha256
from .base import Policy

FORMAT = "fleet_torchrl.policy/2"
POLICY_FILE = "policy.pt"
HASH_KEY = "tensors_sha256"
CONTENT_KEY = "content_sha256"
COVERED = ("format", "kind", "encoding", "spec", "meta")  # besides the tensors
KEYS = (*COVERED, "state_dict", HASH_KEY, CONTENT_KEY)  # what a policy file may hold

log = logging.getLogger(__name__)
_warned: set[str] = set()  # files without a (full) hash, announced once per process


class NonFiniteWeights(ValueError):
    """A policy whose weights hold NaN or inf (``key``: the first such tensor)."""

    def __init__(self, message: str, key: str) -> None:
        super().__init__(message)
        self.key = key


def tensors_sha256(state_dict: dict[str, torch.Tensor]) -> str:
    """SHA-256 of a state dict's tensors: each name, dtype, shape and bytes, in name order.
    A hash of the tensors rather than of the file: the same weights give the same hash
    whatever torch's serialisation does around them."""
    h = hashlib.sha256()
    for key in sorted(state_dict):
        t = state_dict[key].detach().cpu().contiguous()
        h.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def _canonical(value: Any) -> str:
    """A text that tells apart every value a policy file's spec and metadata can hold: the
    type of each scalar is kept (``1``, ``1.0`` and ``True`` differ), floats by their exact
    ``repr``, dict entries in the order of their keys' texts; a tensor by
    :func:`tensors_sha256` of itself."""
    if value is None or isinstance(value, (bool, int, float, str, bytes)):
        return f"{type(value).__name__}:{value!r}"
    if isinstance(value, torch.Tensor):
        return f"tensor:{tensors_sha256({'': value})}"
    if isinstance(value, dict):
        items = sorted(f"{_canonical(k)}={_canonical(v)}" for k, v in value.items())
        return "dict{" + ",".join(items) + "}"
    if isinstance(value, (list, tuple)):
        return f"{type(value).__name__}[" + ",".join(_canonical(v) for v in value) + "]"
    return f"{type(value).__name__}:{value!r}"


def content_sha256(bundle: dict[str, Any]) -> str:
    """SHA-256 of what a policy file's decisions depend on: its format, kind, encoding, spec
    and metadata (:func:`_canonical` of each) and its tensors (:func:`tensors_sha256`)."""
    h = hashlib.sha256()
    for key in COVERED:
        h.update(f"{key}|{_canonical(bundle.get(key))}|".encode())
    h.update(tensors_sha256(bundle["state_dict"]).encode())
    return h.hexdigest()


def first_non_finite(state_dict: dict[str, torch.Tensor]) -> str | None:
    """The name of the first floating-point tensor holding a NaN or an inf, or None."""
    for key in sorted(state_dict):
        t = state_dict[key]
        if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
            return key
    return None


def policy_bytes(policy: Policy, kind: str, meta: dict[str, Any] | None = None) -> bytes:
    """The bytes of the policy file of ``policy`` (of registry agent ``kind``); raises
    :class:`NonFiniteWeights` for a policy with a NaN or an infinite weight, and
    ``ValueError`` for one whose file would be refused at load (an action outside
    {0, 1}: :meth:`Policy.check_loaded`)."""
    state = {k: v.detach().cpu() for k, v in policy.state_dict().items()}
    bad = first_non_finite(state)
    if bad is not None:
        raise NonFiniteWeights(f"cannot save the {kind} policy: its weights hold NaN or inf "
                               f"({bad}); nothing was written", bad)
    wrong = policy.check_loaded()
    if wrong is not None:
        raise ValueError(f"cannot save the {kind} policy: {wrong}; nothing was written")
    bundle = {
        "format": FORMAT,
        "kind": kind,
        "encoding": policy.encoding,
        "spec": policy.policy_spec(),
        "state_dict": state,
        "meta": meta or {},
        HASH_KEY: tensors_sha256(state),
    }
    bundle[CONTENT_KEY] = content_sha256(bundle)
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


def policy_file_sha256(path: str | Path | None) -> str | None:
    """The SHA-256 of the policy file ``path`` names (``policy.pt`` or a folder holding
    one); None for anything else (a baseline's name, nothing)."""
    p = Path(path or "")
    p = p / POLICY_FILE if p.is_dir() else p
    return file_sha256(p) if p.is_file() else None


def _load_error(e: Exception, path: Path) -> str:
    """Why ``torch.load`` refused the file ``path``, in one short line: torch's own message
    for a file its safe loader will not open runs to a dozen lines about its ``weights_only``
    default and a link, and a file cut short gives an ``OSError`` or a zip reader's error,
    none of which helps someone who passed the wrong file or an interrupted copy."""
    try:
        with open(path, "rb") as f:
            zipped = f.read(4) == b"PK\x03\x04"  # what torch.save writes begins as a zip
    except OSError:
        zipped = False
    if zipped and isinstance(e, (RuntimeError, OSError, EOFError)):
        return "truncated or damaged: its zip archive cannot be read"
    if isinstance(e, pickle.UnpicklingError):
        return ("not a file torch.save wrote with tensors only: another kind of file, or one "
                "holding objects a policy file never has")
    return exception_line(e)


def _warn_once(path: Path, message: str) -> None:
    if str(path) not in _warned:
        _warned.add(str(path))
        log.warning(message, path)


def read_policy_file(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """The checked bundle of ``policy.pt`` (or of a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        seeds = sorted((p.parent.name for p in path.glob(f"seed*/{POLICY_FILE}")),
                       key=lambda name: (len(name), name))
        if not (path / POLICY_FILE).is_file() and seeds:  # a recipe's folder: one per seed
            raise FileNotFoundError(
                f"{path} holds one policy per training seed ({', '.join(seeds)}): name one, "
                f"e.g. {path / seeds[0]}")
        path = path / POLICY_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no saved policy at {path}; train it first with `make policies` "
                                "or `make train ARGS=\"agent=... state=...\"`")
    try:
        bundle = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # truncated or foreign file
        raise ValueError(f"{path} is not a readable policy file ({_load_error(e, path)})"
                         ) from None
    if not isinstance(bundle, dict) or bundle.get("format") != FORMAT:
        raise ValueError(f"{path} is not a fleet_torchrl policy file (format {FORMAT} expected)")
    state = bundle.get("state_dict")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor)
                                              for v in state.values()):
        raise ValueError(f"{path} is not a fleet_torchrl policy file (no tensors)")
    extra = sorted(str(k) for k in bundle if k not in KEYS)
    if extra:  # (a flipped byte in a hash's name would otherwise pass for an older file)
        raise ValueError(f"{path}: its key {extra[0][:40]!r} is not one a policy file has: "
                         "retrain the policy or restore the file")
    want = bundle.get(HASH_KEY)
    whole = bundle.get(CONTENT_KEY)
    if want is None and whole is None:
        _warn_once(path, "%s records no hash of its weights (written by an older version): "
                   "loaded unchecked; retrain or re-save it to add one")
    elif want is not None and want != tensors_sha256(state):
        raise ValueError(f"{path} is corrupt: its weights do not match the hash it records; "
                         "retrain the policy or restore the file")
    if whole is not None and whole != content_sha256(bundle):
        raise ValueError(f"{path}: its content does not match its hash (spec or metadata "
                         "changed?): retrain the policy or restore the file")
    if whole is None and want is not None:
        _warn_once(path, "%s records the hash of its weights only (written by an older "
                   "version): its kind, spec and metadata are not covered; re-save it with "
                   "fleet_torchrl.agents.registry.upgrade_policy_file to cover them")
    for key, kind, words in (("encoding", str, "a string"), ("spec", dict, "a dict"),
                             ("meta", (dict, type(None)), "a dict")):
        if not isinstance(bundle.get(key), kind):
            raise ValueError(f"{path}: its {key} must be {words}, not "
                             f"{type(bundle.get(key)).__name__}: retrain the policy or "
                             "restore the file")
    bad = first_non_finite(state)
    if bad is not None:
        raise NonFiniteWeights(f"{path} holds non-finite weights (NaN or inf in {bad}): "
                               "refused; retrain the policy", bad)
    return path, bundle
