"""Range checks for configuration values, free of any configuration framework.

Every schema validates its own fields with these helpers; a failure raises
:class:`ConfigError` with one line naming the field, its value and what is allowed.

A field's own range is declared on the field, not written in ``validate``::

    @dataclass
    class MyConfig:
        n_sims: int = ranged(1000, 1, 10**8)               # [1, 100000000]
        lr: float = ranged(1e-3, 0, 1.0, lo_open=True)      # (0, 1.0]
        backend: str = ranged("auto", choices=BACKENDS)    # one of auto, eager, fused
        env_steps: int | None = ranged(None, 1, 10**7, optional=True)
        margins: list[float] = ranged(lo=0, hi=100, lo_open=True, each=True,
                                      default_factory=lambda: [0.1, 0.5])  # each in (0, 100]

        def validate(self, path: str = "mine") -> MyConfig:
            check_fields(self, path)  # every declared field, in the order of the fields
            ...  # what depends on other fields or groups stays code here
            return self

:func:`ranged` returns a :func:`dataclasses.field` whose metadata holds a :class:`Range`;
:func:`check_fields` checks every such field of an instance under ``path`` and raises the
same one-line :class:`ConfigError` as :func:`check_range` / :func:`check_choice` would
(``mine.n_sims=0 is invalid: allowed [1, 100000000]``). :func:`declared_ranges` lists a
schema's declarations (for tests and documentation). A bound that depends on another field
(``n_vehicles <= n_nodes - 2``) is a cross-field check and stays code in ``validate``.
"""

from __future__ import annotations

import contextvars
import functools
import inspect
import math
import numbers
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar


class ConfigError(ValueError):
    """A configuration value outside its allowed range (message names the field)."""


class SetupError(RuntimeError):
    """Something of this machine stops a run (e.g. a compiled kernel that cannot be built),
    said in one line with what to do instead; the commands report it like a bad value."""


def exception_line(exc: BaseException, limit: int = 200) -> str:
    """An exception as one short line for a message: its type, then the first line of its
    text cut to ``limit`` characters (the type alone when it has no text)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0][:limit]}" if text else \
        type(exc).__name__


# Schemas validate themselves on construction (:func:`validate_on_init`), so a config built
# in Python is checked like one given on the command line. Inside :func:`deferred_validation`
# they do not: OmegaConf builds a composed config bottom-up, where a nested schema cannot
# know its path (``agent.expert`` vs ``agent``) nor check the other groups, and the root's
# validation (``fleet_torchrl.config.validate``) runs right after, in the commands' order.
_DEFERRED: contextvars.ContextVar[bool] = contextvars.ContextVar("fleet_deferred", default=False)


@contextmanager
def deferred_validation() -> Iterator[None]:
    """Construct schemas without validating them here (the caller validates the whole)."""
    token = _DEFERRED.set(True)
    try:
        yield
    finally:
        _DEFERRED.reset(token)


@functools.cache
def _schema_path(cls: type) -> str:
    """A schema's place in the root config: its ``PATH`` (:class:`Schema`), else the
    default ``path`` of its ``validate``."""
    if getattr(cls, "PATH", ""):
        return cls.PATH  # type: ignore[attr-defined]
    param = inspect.signature(cls.validate).parameters.get("path")
    return param.default if param is not None and isinstance(param.default, str) else \
        cls.__name__


# field annotations (strings: the schemas use ``from __future__ import annotations``) whose
# values are checked by type on construction; anything else is left to ``validate``
_SCALARS = {"int": ("an integer", numbers.Integral), "float": ("a number", numbers.Real),
            "str": ("a string", str), "bool": ("true or false", bool)}


def check_types(obj: Any, path: str) -> None:
    """Raise :class:`ConfigError` for a field of a plain scalar type (``int``, ``float``,
    ``str``, ``bool``, or one of them ``| None``) that holds a value of another type: a
    config built in Python is not type-checked by OmegaConf (``n_vehicles=2.7``)."""
    for f in fields(obj):
        ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        optional = ann.endswith(" | None")
        kind = _SCALARS.get(ann.removesuffix(" | None"))
        if kind is None:
            continue
        value = getattr(obj, f.name)
        if value is None and optional:
            continue
        words, types = kind
        ok = isinstance(value, types) and (types is bool or not isinstance(value, bool))
        if ok and types is numbers.Integral:
            value = int(value)
        if not ok:
            raise ConfigError(f"{path}.{f.name}={_fmt(value)} is invalid: allowed {words}"
                              + (" or null" if optional else ""))


def validate_on_init(obj: Any) -> None:
    """What a schema's ``__post_init__`` does: check its field types and call its own
    ``validate()`` (checks of its own fields; what depends on other groups is the root's),
    unless inside :func:`deferred_validation`."""
    if _DEFERRED.get():
        return
    path = _schema_path(type(obj))
    check_types(obj, path)
    obj.validate()


class Schema:
    """Base of a schema dataclass whose own checks are its declared ranges
    (:func:`ranged`): checked on construction (:func:`validate_on_init`) and by
    :meth:`validate` under ``PATH``, its place in the root config (``"state"``, ``"mdp"``). A
    schema with checks across its fields overrides :meth:`validate` and calls
    :func:`check_fields` first."""

    PATH: ClassVar[str] = ""

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str | None = None) -> Any:
        check_fields(self, path or self.PATH)
        return self


def coerce_schema(cls: type, value: Any, path: str,
                  from_dict: Callable[[dict], Any] | None = None) -> Any:
    """``value`` as a validated ``cls``: an instance of it (checked as it stands now: it may
    have been changed since it was built), a dict of its fields (built by ``from_dict``,
    default ``cls(**value)``) or None (the defaults); anything else raises
    :class:`ConfigError` naming ``path``."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value.validate(path)
    if isinstance(value, dict):
        check_known_fields(cls, value, path)
        return from_dict(dict(value)) if from_dict is not None else cls(**value)
    article = "an" if cls.__name__[0] in "AEIOU" else "a"
    raise ConfigError(f"{path}={value!r} is invalid: allowed {article} {cls.__name__}, a dict "
                      "of its fields, or None")


def lookup(table: dict[str, Any], name: str, what: str) -> Any:
    """``table[name]``, else a ``ValueError`` "``what``: allowed one of ..." naming the keys
    (a registry's entry by name: state encodings, objectives)."""
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"{what}: allowed one of {', '.join(table)}") from None


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        return repr(v) if len(v) <= 80 else repr(v[:77]) + "..."
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10**30:
        return f"an integer of about {int(v.bit_length() * 0.30103) + 1} digits"
    return f"{v}"


