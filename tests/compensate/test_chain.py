import torch

from torchcal.compensate.chain import ChainGraph, geometric_jacobian_t
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.kinematics.robot import default_robot_path, load_robot


def _perturbed():
    robot = load_robot(default_robot_path())
    model = ErrorModel(robot)
    gen = torch.Generator().manual_seed(5)
    x = model.nominal_vector() + 1e-3 * torch.randn(model.layout.size, generator=gen, dtype=torch.float64)
    x[model.layout.base_slice] = 0.0
    return robot, model, x, robot.sample_joints(64, gen)


def _chain(robot, model, x, dtype=torch.float64):
    end = robot.T_n_flange @ model.flange_from_tool(x)
    return ChainGraph(model.table(x).unsqueeze(0), robot.T_base_0, end.unsqueeze(0), dtype=dtype)


def test_chain_pose_matches_error_model():
    robot, model, x, q = _perturbed()
    tcp, frames = _chain(robot, model, x)(q, with_frames=True)
    ref = model.base_flange_pose(q, x) @ model.flange_from_tool(x)
    assert torch.allclose(tcp[:, 0], ref, atol=1e-14)
    assert frames.shape == (64, 1, robot.dof, 4, 4)


def test_jacobian_matches_core_and_finite_differences():
    robot, model, x, q = _perturbed()
    chain = _chain(robot, model, x)
    tcp, frames = chain(q, with_frames=True)
    jac_t = geometric_jacobian_t(tcp[:, 0], frames[:, 0])
    _, ref = geometric_jacobian(model, q, x)  # identity instrument frame -> base frame
    assert torch.allclose(jac_t.transpose(-1, -2), ref, atol=1e-14)
    h = 1e-7
    for j in range(robot.dof):
        dq = torch.zeros_like(q)
        dq[:, j] = h
        fd = (chain(q + dq)[0][:, 0, :3, 3] - chain(q - dq)[0][:, 0, :3, 3]) / (2 * h)
        assert torch.allclose(fd, jac_t[:, j, :3], atol=1e-7)


def test_float32_chain_close_to_float64():
    robot, model, x, q = _perturbed()
    p64 = _chain(robot, model, x)(q)[0][:, 0, :3, 3]
    p32 = _chain(robot, model, x, torch.float32)(q.float())[0][:, 0, :3, 3]
    assert (p32.double() - p64).norm(dim=-1).max() < 1e-6  # m


def test_positions_path_matches_full_poses():
    robot, model, x, q = _perturbed()
    tables = torch.stack([robot.table, model.table(x)])
    ends = torch.stack([robot.T_n_flange @ model.flange_from_tool(model.nominal_vector()), robot.T_n_flange @ model.flange_from_tool(x)])
    chain = ChainGraph(tables, robot.T_base_0, ends)
    full = chain(q)[0][..., :3, 3]
    assert torch.allclose(chain.positions(q), full, atol=1e-14)
    assert torch.allclose(chain.positions(q)[:, 0], robot.tcp_position(q), atol=1e-14)
