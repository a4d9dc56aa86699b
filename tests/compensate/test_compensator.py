"""The compensator and monitor graphs against independent kinematics (torch side only)."""

import math

import pytest
import torch
from known_cases import KnownResidual, nominal_tcp_pose, residual_value

from torchcal.compensate.compensator import (
    CONVERGED_ORIENTATION_RAD,
    CONVERGED_POSITION_M,
    CompensatorGraph,
    MonitorGraph,
)
from torchcal.compensate.export_checks import wrist_singular_samples
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import pose_error
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stages.store import load_model


def regular_poses(stored, n, seed, min_singular=0.05):
    """Random poses whose Jacobian is far from singular, 2 deg inside the joint limits (the
    compensator keeps its commands within the limits, so a pose at a limit may not be reachable)."""
    q = stored.robot.sample_joints(4 * n, torch.Generator().manual_seed(seed), margin=math.radians(2))
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    return q[torch.linalg.svdvals(jac)[:, -1] > min_singular][:n]


@pytest.fixture(scope="module")
def stored(model_dir):
    return load_model(model_dir)


def test_compensator_reaches_the_nominal_pose_with_the_calibrated_model(stored):
    q = regular_poses(stored, 500, seed=1)
    base_model = ErrorModel(stored.robot)  # identity instrument frame: calibrated base frame
    target = nominal_tcp_pose(stored.robot, q)
    before = pose_error(target, base_model.tcp_pose(q, stored.x))
    assert before[:, :3].norm(dim=-1).median() > 2e-4  # there is something to correct
    with torch.no_grad():
        q_c = CompensatorGraph(stored.model, stored.x)(q)
    after = pose_error(target, base_model.tcp_pose(q_c, stored.x))
    # every regular pose ends converged: position and orientation within the graph's tolerances
    assert after[:, :3].norm(dim=-1).max() < CONVERGED_POSITION_M  # m
    assert after[:, 3:].norm(dim=-1).max() < CONVERGED_ORIENTATION_RAD  # rad
    with torch.no_grad():
        q_tight = CompensatorGraph(stored.model, stored.x, converged_position_m=1e-12, converged_orientation_rad=1e-12)(q)
    after = pose_error(target, base_model.tcp_pose(q_tight, stored.x))
    assert after[:, :3].norm(dim=-1).max() < 1e-12  # tighter tolerances: the position to rounding
    with torch.no_grad():
        q_pose = CompensatorGraph(stored.model, stored.x, task="pose")(q)
    after = pose_error(target, base_model.tcp_pose(q_pose, stored.x))
    assert after[:, :3].norm(dim=-1).max() < CONVERGED_POSITION_M and after[:, 3:].norm(dim=-1).max() < CONVERGED_ORIENTATION_RAD


def test_residual_head_is_compensated_with_the_patent_sign(stored):
    """p_cal(q_c) + r(q_c) = p_t, and p_nom(q_c) = p_t - dp(q_c) with dp the monitor output."""
    q = regular_poses(stored, 300, seed=2)
    base_model = ErrorModel(stored.robot)
    target = nominal_tcp_pose(stored.robot, q)
    with torch.no_grad():
        q_c = CompensatorGraph(stored.model, stored.x, KnownResidual())(q)
        dp = MonitorGraph(stored.model, stored.x, KnownResidual())(q_c)
    reached = base_model.tcp_position(q_c, stored.x) + residual_value(q_c)
    assert (reached - target[:, :3, 3]).norm(dim=-1).max() < 1e-9
    # T_c = T_t - dT: the nominal robot at the corrected command sits at the target minus the error
    assert (stored.robot.tcp_position(q_c) - (target[:, :3, 3] - dp)).norm(dim=-1).max() < 1e-9
    # the patents' single evaluation of dT at q_t agrees to second order only
    with torch.no_grad():
        dp_t = MonitorGraph(stored.model, stored.x, KnownResidual())(q)
    assert ((dp - dp_t).norm(dim=-1) < 0.05 * dp_t.norm(dim=-1)).all()


def test_monitor_is_calibrated_minus_nominal(stored):
    q = stored.robot.sample_joints(1000, torch.Generator().manual_seed(3))
    expected = ErrorModel(stored.robot).tcp_position(q, stored.x) + residual_value(q) - stored.robot.tcp_position(q)
    with torch.no_grad():
        got = MonitorGraph(stored.model, stored.x, KnownResidual())(q)
        got32 = MonitorGraph(stored.model, stored.x, KnownResidual(), dtype=torch.float32)(q.float())
    assert (got - expected).abs().max() < 1e-14
    assert (got32.double() - expected).norm(dim=-1).max() < 1e-6  # m


