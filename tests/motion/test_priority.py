import math

import pytest
import torch

from torchcal.kinematics.error_model import ErrorModel
from torchcal.motion.priority import (
    PrioritySettings,
    TcpKinematics,
    filtered_inverse,
    priority_step,
)
from torchcal.motion.scenario import perturbed_parameters

DEG = math.pi / 180.0
SETTINGS = PrioritySettings()


def _kin(model: ErrorModel, x: torch.Tensor, joint_map=None) -> TcpKinematics:
    return TcpKinematics(model.table(x), model.T_base_0, model.T_n_flange @ model.flange_from_tool(x), joint_map)


def test_pose_matches_pytorch_kinematics(robot):
    """A second, independent forward kinematics: pytorch-kinematics on the URDF of the nominal chain
    (which rounds joint origins to float32: agreement to 1e-7, not to round-off)."""
    model = ErrorModel(robot)
    kin = _kin(model, model.nominal_vector())
    q = robot.sample_joints(20, torch.Generator().manual_seed(0))
    flange = robot.pk_chain().forward_kinematics(q).get_matrix()
    tool = torch.eye(4, dtype=torch.float64)
    tool[:3, 3] = robot.tool
    torch.testing.assert_close(kin.pose(q), flange @ tool, rtol=0, atol=1e-6)


def test_pose_matches_textbook_mdh_product(robot, mdh_fk):
    model = ErrorModel(robot)
    kin = _kin(model, model.nominal_vector())
    q = robot.sample_joints(20, torch.Generator().manual_seed(0))
    torch.testing.assert_close(kin.pose(q), torch.from_numpy(mdh_fk(q.numpy())), rtol=0, atol=1e-13)


def test_jacobian_matches_finite_differences(robot):
    model = ErrorModel(robot)
    x = perturbed_parameters(model, 2)
    # a joint-space error (a first harmonic on every joint) exercises the chain rule of joint_map
    joint_map = lambda q: q + 0.01 * torch.sin(q) + 0.002 * torch.cos(2 * q)  # noqa: E731
    for mapping in (None, joint_map):
        kin = _kin(model, x, mapping)
        q = robot.sample_joints(3, torch.Generator().manual_seed(1))
        _, jac = kin(q)
        h = 1e-6
        for j in range(robot.dof):
            dq = torch.zeros(robot.dof, dtype=torch.float64)
            dq[j] = h
            plus, minus = kin.pose(q + dq), kin.pose(q - dq)
            from torchcal.kinematics import transforms as tf

            linear = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * h)
            angular = tf.so3_log(plus[:, :3, :3] @ minus[:, :3, :3].transpose(-1, -2)) / (2 * h)
            torch.testing.assert_close(jac[:, :, j], torch.cat([linear, angular], -1), rtol=1e-6, atol=1e-8)


def test_filtered_inverse_is_pinv_outside_eps_and_continuous_inside():
    gen = torch.Generator().manual_seed(0)
    u, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    v, _ = torch.linalg.qr(torch.randn(6, 6, generator=gen, dtype=torch.float64))

    def matrix(smallest):
        return u @ torch.diag(torch.tensor([1.0, 0.5, smallest], dtype=torch.float64)) @ v[:3]

    inv, _ = filtered_inverse(matrix(0.2), eps=0.1, a_max=0.05)
    torch.testing.assert_close(inv, torch.linalg.pinv(matrix(0.2)))
    values = torch.linspace(0.0, 0.15, 3001, dtype=torch.float64)
    gains = torch.stack([filtered_inverse(matrix(float(x)), 0.1, 0.05)[0] for x in values])
    jumps = (gains[1:] - gains[:-1]).abs().amax((-1, -2))
    assert float(jumps.max()) < 0.1  # no jump anywhere, eps = 0.1 included (step 5e-5 in sigma)
    assert float(gains.abs().max()) <= 1 / 0.1 + 1e-9  # bounded by 1/eps, not 1/sigma
    torch.testing.assert_close(gains[0] @ matrix(0.0) @ v[2], torch.zeros(6, dtype=torch.float64))


def test_regular_pose_tracks_both_tasks_exactly(robot):
    model = ErrorModel(robot)
    kin = _kin(model, model.nominal_vector())
    q = torch.tensor([10, -80, 10, 20, 60, 20], dtype=torch.float64) * DEG
    _, jac = kin(q)
    dp = torch.tensor([1e-4, -2e-4, 3e-4], dtype=torch.float64)
    dw = torch.tensor([1e-4, 2e-4, -1e-4], dtype=torch.float64)
    step = priority_step(jac, dp, dw, SETTINGS)
    assert float(step.sigma_orientation) > SETTINGS.orientation_eps
    torch.testing.assert_close(jac @ step.dq, torch.cat([dp, dw]), rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize("q5_deg", [0.0, 0.01, 0.5])
def test_wrist_singularity_keeps_position_exact_and_orientation_bounded(robot, q5_deg):
    model = ErrorModel(robot)
    kin = _kin(model, model.nominal_vector())
    q = torch.tensor([10, -80, 10, 0, q5_deg, 20], dtype=torch.float64) * DEG
    _, jac = kin(q)
    dp = torch.tensor([1e-4, 0.0, -1e-4], dtype=torch.float64)
    dw = torch.tensor([2e-4, -1e-4, 1e-4], dtype=torch.float64)
    step = priority_step(jac, dp, dw, SETTINGS)
    assert float(step.sigma_orientation) < SETTINGS.orientation_eps
    torch.testing.assert_close(jac[:3] @ step.dq, dp, rtol=1e-10, atol=1e-15)  # position exact
    # the orientation yields instead of spinning the wrist: |dq| stays of the order of |dw| / eps
    assert float(step.dq.abs().max()) < 2 * float(dw.norm()) / SETTINGS.orientation_eps
    assert float((jac[3:] @ step.dq - dw).norm()) > 0  # and the orientation is not reached exactly
