"""Joint-space terms fitted with the geometry: where orientations were measured, they judge the terms too."""

from __future__ import annotations

import math
import warnings

import torch

from tests.helpers import central_difference_jacobian
from torchcal.config.schema import FitConfig
from torchcal.data.measurements import Measurements
from torchcal.identify.joint_fit import JointErrorProblem
from torchcal.kinematics import transforms as tf
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.orientation import model_orientation_errors
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

PROBE = tf.so3_exp(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64))  # a 6-D probe mounted at some angle


def _measured_6d(twin: Twin, n: int, seed: int) -> Measurements:
    """The sagging twin's points (tracker noise) and the probe's exact orientation at ``n`` poses."""
    gen = torch.Generator().manual_seed(seed)
    q = twin.robot.sample_joints(n, gen, margin=math.radians(10))
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q + twin.joint_deviation(q), twin.x_true)
    return Measurements(q=q, position=twin.measure(q, gen), rotation=flange[..., :3, :3] @ PROBE)


def test_a_6d_fit_with_joint_space_terms_keeps_the_measured_orientation(tmp_path):
    # the terms' problem used to have position rows only: the probe rotation, seen by the orientations alone,
    # went back to its prior (0) and the model missed every measured orientation by the probe's 61 deg
    twin = Twin.create(TwinConfig(seed=4, gravity=True, gear=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit_model(tmp_path / "m", twin.robot, _measured_6d(twin, 200, 1),
                  FitConfig(residual="none", gravity_compliance="wrist", joint_harmonics="none", progress=False))
    stored = load_model(tmp_path / "m")
    assert stored.model.with_orientation and stored.metadata.get("gravity_compliance")
    tool_rotation = tf.so3_exp(stored.x[stored.model.layout.tool_slice][3:])
    assert math.degrees(float(tf.rotation_angle(tool_rotation.T @ PROBE))) < 0.2
    scored = model_orientation_errors(stored, _measured_6d(twin, 200, 2), register=True).metrics()
    assert scored["orientation_rms_deg"] < 0.05


def test_the_6d_rows_of_the_terms_problem_have_their_finite_difference_jacobian():
    from torchcal.identify.compliance import gravity_torque_basis
    from torchcal.kinematics.error_model import ErrorModel

    twin = Twin.create(TwinConfig(seed=4, gravity=True, gear=False))
    data = _measured_6d(twin, 12, 3)
    model = ErrorModel(twin.robot, with_orientation=True, T_instrument_base=twin.T_instrument_base())
    basis = gravity_torque_basis(twin.robot, data.q, ("tcp",))
    columns = [(0, j) for j in range(1, 4)]
    size = model.layout.size
    free = torch.cat([torch.tensor([model.layout.index(n) for n in ("alpha3", "theta5", "tool_rz")]),
                      torch.arange(size, size + len(columns))])
    problem = JointErrorProblem(model, data, basis, free, columns, orientation_weight_m_per_rad=0.5)
    assert problem.rows_per_pose == 6
    x = torch.cat([model.nominal_vector(), torch.tensor([2e-3, -1e-3, 5e-4], dtype=torch.float64)])
    x[model.layout.tool_slice.start + 3: model.layout.tool_slice.stop] = tf.so3_log(PROBE)
    r, jac = problem.jacobian(x)
    assert r.shape == (6 * len(data),)
    expected = central_difference_jacobian(problem.residuals, x, free.tolist(), step=1e-7)
    rows = jac.reshape(len(data), 6, -1)
    fd = expected.reshape(len(data), 6, -1)
    torch.testing.assert_close(rows[:, :3], fd[:, :3], rtol=1e-5, atol=1e-8)  # central differences: ~1e-9 m round-off
    # the rotation rows are the small-angle ones (as CalibrationProblem's): exact where the model meets the
    # measured orientation, off by about the remaining angle (here the twin's tenths of a degree) elsewhere
    angle = float(r.reshape(len(data), 6)[:, 3:].norm(dim=-1).max()) / 0.5
    assert angle < 0.02
    torch.testing.assert_close(rows[:, 3:], fd[:, 3:], rtol=0, atol=2 * angle * float(fd[:, 3:].abs().max()))
