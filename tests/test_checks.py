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
