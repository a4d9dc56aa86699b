import math

import pytest
import torch

from torchcal.core.errors import ModelError
from torchcal.motion.profiles import make_profile, quintic, scurve, trapezoid

DT = 1e-4


def _sample(profile):
    t = torch.arange(0.0, profile.duration + 2 * DT, DT, dtype=torch.float64)
    return (t, *profile.evaluate(t))


@pytest.mark.parametrize("distance", [1.0, 0.05])
def test_trapezoid_velocity_continuous_acceleration_jumps(distance):
    v_max, a_max = 0.5, 2.0
    p = trapezoid(distance, v_max, a_max)
    _t, s, v, a = _sample(p)
    assert float(s[-1]) == pytest.approx(distance, abs=1e-12)
    assert float(v.max()) <= v_max * (1 + 1e-12) and float(a.abs().max()) <= a_max * (1 + 1e-12)
    # velocity is the derivative of position (trapezoid rule, exact up to a * DT where a jumps)
    torch.testing.assert_close(torch.diff(s) / DT, 0.5 * (v[1:] + v[:-1]), atol=a_max * DT, rtol=0)
    assert float(torch.diff(v).abs().max()) <= a_max * DT * (1 + 1e-9)
    # ... while the acceleration does (what the S-curve removes)
    assert float(torch.diff(a).abs().max()) >= 0.99 * a_max


@pytest.mark.parametrize("distance", [1.0, 0.1, 1e-3])
def test_scurve_acceleration_continuous(distance):
    v_max, a_max, j_max = 0.5, 2.0, 20.0
    p = scurve(distance, v_max, a_max, j_max)
    _t, s, v, a = _sample(p)
    assert float(s[-1]) == pytest.approx(distance, abs=1e-12)
    assert float(v.max()) <= v_max * (1 + 1e-12) and float(a.abs().max()) <= a_max * (1 + 1e-12)
    torch.testing.assert_close(torch.diff(s) / DT, 0.5 * (v[1:] + v[:-1]), atol=1e-6, rtol=0)
    # trapezoid rule is exact up to j * DT at the jerk switches
    torch.testing.assert_close(torch.diff(v) / DT, 0.5 * (a[1:] + a[:-1]), atol=j_max * DT, rtol=0)
    assert float(torch.diff(a).abs().max()) <= j_max * DT * (1 + 1e-9)
    assert bool((torch.diff(s) >= -1e-15).all())


def test_scurve_reaches_limits_on_long_moves_and_is_not_slower_than_needed():
    p = scurve(2.0, 0.5, 2.0, 20.0)
    assert p.peak_velocity == pytest.approx(0.5) and p.peak_acceleration == pytest.approx(2.0)
    # closed form: T = D / v + v / a + a / j for a long move reaching both limits
    assert p.duration == pytest.approx(2.0 / 0.5 + 0.5 / 2.0 + 2.0 / 20.0, rel=1e-12)
    assert trapezoid(2.0, 0.5, 2.0).duration == pytest.approx(2.0 / 0.5 + 0.5 / 2.0, rel=1e-12)


def test_quintic_continuous_and_within_limits():
    p = quintic(0.3, 0.5, 2.0)
    _t, s, v, a = _sample(p)
    assert float(s[-1]) == pytest.approx(0.3, abs=1e-12)
    assert float(v.max()) <= 0.5 * (1 + 1e-9) and float(a.abs().max()) <= 2.0 * (1 + 1e-9)
    torch.testing.assert_close(torch.diff(v) / DT, 0.5 * (a[1:] + a[:-1]), atol=1e-3, rtol=0)
    assert float(torch.diff(a).abs().max()) < 0.01 * p.peak_acceleration


def test_bad_profile_arguments():
    with pytest.raises(ModelError):
        trapezoid(0.0, 1.0, 1.0)
    with pytest.raises(ModelError):
        scurve(1.0, 1.0, -1.0, 1.0)
    with pytest.raises(ModelError):
        make_profile("cubic", 1.0, 1.0, 1.0, 1.0)
    assert math.isfinite(make_profile("scurve", 1.0, 1.0, 1.0, 1.0).duration)
