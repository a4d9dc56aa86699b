"""The compensator's step functions against closed forms and their defining properties."""

import torch

from torchcal.compensate.linalg import gauss_jordan, inverse3
from torchcal.compensate.steps import bounded, pose_step, position_first_step

F64 = {"dtype": torch.float64}


def _spd(n: int, seed: int) -> torch.Tensor:
    a = torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(seed), **F64)
    return a @ a.transpose(-1, -2) + 0.1 * torch.eye(3, **F64)


def test_inverse3_is_the_inverse():
    a = _spd(200, 0)
    assert (inverse3(a) - torch.linalg.inv(a)).abs().max() < 1e-10
    general = torch.randn(200, 3, 3, generator=torch.Generator().manual_seed(1), **F64)  # not symmetric
    assert (inverse3(general) @ general - torch.eye(3, **F64)).abs().max() < 1e-8


def test_bounded_keeps_direction_and_caps_the_largest_joint():
    dq = torch.tensor([[0.3, -0.1, 0.0], [0.01, 0.02, -0.03], [0.0, 0.0, 0.0]], **F64)
    out = bounded(dq, torch.tensor(0.1, **F64))
    assert torch.allclose(out[0], dq[0] / 3)  # scaled as a whole
    assert torch.equal(out[1], dq[1])  # small steps untouched
    assert torch.equal(out[2], dq[2])  # zero stays zero (no NaN)


def _case(seed: int, n_joints: int = 6):
    g = torch.Generator().manual_seed(seed)
    jac_t = torch.randn(50, n_joints, 6, generator=g, **F64)
    error = torch.randn(50, 6, 1, generator=g, **F64) * 1e-3
    return jac_t, error


def _position_first(jac_t, error, orientation=True, floor=0.0, orient_floor=0.0):
    return position_first_step(jac_t, error, torch.tensor(0.0, **F64), torch.tensor(floor, **F64),
                               torch.tensor(orient_floor, **F64), torch.eye(3, **F64), torch.tensor(10.0, **F64),
                               torch.tensor(10.0, **F64), orientation=orientation)


def test_position_first_solves_the_linearized_position_task_exactly():
    for n in (6, 7):
        jac_t, error = _case(n, n)
        dq = _position_first(jac_t, error)
        jp = jac_t[..., :3].transpose(-1, -2)
        assert ((jp @ dq.unsqueeze(-1)) - error[:, :3]).abs().max() < 1e-10  # errors are 1e-3


def test_orientation_part_lies_in_the_position_null_space_and_solves_the_rest():
    """With six joints and no damping both tasks are met: the step is the full 6-D solution."""
    jac_t, error = _case(3)
    dq = _position_first(jac_t, error)
    full = torch.linalg.solve(jac_t.transpose(-1, -2), error).squeeze(-1)
    assert (dq - full).abs().max() < 1e-9
    only_position = _position_first(jac_t, error, orientation=False)
    jp = jac_t[..., :3].transpose(-1, -2)
    assert (jp @ (dq - only_position).unsqueeze(-1)).abs().max() < 1e-10  # orientation part moves no position


def test_position_first_damping_gives_way_on_orientation_not_position():
    """A rank-deficient orientation task (two aligned wrist axes): position still exact."""
    jac_t, error = _case(4)
    jac_t[:, 5, 3:] = jac_t[:, 3, 3:]  # joints 4 and 6 turn about the same axis...
    jac_t[:, 5, :3] = jac_t[:, 3, :3]  # ...through the same point: a wrist singularity
    dq = _position_first(jac_t, error, orient_floor=1e-4)
    jp = jac_t[..., :3].transpose(-1, -2)
    assert torch.isfinite(dq).all()
    assert ((jp @ dq.unsqueeze(-1)) - error[:, :3]).abs().max() < 1e-9


def test_pose_step_matches_the_damped_least_squares_closed_form():
    jac_t, error = _case(5)
    gain, floor = torch.tensor(10.0, **F64), torch.tensor(1e-10, **F64)
    eye = torch.eye(6, **F64)
    got = pose_step(jac_t, error, gain, floor, eye, gauss_jordan)
    lam2 = gain * (error * error).sum(-2, keepdim=True) + floor
    jac = jac_t.transpose(-1, -2)
    expected = (jac_t @ torch.linalg.solve(jac @ jac_t + lam2 * eye, error)).squeeze(-1)
    assert (got - expected).abs().max() < 1e-12