def as_number(value: Any) -> int | float | None:
    """``value`` as a plain Python ``int`` or ``float`` if it is one number, else None.

    A numpy scalar or 0-d array and a 0-d (or one-element) torch tensor are unwrapped; any
    other real number (``Fraction``, ``Decimal``...) becomes a ``float``. ``bool`` (also
    numpy's and a bool tensor), a string, None, a container are no number. NaN and inf stay
    what they are: :func:`check_range` refuses them."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):  # np.float64 is a float: plain float, same value
        return float(value)
    shape, item = getattr(value, "shape", None), getattr(value, "item", None)
    if shape is not None and callable(item):  # numpy scalar or array, torch tensor
        try:
            v = item() if math.prod(tuple(shape)) == 1 else None
        except (TypeError, ValueError, RuntimeError):
            return None
        return None if isinstance(v, bool) or not isinstance(v, (int, float)) else v
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        try:
            return float(value)
        except (TypeError, ValueError, OverflowError):
            return None
    return None


def check_range(path: str, value: Any, lo: float | None = None, hi: float | None = None,
                allowed: str | None = None, *, lo_open: bool = False,
                hi_open: bool = False) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a finite number with
    ``lo <= value <= hi`` (``lo < value`` with ``lo_open``, ``value < hi`` with
    ``hi_open``): NaN and inf are refused in every numeric type (Python, numpy scalars, 0-d
    torch tensors), and so are ``bool``, strings and None (:func:`as_number`). The message
    says ``allowed``, by default the interval (``[1, 10]``, ``(0, 1.0]``)."""
    v = as_number(value)
    bad = v is None or (isinstance(v, float) and not math.isfinite(v))
    bad = bad or (lo is not None and (v <= lo if lo_open else v < lo)) or \
        (hi is not None and (v >= hi if hi_open else v > hi))
    if bad:
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed "
                          f"{allowed or interval(lo, hi, lo_open, hi_open)}")


def interval(lo: float | None, hi: float | None, lo_open: bool = False,
             hi_open: bool = False) -> str:
    """The interval ``[lo, hi]`` as the messages write it (``(`` / ``)`` for an open bound,
    ``-inf`` / ``inf`` for none)."""
    lo_s = "-inf" if lo is None else _fmt(lo)
    hi_s = "inf" if hi is None else _fmt(hi)
    return f"{'(' if lo_open else '['}{lo_s}, {hi_s}{')' if hi_open else ']'}"


def check_known_fields(cls: type, value: dict, path: str) -> None:
    """A dict meant to build the dataclass ``cls`` holds only its fields (the first unknown
    key is named, with the allowed ones)."""
    known = {f.name for f in fields(cls)}
    extra = sorted(str(k) for k in value if k not in known)
    if extra:
        raise ConfigError(f"{path}.{extra[0]} is not a setting of {path} (allowed: "
                          f"{', '.join(sorted(known))})")


