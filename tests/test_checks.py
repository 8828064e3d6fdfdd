"""The range checks every schema uses (fleet_torchrl/utils/checks.py): a finite number of any
numeric type within its range passes; NaN, inf, a bool, a string, None or a container is
refused in one line naming the setting."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

from fleet_torchrl.utils.checks import ConfigError, as_number, check_device, check_range

NOT_FINITE = [float("nan"), float("inf"), float("-inf"), np.float32("nan"),
              np.float32("inf"), np.float64("nan"), np.float64("-inf"), np.float16("nan"),
              np.array(np.nan), np.array([np.inf]), torch.tensor(float("nan")),
              torch.tensor(float("inf"), dtype=torch.float64), torch.tensor([float("nan")]),
              torch.tensor(float("nan"), dtype=torch.bfloat16)]
NOT_NUMBERS = [True, False, np.bool_(True), torch.tensor(True), "0.5", None, [0.5], (0.5,),
               {"v": 0.5}, np.array([0.1, 0.2]), torch.tensor([0.1, 0.2]), object()]
FINITE = [0.5, 1, 0, np.float32(0.5), np.float64(0.25), np.float16(1.0), np.int64(1),
          np.uint8(0), np.int32(1), np.array(0.5), torch.tensor(0.5), torch.tensor(1),
          torch.tensor([0.75]), Fraction(1, 2)]


def _id(value) -> str:
    """A test id that is the same in every process (no memory address: a bare object's repr
    has one, and parallel workers must collect the same ids)."""
    return type(value).__name__ if type(value) is object else repr(value)[:30]


@pytest.mark.parametrize("value", NOT_FINITE + NOT_NUMBERS,
                         ids=[_id(v) for v in NOT_FINITE + NOT_NUMBERS])
def test_non_finite_values_and_non_numbers_are_refused_in_one_line(value):
    with pytest.raises(ConfigError) as e:
        check_range("site.p_c", value, 0.0, 1.0)
    msg = str(e.value)
    assert msg.startswith("site.p_c=") and "is invalid: allowed [0.0, 1.0]" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("value", NOT_FINITE, ids=[_id(v) for v in NOT_FINITE])
def test_non_finite_values_are_refused_without_bounds_too(value):
    """An open range (``lo``/``hi`` None) still refuses NaN and inf, whatever the type."""
    with pytest.raises(ConfigError):
        check_range("x", value)


@pytest.mark.parametrize("value", FINITE, ids=[_id(v) for v in FINITE])
def test_finite_numbers_of_any_type_pass(value):
    check_range("x", value, 0.0, 1.0)
    assert isinstance(as_number(value), (int, float)) and not isinstance(as_number(value), bool)


def test_numbers_out_of_range_of_any_type_are_refused():
    for value in (np.int64(5), np.float32(1.5), torch.tensor(-1), 10**400, -(10**400)):
        with pytest.raises(ConfigError) as e:
            check_range("x", value, 0, 1)
        assert len(str(e.value)) < 120  # a 400-digit integer is not printed whole


def test_as_number_unwraps_one_number_and_nothing_else():
    assert as_number(np.float32(0.5)) == 0.5 and type(as_number(np.float32(0.5))) is float
    assert as_number(np.int64(3)) == 3 and type(as_number(np.int64(3))) is int
    assert as_number(torch.tensor([7])) == 7
    assert as_number(np.float64("nan")) != as_number(np.float64("nan"))  # NaN stays NaN
    for v in NOT_NUMBERS:
        assert as_number(v) is None, v


def test_schemas_refuse_numpy_and_torch_non_finite_values():
    from fleet_torchrl.agents.config import NetworkConfig
    from fleet_torchrl.env import MDPConfig
    from fleet_torchrl.sim import SiteConfig

    cases = [(SiteConfig, "p_c"), (SiteConfig, "e_move"), (MDPConfig, "gamma"),
             (MDPConfig, "p_f"), (NetworkConfig, "lr")]
    for schema, name in cases:
        for bad in (np.float32("nan"), np.float64("inf"), np.float32("-inf")):
            with pytest.raises(ConfigError, match=rf"\.{name}=") as e:
                schema(**{name: bad})
            assert "\n" not in str(e.value)
    assert SiteConfig(p_c=np.float32(0.5)).p_c == 0.5  # a finite numpy value is a number


def test_devices_this_machine_does_not_have_are_refused():
    check_device("x.device", "cpu")
    for bad in ("nope", "cuda:x", "xpu", "meta", 3):
        with pytest.raises(ConfigError, match=r"^x\.device=.* is invalid: allowed cpu, cuda"):
            check_device("x.device", bad)
    mps = getattr(torch.backends, "mps", None)
    if mps is None or not mps.is_available():
        with pytest.raises(ConfigError, match="MPS is not available here; use cpu"):
            check_device("x.device", "mps")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available here; use cpu"):
            check_device("x.device", "cuda")
    else:
        n = torch.cuda.device_count()
        check_device("x.device", f"cuda:{n - 1}")
        with pytest.raises(ConfigError, match=f"allowed cuda:0 to cuda:{n - 1}"):
            check_device("x.device", f"cuda:{n}")


def test_declared_ranges_check_like_the_calls_they_replace():
    """A field declared with ``ranged`` is checked by ``check_fields`` under the schema's
    path, with the message ``check_range`` / ``check_choice`` give, in the fields' order."""
    from dataclasses import dataclass

    from fleet_torchrl.utils.checks import (
        check_choice,
        check_fields,
        declared_ranges,
        ranged,
    )

    @dataclass
    class Schema:
        plain: str = "x"  # no declaration: not checked
        n: int = ranged(3, 1, 10)
        lr: float = ranged(0.5, 0, 1.0, lo_open=True)
        cap: float = ranged(1.0, None, 2.0, hi_open=True, allowed="below 2")
        kind: str = ranged("a", choices=("a", "b"))
        lazy: str = ranged("a", choices=lambda: ("a", "c"))
        steps: int | None = ranged(None, 1, 100, optional=True)
        margins: list[float] = ranged(lo=0, hi=100.0, lo_open=True, each=True,
                                      default_factory=lambda: [0.1, 1.0])

    assert list(declared_ranges(Schema)) == ["n", "lr", "cap", "kind", "lazy", "steps",
                                             "margins"]
    assert Schema().margins == [0.1, 1.0] and Schema().margins is not Schema().margins
    check_fields(Schema(steps=100, lr=1.0, cap=-5.0, kind="b", lazy="c"), "s")

    def message(**bad) -> str:
        with pytest.raises(ConfigError) as e:
            check_fields(Schema(**bad), "s")
        return str(e.value)

    def expected(call, *args, **kwargs) -> str:
        with pytest.raises(ConfigError) as e:
            call(*args, **kwargs)
        return str(e.value)

    assert message(n=0) == expected(check_range, "s.n", 0, 1, 10) == \
        "s.n=0 is invalid: allowed [1, 10]"
    assert message(n=float("nan")) == "s.n=nan is invalid: allowed [1, 10]"
    assert message(lr=0) == "s.lr=0 is invalid: allowed (0, 1.0]"  # the open bound itself
    assert message(lr=1.5) == "s.lr=1.5 is invalid: allowed (0, 1.0]"
    assert message(cap=2.0) == "s.cap=2.0 is invalid: allowed below 2"
    assert message(kind="z") == expected(check_choice, "s.kind", "z", ("a", "b")) == \
        "s.kind='z' is invalid: allowed one of a, b"
    assert message(lazy="b") == "s.lazy='b' is invalid: allowed one of a, c"
    assert message(steps=0) == "s.steps=0 is invalid: allowed [1, 100]"
    assert message(margins=[0.5, 0.0]) == "s.margins[1]=0.0 is invalid: allowed (0, 100.0]"
    assert message(margins=0.5) == \
        "s.margins=0.5 is invalid: allowed a list of values in (0, 100.0]"
    assert message(n=0, kind="z") == "s.n=0 is invalid: allowed [1, 10]"  # the first field
    with pytest.raises(TypeError):
        ranged(1, 0, 1, choices=("a",))


def test_open_bounds_of_check_range():
    check_range("x", 0.5, 0, 1, lo_open=True, hi_open=True)
    for bad in (0, 0.0, 1, 1.0):
        with pytest.raises(ConfigError, match=r"^x=.* is invalid: allowed \(0, 1\)$"):
            check_range("x", bad, 0, 1, lo_open=True, hi_open=True)
    check_range("x", 0, 0, 1)  # closed by default