def test_damping_bounds_the_step_at_a_wrist_singularity(stored):
    q = regular_poses(stored, 50, seed=4)
    q[:, 4] = 0.0  # q5 = 0: axes 4 and 6 align
    for task in ("position", "pose"):
        graph = CompensatorGraph(stored.model, stored.x, task=task)
        with torch.no_grad():
            q_c = graph(q)
        assert torch.isfinite(q_c).all()
        # no joint moves more than max_step per step, whatever the pose
        assert (q_c - q).abs().max() <= graph.iterations * float(graph.max_step) + 1e-12


def near_wrist_singularity(stored, n, seed, degrees=1.0):
    """Random poses with |q5| < ``degrees`` whose position Jacobian keeps sigma_min > 1 mm/rad."""
    q = wrist_singular_samples(stored.robot, 2 * n, torch.Generator().manual_seed(seed), degrees)
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    return q[torch.linalg.svdvals(jac[:, :3, :])[:, -1] > 1e-3][:n]


def test_position_task_solves_the_position_near_the_wrist_singularity(stored):
    """|q5| < 1 deg: the position reached to 1 um (in fact to rounding), the orientation deviation
    reported by the graph's second output as the calibrated model has it."""
    q = near_wrist_singularity(stored, 400, seed=6)
    base_model = ErrorModel(stored.robot)
    target = nominal_tcp_pose(stored.robot, q)
    graph = CompensatorGraph(stored.model, stored.x)
    with torch.no_grad():
        q_c, residual = graph.solve(q)
    after = pose_error(target, base_model.tcp_pose(q_c, stored.x))
    assert after[:, :3].norm(dim=-1).max() < 1e-6  # m: 1 um on every pose
    assert (residual[:, 0] - after[:, :3].norm(dim=-1)).abs().max() < 1e-7  # m
    assert (residual[:, 1] - after[:, 3:].norm(dim=-1)).abs().max() < 1e-6  # rad
    # the 6-D task cannot do this: it trades position for orientation there
    with torch.no_grad():
        q_pose = CompensatorGraph(stored.model, stored.x, task="pose")(q)
    pose_task = pose_error(target, base_model.tcp_pose(q_pose, stored.x))[:, :3].norm(dim=-1)
    assert pose_task.max() > 1e-5


def test_commands_stay_within_the_joint_limits(stored):
    limits = stored.robot.joint_limits
    q = stored.robot.sample_joints(300, torch.Generator().manual_seed(7))
    q[:, 1] = limits[1, 1]  # joint 2 commanded at its upper limit
    for task in ("position", "pose"):
        with torch.no_grad():
            q_c = CompensatorGraph(stored.model, stored.x, task=task)(q)
        assert ((q_c >= limits[:, 0]) & (q_c <= limits[:, 1])).all()


def test_iteration_count_is_what_converges(stored):
    """The default count of either task reaches 1e-9 m on regular poses (the wrist and position
    singular strata that set the position task's count are in the manifest's convergence)."""
    q = regular_poses(stored, 500, seed=5)
    target = nominal_tcp_pose(stored.robot, q)[:, :3, 3]
    for task in ("position", "pose"):
        with torch.no_grad():
            q_c = CompensatorGraph(stored.model, stored.x, task=task)(q)
        assert (ErrorModel(stored.robot).tcp_position(q_c, stored.x) - target).norm(dim=-1).max() < 1e-9, task


def test_a_command_the_steps_cannot_improve_is_returned_unchanged(stored):
    """Joint 2 at its limit and the correction pointing beyond it: the graph never returns a
    command that the model says lands further from the target than the nominal one."""
    limits = stored.robot.joint_limits
    q = stored.robot.sample_joints(2000, torch.Generator().manual_seed(8))
    q[:, 1] = limits[1, 1]
    graph = CompensatorGraph(stored.model, stored.x)
    base_model = ErrorModel(stored.robot)
    target = nominal_tcp_pose(stored.robot, q)[:, :3, 3]
    with torch.no_grad():
        q_c, residual = graph.solve(q)
    before = (base_model.tcp_position(q, stored.x) - target).norm(dim=-1)
    after = (base_model.tcp_position(q_c, stored.x) - target).norm(dim=-1)
    assert (after <= before + 1e-12).all()
    kept = (q_c == q).all(-1)
    assert kept.any() and (~kept).any()  # some commands cannot be improved there, most can
    assert (residual[kept, 0] - before[kept]).abs().max() < 1e-12  # and the graph says so


def _steps_taken(graph, q):
    """Steps each pose takes, over both phases (the torch reference of the exported Loops)."""
    with torch.no_grad():
        weights, _, q_it, jac_t, error = graph.start(q, None)
        count = torch.zeros(len(q), dtype=torch.long)
        for orientation, most in graph.phases:
            score = graph.score(error, orientation)
            for _ in range(most):
                count += (score[:, 0] >= 1.0).long()
                _, q_it, jac_t, error, score = graph.iterate(q_it, jac_t, error, score, weights, None, orientation)
    return count