def check_choice(path: str, value: Any, choices: tuple[str, ...] | list[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed one of {', '.join(choices)}")


RANGE_KEY = "fleet_range"  # the key of a field's :class:`Range` in its metadata


@dataclass(frozen=True)
class Range:
    """What a field allows, declared with :func:`ranged`: a finite number in ``[lo, hi]``
    (either bound open or absent), or one of ``choices`` (a tuple, or a function returning
    the names, called at check time: a registry imported lazily); ``optional``: None too;
    ``each``: the value is a list (or tuple) and every element is checked, as
    ``path[i]``; ``allowed`` replaces the interval in the message."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    allowed: str | None = None
    choices: tuple[str, ...] | Callable[[], Iterable[str]] | None = None
    optional: bool = False
    each: bool = False

    def describe(self) -> str:
        """What is allowed, as the messages say it (``[1, 10]``, ``one of a, b``)."""
        if self.choices is not None:
            return f"one of {', '.join(self.names())}"
        return self.allowed or interval(self.lo, self.hi, self.lo_open, self.hi_open)

    def names(self) -> tuple[str, ...]:
        """The allowed choices (empty for a numeric range)."""
        c = self.choices
        return () if c is None else tuple(c() if callable(c) else c)

    def check(self, path: str, value: Any) -> None:
        """Raise :class:`ConfigError` (one line naming ``path``) unless ``value`` is allowed."""
        if value is None and self.optional:
            return
        if self.each:
            if not isinstance(value, (list, tuple)):
                raise ConfigError(f"{path}={_fmt(value)} is invalid: allowed a list of values "
                                  f"in {self.describe()}")
            for i, v in enumerate(value):
                self._check_one(f"{path}[{i}]", v)
        else:
            self._check_one(path, value)

    def _check_one(self, path: str, value: Any) -> None:
        if self.choices is not None:
            check_choice(path, value, self.names())
        else:
            check_range(path, value, self.lo, self.hi, self.allowed, lo_open=self.lo_open,
                        hi_open=self.hi_open)


def ranged(default: Any = MISSING, lo: float | None = None, hi: float | None = None, *,
           lo_open: bool = False, hi_open: bool = False, allowed: str | None = None,
           choices: tuple[str, ...] | Callable[[], Iterable[str]] | None = None,
           optional: bool = False, each: bool = False,
           default_factory: Callable[[], Any] | Any = MISSING) -> Any:
    """A dataclass field (``default`` or ``default_factory``) with its allowed values
    declared (:class:`Range`); :func:`check_fields` checks it."""
    if (lo is not None or hi is not None) and choices is not None:
        raise TypeError("ranged: a numeric range (lo, hi) or choices, not both")
    meta = {RANGE_KEY: Range(lo, hi, lo_open, hi_open, allowed,
                             tuple(choices) if isinstance(choices, (list, tuple)) else choices,
                             optional, each)}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def declared_ranges(cls_or_obj: Any) -> dict[str, Range]:
    """The fields of a dataclass (class or instance) that declare what they allow, in the
    order of the fields."""
    return {f.name: f.metadata[RANGE_KEY] for f in fields(cls_or_obj) if RANGE_KEY in f.metadata}


def check_fields(obj: Any, path: str) -> None:
    """Check every declared field of the dataclass instance ``obj`` (:func:`ranged`), in the
    order of the fields, as ``<path>.<field>``: the first one not allowed raises
    :class:`ConfigError`. A schema's ``validate`` calls it."""
    for name, r in declared_ranges(obj).items():
        r.check(f"{path}.{name}", getattr(obj, name))


def check_device(path: str, device: str) -> None:
    """A torch device string that exists on this machine."""
    if device == "cpu":  # the default: no torch import (composing a config stays light)
        return
    if not isinstance(device, str):
        raise ConfigError(f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps")
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError(
            f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps") from None
    if dev.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{path}={_fmt(device)} is invalid: allowed cpu, cuda, cuda:N, mps")
    problem = device_problem(dev)
    if problem is not None:
        raise ConfigError(f"{path}={_fmt(device)} is invalid: {problem}")


def device_problem(dev: Any) -> str | None:
    """Why the torch device ``dev`` cannot be used on this machine (what to use instead), or
    None if it can: CUDA or MPS not available here, a CUDA index beyond the devices there."""
    import torch

    if dev.type == "cuda":
        if not torch.cuda.is_available():
            return "CUDA is not available here; use cpu"
        n = torch.cuda.device_count()
        if dev.index is not None and dev.index >= n:
            return f"this machine has {n} CUDA device(s); allowed cuda:0 to cuda:{n - 1}"
    if dev.type == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            return "MPS is not available here; use cpu"
    return None
