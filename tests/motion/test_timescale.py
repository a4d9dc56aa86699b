import math

import numpy as np
import pytest

from torchcal.core.errors import ModelError
from torchcal.motion.timescale import time_optimal, velocity_curve


def _linear_joint(c: float, length: float = 0.4, n: int = 2001):
    s = np.linspace(0.0, length, n)
    return s, np.full((n, 1), c), np.zeros((n, 1))


@pytest.mark.parametrize("c, joint_speed, joint_accel, v, a", [
    (1.0, 100.0, 100.0, 0.25, 2.0),   # the path limits bind
    (4.0, 0.5, 100.0, 0.25, 2.0),     # the joint speed binds: s_dot <= 0.5 / 4
    (4.0, 100.0, 4.0, 0.25, 2.0),     # the joint acceleration binds: s_ddot <= 4 / 4
])
def test_trapezoid_closed_form(c, joint_speed, joint_accel, v, a):
    s, dq, ddq = _linear_joint(c)
    law = time_optimal(s, dq, ddq, speed=v, path_accel=a, joint_speed=np.array([joint_speed]),
                       joint_accel=np.array([joint_accel]))
    v_eff, a_eff = min(v, joint_speed / c), min(a, joint_accel / c)
    length = s[-1]
    expected = length / v_eff + v_eff / a_eff  # trapezoid, cruise reached (length > v^2 / a)
    assert law.duration == pytest.approx(expected, rel=2e-3)
    assert float(law.s_dot.max()) == pytest.approx(v_eff, rel=1e-9)
    assert law.s_dot[0] == 0.0 and law.s_dot[-1] == 0.0
    t = np.linspace(0.0, law.duration, 4001)
    s_t = law.sample(t)
    assert s_t[0] == 0.0 and s_t[-1] == pytest.approx(length, abs=1e-12)
    speed = np.diff(s_t) / np.diff(t)
    assert np.all(speed <= v_eff * (1 + 1e-6)) and np.all(np.diff(s_t) >= 0)


def test_curved_joint_path_respects_acceleration_by_finite_differences():
    s = np.linspace(0.0, 0.3, 3001)
    q = 0.8 * np.sin(12.0 * s)[:, None] + np.array([[0.0, 1.0]]) * s[:, None]  # two joints
    dq = np.concatenate([9.6 * np.cos(12.0 * s)[:, None], np.ones((len(s), 1))], 1)
    ddq = np.concatenate([-115.2 * np.sin(12.0 * s)[:, None], np.zeros((len(s), 1))], 1)
    limits_v, limits_a = np.array([1.5, 10.0]), np.array([20.0, 50.0])
    law = time_optimal(s, dq, ddq, speed=0.25, path_accel=5.0, joint_speed=limits_v, joint_accel=limits_a)
    dt = 1e-3
    t = np.arange(0.0, law.duration, dt)
    s_t = law.sample(t)
    q_t = np.interp(s_t, s, q[:, 0])
    speed = np.abs(np.diff(q_t)) / dt
    accel = np.abs(np.diff(q_t, 2)) / dt**2
    assert speed.max() <= limits_v[0] * 1.01
    assert accel.max() <= limits_a[0] * 1.05
    assert speed.max() >= 0.9 * limits_v[0] or accel.max() >= 0.9 * limits_a[0]  # and it is not needlessly slow


def test_velocity_curve_of_a_curved_joint_at_rest_in_s():
    # q' = 0, q'' = 2: |q''| s_dot^2 <= A gives s_dot^2 <= A / 2
    cap = velocity_curve(np.zeros((1, 1)), np.full((1, 1), 2.0), 10.0, 100.0, np.array([1.0]), np.array([3.0]))
    assert cap[0] == pytest.approx(1.5)


def test_bad_limits_are_refused():
    s, dq, ddq = _linear_joint(1.0)
    with pytest.raises(ModelError, match="joint speed"):
        time_optimal(s, dq, ddq, speed=0.25, path_accel=2.0, joint_speed=np.array([0.0]), joint_accel=np.array([1.0]))
    with pytest.raises(ModelError, match="speed limit"):
        time_optimal(s, dq, ddq, speed=math.inf, path_accel=2.0, joint_speed=np.array([1.0]), joint_accel=np.array([1.0]))
