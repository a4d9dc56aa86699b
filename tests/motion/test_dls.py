import math

import pytest
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.motion.dls import adaptive_damping, damped_inverse, dls_inverse, pseudo_inverse

DEG = math.pi / 180.0


def _regular_jacobians(model, x, eps):
    q = model.robot.sample_joints(64, torch.Generator().manual_seed(1), margin=0.2)
    _, jac = geometric_jacobian(model, q, x)
    keep = torch.linalg.svdvals(jac)[:, -1] > 2 * eps
    assert keep.sum() > 10
    return jac[keep]


def test_dls_equals_pinv_far_from_singularity(model, x_nom):
    jac = _regular_jacobians(model, x_nom, 0.04)
    inv = dls_inverse(jac, eps=0.04, a_max=0.06)
    assert bool((inv.damping_sq == 0).all())
    torch.testing.assert_close(inv.inverse, torch.linalg.pinv(jac), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(inv.inverse, torch.linalg.inv(jac), rtol=1e-9, atol=1e-9)


def test_damped_inverse_matches_textbook_formula(model, x_nom):
    jac = _regular_jacobians(model, x_nom, 0.04)[:5]
    a2 = torch.tensor([0.0, 1e-4, 1e-3, 1e-2, 0.1], dtype=torch.float64)
    eye = torch.eye(6, dtype=torch.float64)
    expected = jac.transpose(-1, -2) @ torch.linalg.inv(jac @ jac.transpose(-1, -2) + a2[:, None, None] * eye)
    torch.testing.assert_close(damped_inverse(jac, a2).inverse, expected, rtol=1e-9, atol=1e-9)
    # wide (position-only) Jacobians too
    pos = jac[:, :3]
    expected = pos.transpose(-1, -2) @ torch.linalg.inv(pos @ pos.transpose(-1, -2) + 1e-3 * torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(damped_inverse(pos, 1e-3).inverse, expected, rtol=1e-9, atol=1e-9)


def test_bounded_at_exact_wrist_singularity(model, x_nom):
    q = torch.tensor([10.0, -80.0, 10.0, 30.0, 0.0, 20.0], dtype=torch.float64) * DEG
    _, jac = geometric_jacobian(model, q, x_nom)
    a_max = 0.06
    inv = dls_inverse(jac, eps=0.04, a_max=a_max)
    assert float(inv.sigma_min) < 1e-12
    torch.testing.assert_close(inv.damping_sq, torch.tensor(a_max**2, dtype=torch.float64), rtol=1e-9, atol=0)
    gain = torch.linalg.matrix_norm(inv.inverse, ord=2)
    assert torch.isfinite(inv.inverse).all()
    assert float(gain) <= 1.0 / (2.0 * a_max) * (1 + 1e-9)
    # the undamped inverse of a slightly perturbed pose explodes like 1 / sigma_min
    q[4] = 1e-6
    _, jac = geometric_jacobian(model, q, x_nom)
    assert float(torch.linalg.matrix_norm(pseudo_inverse(jac).inverse, ord=2)) > 1e5
    assert float(torch.linalg.matrix_norm(dls_inverse(jac, 0.04, a_max).inverse, ord=2)) <= 1.0 / (2.0 * a_max) * (1 + 1e-9)


def test_adaptive_damping_law():
    sigma = torch.tensor([0.0, 0.02, 0.04, 0.1], dtype=torch.float64)
    a2 = adaptive_damping(sigma, eps=0.04, a_max=0.1)
    expected = torch.tensor([0.01, 0.01 * 0.75, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(a2, expected)
    with pytest.raises(ModelError):
        adaptive_damping(sigma, eps=0.0, a_max=0.1)


def test_selective_damping_keeps_regular_directions_exact():
    u, _ = torch.linalg.qr(torch.randn(6, 6, generator=torch.Generator().manual_seed(2), dtype=torch.float64))
    v, _ = torch.linalg.qr(torch.randn(6, 6, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    s = torch.tensor([2.0, 1.5, 1.0, 0.5, 0.3, 0.01], dtype=torch.float64)
    jac = u @ torch.diag(s) @ v.T
    sel = dls_inverse(jac, 0.04, 0.06, selective=True).inverse
    uni = dls_inverse(jac, 0.04, 0.06).inverse
    regular = u[:, 0]  # a twist along the largest singular direction
    torch.testing.assert_close(sel @ regular, v[:, 0] / 2.0, rtol=1e-12, atol=1e-12)
    assert float((uni @ regular - v[:, 0] / 2.0).norm()) > 1e-5