def test_each_pose_steps_until_it_converges_whatever_its_batch(stored):
    """A converged pose keeps its command while its batch steps on: a pose alone and in a batch
    (here with a wrist-singular pose and one pinned at a joint limit, which take more steps) get
    the same command; regular poses stop after two or three steps, the pinned one takes all six."""
    graph = CompensatorGraph(stored.model, stored.x)
    pinned = stored.robot.sample_joints(200, torch.Generator().manual_seed(11))
    pinned[:, 1] = stored.robot.joint_limits[1, 1]  # joint 2 at its limit: some corrections point beyond it
    with torch.no_grad():
        unsolved = graph.solve(pinned)[1][:, 0] > 1e-6
    q = torch.cat([regular_poses(stored, 30, seed=9), near_wrist_singularity(stored, 5, seed=10), pinned[unsolved][:1]])
    with torch.no_grad():
        together, residual = graph.solve(q)
        alone = torch.cat([graph.solve(row[None])[0] for row in q])
    assert (together - alone).abs().max() < 1e-12  # rad
    steps = _steps_taken(graph, q)
    assert steps[:30].max() <= 3 and steps[:30].min() >= 2
    assert int(steps[-1]) == graph.iterations
    # and they have converged where they stopped
    assert residual[:30, 0].max() < CONVERGED_POSITION_M and residual[:30, 1].max() < 10 * CONVERGED_ORIENTATION_RAD


@pytest.fixture(scope="module")
def flange_served(stored):
    """The model as an export serves it by default (the flange as TCP), and poses over the joint range and near the wrist singularity."""
    from torchcal.compensate.production_tcp import production_view, tcp_transform

    gen = torch.Generator().manual_seed(21)
    q = torch.cat([stored.robot.sample_joints(1500, gen), wrist_singular_samples(stored.robot, 1500, gen)])
    return production_view(stored, tcp_transform(None, None)), q


def test_tool_length_keeps_the_nominal_command_where_the_corrected_one_turns_a_tool_further_off(flange_served):
    view, q = flange_served
    length = 0.1
    held, guarded = CompensatorGraph.from_stored(view), CompensatorGraph.from_stored(view, tool_length=length)
    with torch.no_grad():
        q_held, after = held.solve(q)
        q_guarded, residual = guarded.solve(q)
        before = held.nominal_residual(q)
    # by the model's bound |e_p| + L theta: the corrected command where it is no worse than the nominal one
    kept = after[:, 0] + length * after[:, 1] > before[:, 0] + length * before[:, 1]
    assert 0 < int(kept.sum()) < 0.2 * len(q)  # some poses, near singularities; most keep their correction
    torch.testing.assert_close(q_guarded, torch.where(kept.unsqueeze(-1), q, q_held), rtol=0, atol=0)
    torch.testing.assert_close(residual, torch.where(kept.unsqueeze(-1), before, after), rtol=0, atol=0)
    # the default judges the TCP alone: the held commands are the position-first solution wherever it helps the TCP
    assert float(after[:, 0].median()) < 1e-9


def test_tool_length_bounds_where_a_tool_beyond_the_flange_lands_on_the_true_robot(flange_served, twin):
    """On the twin's true robot, a point 100 mm beyond the flange: the position-first command can
    swing it by millimetres near singular poses to hold the flange; with tool_length 100 mm the
    worst case falls, at a small cost to the flange itself."""
    view, q = flange_served
    T_cal = view.model.instrument_from_base(view.x)
    tip = torch.eye(4, dtype=torch.float64)
    tip[2, 3] = 0.1

    def errors(q_c):
        true = twin.T_instrument_base() @ twin.model.base_flange_pose(q_c, twin.x_true)
        target = T_cal @ view.robot.flange_pose(q)
        return ((true @ tip)[:, :3, 3] - (target @ tip)[:, :3, 3]).norm(dim=-1), (true - target)[:, :3, 3].norm(dim=-1)

    with torch.no_grad():
        tip_held, flange_held = errors(CompensatorGraph.from_stored(view).solve(q)[0])
        tip_guarded, flange_guarded = errors(CompensatorGraph.from_stored(view, tool_length=0.1).solve(q)[0])
    assert float(tip_guarded.max()) < 0.5 * float(tip_held.max())
    assert float(tip_guarded.pow(2).mean()) < float(tip_held.pow(2).mean())
    assert float(flange_guarded.pow(2).mean().sqrt()) < 1.5 * float(flange_held.pow(2).mean().sqrt())
