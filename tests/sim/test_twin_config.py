"""The twin's settings refuse values that would write poses outside the joint limits or print a
contradictory range."""

import math

import pytest

from torchcal.config import compose_run_config
from torchcal.core.errors import TorchcalError
from torchcal.sim.twin_config import MAX_MARGIN_DEG, TwinConfig


@pytest.mark.parametrize("margin", [MAX_MARGIN_DEG, 500.0])
def test_margin_beyond_the_bound_is_refused_with_its_reason(margin):
    with pytest.raises(TorchcalError, match=r"margin_deg must be in \[0, 45\) deg, got .*leaves no range to sample"):
        TwinConfig(margin_deg=margin)
    with pytest.raises(TorchcalError, match="margin_deg must be in"):
        compose_run_config([f"twin.margin_deg={margin}"])


def test_margin_within_the_bound_is_kept():
    assert TwinConfig(margin_deg=0.0).margin_deg == 0.0
    assert TwinConfig(margin_deg=44.5).margin_deg == 44.5
    with pytest.raises(TorchcalError, match=r"margin_deg must be a finite number in \[0, inf\), got -1"):
        TwinConfig(margin_deg=-1.0)


def test_margin_is_checked_against_the_narrowest_joint_range():
    TwinConfig(margin_deg=20.0).check_margin([340.0, 90.0, 300.0])
    with pytest.raises(TorchcalError, match=r"below half the narrowest joint range of the robot \(30 deg of 60\), got 30"):
        TwinConfig(margin_deg=30.0).check_margin([340.0, 60.0])


@pytest.mark.parametrize("name", ["tracker_sigma_mm", "margin_deg", "instrument_distance_mm", "length_error_mm"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_a_size_that_is_not_finite_is_refused_in_plain_words(name, value):
    with pytest.raises(TorchcalError, match=rf"^{name} must be a finite number, got {value!r}$"):
        TwinConfig(**{name: value})
