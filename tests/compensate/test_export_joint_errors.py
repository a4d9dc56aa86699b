"""Joint-space errors (gravity compliance, first harmonics) inside the exported graphs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch

from torchcal.compensate import compensator as compensator_module
from torchcal.compensate.compensator import (
    CONVERGED_ORIENTATION_RAD,
    CONVERGED_POSITION_M,
    CompensatorGraph,
    MonitorGraph,
    _TwoModels,
)
from torchcal.compensate.export import export_model
from torchcal.compensate.graphs import build_graphs
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.config.schema import FitConfig
from torchcal.identify.compliance import POINT_SETS, GravityCompliance
from torchcal.identify.harmonics import JointHarmonics
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import pose_error
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, model_joints, save_fit
from torchcal.stages.store import load_model


def _errors(kind: str, n: int, scale: float = 1.0) -> JointSpaceErrors:
    """Known terms of realistic size (``scale`` multiplies the harmonics)."""
    gen = torch.Generator().manual_seed(7)
    compliance = harmonics = None
    if kind in ("wrist", "elbow+wrist", "elbow+forearm+wrist", "both"):
        points = POINT_SETS["elbow+wrist" if kind == "both" else kind]
        compliance = GravityCompliance(points, torch.randn(len(points), n, generator=gen, dtype=torch.float64) * 2e-4)
    if kind == "learned":  # nonlinear compliance and a series of order 4 (rad per m^3 on tau^3, up to ~1 m^3)
        compliance = GravityCompliance(("elbow", "tcp", "tcp3"), torch.randn(3, n, generator=gen, dtype=torch.float64) * 2e-4)
        orders = torch.arange(1, 5, dtype=torch.float64).repeat_interleave(2)[:, None]
        harmonics = JointHarmonics(torch.randn(8, n, generator=gen, dtype=torch.float64) * 1e-3 * scale / orders)
    if kind in ("harmonics", "both"):
        harmonics = JointHarmonics(torch.randn(2, n, generator=gen, dtype=torch.float64) * 1e-3 * scale)
    return JointSpaceErrors(compliance, harmonics)


@pytest.fixture(scope="module")
def calibrated(twin):
    """A geometric fit of the compensate fixtures' twin: model and parameters to attach terms to."""
    train = twin.sample(150, torch.Generator().manual_seed(11))
    result = fit(twin.robot, train, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False))
    return result.model, result.x


@pytest.mark.parametrize("kind", ["wrist", "elbow+wrist", "elbow+forearm+wrist", "harmonics", "both", "learned"])
def test_graph_joint_errors_equal_the_identified_model(calibrated, kind):
    model, x = calibrated
    errors = _errors(kind, model.robot.dof)
    models = _TwoModels(model, x, None, torch.float64, "cpu", errors)
    q = model.robot.sample_joints(500, torch.Generator().manual_seed(3))
    nominal, nominal_frames = models.nominal(q, with_frames=True)
    dq, slope = models.joint_errors(q, nominal_frames[:, 0], nominal[:, 0, :3, 3])
    expected = errors.effective_joints(model.robot, q) - q
    assert float(expected.abs().max()) > 1e-5  # the terms are not negligible here
    assert torch.allclose(dq, expected, rtol=0, atol=1e-15)
    if errors.harmonics is not None:  # the slope against central differences of the harmonic term
        h = 1e-6
        fd = (errors.harmonics.deflection(q + h) - errors.harmonics.deflection(q - h)) / (2 * h)
        assert torch.allclose(slope, fd, rtol=0, atol=5e-12)  # central-difference roundoff of order-4 terms ~1e-12
    else:
        assert slope is None


@pytest.mark.parametrize("kind", ["wrist", "both", "learned"])
def test_monitor_graph_predicts_the_chain_at_the_deflected_joints(calibrated, kind):
    model, x = calibrated
    errors = _errors(kind, model.robot.dof)
    q = model.robot.sample_joints(300, torch.Generator().manual_seed(4))
    base = ErrorModel(model.robot)
    with torch.no_grad():
        got = MonitorGraph(model, x, None, joint_errors=errors)(q)
    q_eff = errors.effective_joints(model.robot, q)
    real = (model.base_flange_pose(q_eff, x) @ model.flange_from_tool(x))[..., :3, 3]
    assert torch.allclose(got, real - base.tcp_position(q, base.nominal_vector()), rtol=0, atol=1e-13)


def _solve_residual(model, x, errors, q, iterations: int | None, task: str = "pose", source: str = "model") -> torch.Tensor:
    """Pose error (m, rad) of the real chain at the compensator's command against the nominal target
    (``source="geometry"``: the orientation rows are the geometric chain's, without the joint-space errors)."""
    with torch.no_grad():
        q_c = CompensatorGraph(model, x, joint_errors=errors, iterations=iterations, task=task, orientation_source=source)(q)
    real = model.base_flange_pose(errors.effective_joints(model.robot, q_c), x) @ model.flange_from_tool(x)
    base = ErrorModel(model.robot)
    target = base.base_flange_pose(q, base.nominal_vector()) @ base.flange_from_tool(base.nominal_vector())
    error = pose_error(target, real)
    if source == "geometry":
        geometric = model.base_flange_pose(q_c, x) @ model.flange_from_tool(x)
        error[:, 3:] = pose_error(target, geometric)[:, 3:]
    return error


def test_a_position_only_model_orients_by_its_geometry_and_places_by_the_whole_model(calibrated):
    """By default a model fitted to positions turns the tool by its geometry alone: the joint-space terms
    move the position (solved to the tolerance) and not the orientation, which is the MDH chain's to
    second order in the terms (below ``(sum |dq_i|)^2``)."""
    model, x = calibrated
    assert not model.with_orientation
    errors = _errors("both", model.robot.dof)
    q = model.robot.sample_joints(2000, torch.Generator().manual_seed(5), margin=math.radians(5))
    _, jac = geometric_jacobian(ErrorModel(model.robot), q, x)
    regular = torch.linalg.svdvals(jac)[:, -1] > 0.05
    assert CompensatorGraph(model, x, joint_errors=errors).orientation_source == "geometry"
    dq = (errors.effective_joints(model.robot, q) - q).abs().sum(-1)  # the terms' whole turn, at most
    assert 1e-3 < float(dq.max()) < 2e-2  # terms of a realistic size (a few mrad): their square is below 1e-4 rad
    geometric = _solve_residual(model, x, errors, q, 5, source="geometry")[regular]
    assert float(geometric[:, :3].norm(dim=-1).max()) < 2 * CONVERGED_POSITION_M
    assert bool((geometric[:, 3:].norm(dim=-1) <= dq[regular] ** 2 + 2 * CONVERGED_ORIENTATION_RAD).all())
    # the model source solves the whole chain's orientation instead; the geometry source leaves it turned by the terms
    whole = _solve_residual(model, x, errors, q, 5, source="model")[regular]
    assert float(whole[:, 3:].norm(dim=-1).max()) < math.hypot(CONVERGED_POSITION_M, CONVERGED_ORIENTATION_RAD)
    with torch.no_grad():
        q_c = CompensatorGraph(model, x, joint_errors=errors, iterations=5, task="pose")(q[regular])
    base = ErrorModel(model.robot)
    turned = pose_error(base.base_flange_pose(q[regular], base.nominal_vector()),
                        model.base_flange_pose(errors.effective_joints(model.robot, q_c), x))[:, 3:].norm(dim=-1)
    assert float(turned.median()) > 100 * CONVERGED_ORIENTATION_RAD


def test_compensator_solves_the_deflected_chain_and_needs_the_harmonic_slope(calibrated, monkeypatch):
    """With harmonics of 0.05 rad the Newton step needs ``1 + slope``: without it five steps stop
    short (measured: 2e-8 m median against 6e-16 m with the slope)."""
    model, x = calibrated
    errors = _errors("both", model.robot.dof, scale=20.0)  # harmonics up to 0.05 rad
    q = model.robot.sample_joints(2000, torch.Generator().manual_seed(5), margin=math.radians(5))
    _, jac = geometric_jacobian(ErrorModel(model.robot), q, x)
    regular = torch.linalg.svdvals(jac)[:, -1] > 0.05
    assert regular.double().mean() > 0.5
    solved = _solve_residual(model, x, errors, q, 5)[regular].norm(dim=-1)  # the model source: the whole chain's pose
    # each pose steps until its position and rotation errors are below the graph's tolerance
    assert float(solved.max()) < math.hypot(CONVERGED_POSITION_M, CONVERGED_ORIENTATION_RAD)
    position_first = _solve_residual(model, x, errors, q, None, task="position")[regular]
    assert float(position_first[:, :3].norm(dim=-1).max()) < CONVERGED_POSITION_M  # the default task
    monkeypatch.setattr(compensator_module, "command_jacobian_t",
                        lambda pose, frames, slope: compensator_module.geometric_jacobian_t(pose, frames))
    without_slope = _solve_residual(model, x, errors, q, 5)[regular].norm(dim=-1)
    assert float(without_slope.median()) > 1e-9  # at most the same five steps, no slope: far from solved


@pytest.fixture(scope="module")
def sagging(tmp_path_factory):
    """A twin with gravity sag and gear errors, fitted with both joint-space terms, and its export."""
    twin = Twin.create(TwinConfig(seed=5, gravity=True, gear=True))
    train = twin.sample(300, torch.Generator().manual_seed(6))
    result = fit(twin.robot, train, FitConfig(residual="none", progress=False, gravity_compliance="wrist", joint_harmonics="first"))
    root = tmp_path_factory.mktemp("sag")
    folder = save_fit(root / "model", twin.robot, train, result, {})
    return twin, folder, export_model(folder, root / "export"), root / "export"


def served(folder):
    """The model as the exported files serve it: the default production TCP, the flange."""
    return production_view(load_model(folder), tcp_transform(None, None))


def test_export_carries_the_joint_space_errors_with_onnxruntime_parity(sagging):
    _twin, folder, manifest, out = sagging
    assert manifest["stages"]["gravity_compliance"] and manifest["stages"]["joint_harmonics"]
    # fitted to positions: the terms correct the position, the geometry orients the tool, and the files say so
    assert manifest["solver"]["orientation_source"] == "geometry"
    assert "MDH table alone" in (out / "README.md").read_text()
    stored = served(folder)
    q = stored.robot.sample_joints(2000, torch.Generator().manual_seed(8))
    graphs = build_graphs(stored)
    with torch.no_grad():
        monitor = graphs["monitor"](q)
        command = graphs["compensator"](q)
    # the monitor is the stored model's own prediction (joint errors from model_joints)
    expected = (stored.model.base_flange_pose(model_joints(stored, q), stored.x) @ stored.model.flange_from_tool(stored.x))[..., :3, 3]
    assert torch.allclose(monitor, expected - stored.robot.tcp_position(q), rtol=0, atol=1e-13)
    session = ort.InferenceSession(str(out / manifest["files"]["monitor"]), providers=["CPUExecutionProvider"])
    ort_monitor = session.run(None, {session.get_inputs()[0].name: q.numpy()})[0]
    assert np.abs(ort_monitor - monitor.numpy()).max() * 1e3 <= 1e-9  # mm
    session = ort.InferenceSession(str(out / manifest["files"]["compensator"]), providers=["CPUExecutionProvider"])
    ort_command = session.run(None, {session.get_inputs()[0].name: q.numpy()})[0]
    tcp = lambda qq: (stored.model.base_flange_pose(qq, stored.x) @ stored.model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    converged = (tcp(model_joints(stored, command)) - stored.robot.tcp_position(q)).norm(dim=-1) < 1e-9
    assert converged.double().mean() > 0.8
    gap = (tcp(torch.from_numpy(ort_command)) - tcp(command)).norm(dim=-1)[converged] * 1e3
    assert float(gap.max()) <= 1e-9


def test_compensation_with_joint_space_errors_on_the_true_twin(sagging):
    """The sagging twin's true TCP at the exported commands: better than a geometry-only export."""
    from torchcal.compensate.true_robot_check import compensation_on_true_robot

    twin, folder, manifest, out = sagging
    stored = served(folder)
    q = twin.robot.sample_joints(300, torch.Generator().manual_seed(9), margin=math.radians(5))
    true_flange = lambda qq: twin.true_tcp_positions(qq, tcp_transform(None, None))  # noqa: E731
    result = compensation_on_true_robot(stored, build_graphs(stored), out, manifest, q, true_flange)
    assert result["onnx_float64_over_torch"] <= 1.05
    solved = result["torch_on_solved"]["position_rms_mm"]
    # at the flange (the export's default TCP) what is left is the model's own error there
    assert solved <= 1.10 * result["model_own_error"]["position_rms_mm"]
    assert solved < 0.5 * result["uncompensated"]["position_rms_mm"]
    # dropping the joint-space terms from the same model leaves the sag and gear errors in place
    meta = dict(stored.metadata)
    for key in ("gravity_compliance", "joint_harmonics"):
        meta.pop(key)
    rigid = build_graphs(dataclasses.replace(stored, metadata=meta))
    T = stored.model.instrument_from_base(stored.x)
    target = stored.robot.tcp_position(q) @ T[:3, :3].T + T[:3, 3]
    with torch.no_grad():
        miss = (true_flange(rigid["compensator"](q)) - target).norm(dim=-1) * 1e3
        full = (true_flange(build_graphs(stored)["compensator"](q)) - target).norm(dim=-1) * 1e3
    assert float(full.median()) < float(miss.median())


def test_from_stored_keeps_the_joint_space_errors(sagging):
    """Graphs built from a model folder directly carry the same terms as the exported ones."""
    _, folder, _, _ = sagging
    stored = load_model(folder)
    graphs = build_graphs(stored)
    q = stored.robot.sample_joints(200, torch.Generator().manual_seed(10))
    with torch.no_grad():
        assert torch.equal(CompensatorGraph.from_stored(stored)(q), graphs["compensator"](q))
        assert torch.equal(MonitorGraph.from_stored(stored)(q), graphs["monitor"](q))
        rigid = MonitorGraph(stored.model, stored.x)(q)  # without the terms: a different prediction
    assert float((rigid - graphs["monitor"](q)).norm(dim=-1).max()) > 1e-5


def test_learned_joint_model_is_saved_loaded_and_exported_with_onnxruntime_parity(tmp_path):
    """A Fourier series of order 3 and cubic compliance, fitted on a twin that has both: the folder keeps
    them, and the exported monitor and compensator agree with torch to 1e-9 mm (float64)."""
    twin = Twin.create(TwinConfig(seed=5, gravity=True, gear=True, gear_orders=3, compliance_cubic=0.5))
    train = twin.sample(300, torch.Generator().manual_seed(6))
    result = fit(twin.robot, train, FitConfig(residual="none", uncertainty="none", progress=False,
                                              gravity_compliance="elbow+wrist+cubic", joint_harmonics="fourier3"))
    assert result.harmonics.order == 3 and result.harmonics.prior_scale_rad is not None
    folder = save_fit(tmp_path / "model", twin.robot, train, result, {})
    stored = load_model(folder)
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    assert terms.compliance.points == ("elbow", "tcp", "tcp3")
    assert torch.equal(terms.harmonics.coefficients, result.harmonics.coefficients)
    assert terms.harmonics.prior_scale_rad == result.harmonics.prior_scale_rad
    manifest = export_model(folder, tmp_path / "export")
    stored = served(folder)
    q = stored.robot.sample_joints(1000, torch.Generator().manual_seed(8))
    graphs = build_graphs(stored)
    with torch.no_grad():
        monitor, command = graphs["monitor"](q), graphs["compensator"](q)
    expected = (stored.model.base_flange_pose(model_joints(stored, q), stored.x) @ stored.model.flange_from_tool(stored.x))[..., :3, 3]
    assert torch.allclose(monitor, expected - stored.robot.tcp_position(q), rtol=0, atol=1e-13)
    out = tmp_path / "export"
    session = ort.InferenceSession(str(out / manifest["files"]["monitor"]), providers=["CPUExecutionProvider"])
    assert np.abs(session.run(None, {session.get_inputs()[0].name: q.numpy()})[0] - monitor.numpy()).max() * 1e3 <= 1e-9
    session = ort.InferenceSession(str(out / manifest["files"]["compensator"]), providers=["CPUExecutionProvider"])
    ort_command = session.run(None, {session.get_inputs()[0].name: q.numpy()})[0]
    tcp = lambda qq: (stored.model.base_flange_pose(qq, stored.x) @ stored.model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    converged = (tcp(model_joints(stored, command)) - stored.robot.tcp_position(q)).norm(dim=-1) < 1e-9
    assert converged.double().mean() > 0.8
    assert float((tcp(torch.from_numpy(ort_command)) - tcp(command)).norm(dim=-1)[converged].max()) * 1e3 <= 1e-9


def test_a_production_tcp_keeps_the_gravity_point_the_terms_were_fitted_at(sagging):
    """The 'tcp' gravity term describes the calibration's payload where it was measured: a view ending in a
    production TCP 150 mm further and turned must deflect the joints as the fitted model does, in torch and
    in the graphs (its torques used to follow the production TCP)."""
    from torchcal.compensate.compensator import _TwoModels

    _twin, folder, _manifest, _out = sagging
    stored = load_model(folder)
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    assert terms.compliance is not None and "tcp" in terms.compliance.points
    view = production_view(stored, tcp_transform([30.0, -20.0, 150.0], [10.0, 80.0, -30.0]))
    q = stored.robot.sample_joints(300, torch.Generator().manual_seed(12))
    fitted = model_joints(stored, q) - q
    assert float(fitted.abs().max()) > 1e-5
    torch.testing.assert_close(model_joints(view, q) - q, fitted, rtol=0, atol=1e-13)
    graph = _TwoModels(view.model, view.x, None, torch.float64, "cpu", JointSpaceErrors.from_metadata(view.metadata))
    nominal, nominal_frames = graph.nominal(q, with_frames=True)
    point = nominal[:, 0, :3, 3] + (nominal[:, 0, :3, :3] @ graph.gravity_point_shift)[..., 0]
    dq, _ = graph.joint_errors(q, nominal_frames[:, 0], point)
    torch.testing.assert_close(dq, fitted, rtol=0, atol=1e-13)
    # the same view without the pinned point moves the torques with the TCP: a different deflection
    unpinned = dataclasses.replace(view, metadata={**view.metadata, **JointSpaceErrors(
        dataclasses.replace(JointSpaceErrors.from_metadata(view.metadata).compliance, tcp_point=None),
        terms.harmonics).to_metadata()})
    assert float((model_joints(unpinned, q) - q - fitted).abs().max()) > 1e-6
