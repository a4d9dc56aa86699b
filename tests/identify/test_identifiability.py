"""Identifiability: known structural dependencies of a 6R arm measured by position only."""

from __future__ import annotations

import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.identifiability import analyze
from torchcal.identify.pose_selection import select_poses_d_optimal
from torchcal.identify.problem import CalibrationProblem
from torchcal.kinematics.error_model import ErrorModel


def _jacobian(robot, q, model=None):
    model = model or ErrorModel(robot)
    x = model.nominal_vector()
    free = torch.nonzero(model.default_active()).squeeze(-1)
    problem = CalibrationProblem(model, Measurements(q=q, position=robot.tcp_position(q)), free)
    _, jac = problem.jacobian(x)
    return jac, problem.names


def test_base_frame_absorbs_row_one_and_tool_absorbs_d6(robot, generator):
    jac, names = _jacobian(robot, robot.sample_joints(100, generator))
    report = analyze(jac, names)
    assert {"alpha1", "a1", "theta1", "d1", "d6", "theta6"} <= set(report.dependent)
    assert report.dependent["d1"][0][0] == "base_z"
    assert report.dependent["d6"][0][0] == "tool_z"
    assert report.rank == len(report.base_set)
    # 4R + 6 - 3 (no tool orientation) = 27 minus the wrist's two position-only dependencies: with the
    # tool point on axis 6, tilting axis 6 about x5 (alpha6) moves it as d5 does, shifting it along x5
    # (a6) as turning joint 5's zero (theta5) does
    assert len(report.base_set) == 25
    assert report.dependent["alpha6"][0][0] == "d5" and report.dependent["a6"][0][0] == "theta5"
    assert report.condition_number < 100


def test_too_little_excitation_is_reported(robot, generator):
    """Moving joint 2 alone cannot tell most parameters apart: they must be named."""
    q = torch.zeros(40, 6, dtype=torch.float64)
    q[:, 1] = torch.linspace(-1.0, 0.5, 40, dtype=torch.float64)
    jac, names = _jacobian(robot, q)
    report = analyze(jac, names)
    assert len(report.dependent) > 15
    assert "theta4" in report.dependent


def test_d_optimal_selection_beats_random(robot, generator):
    candidates = robot.sample_joints(600, generator)
    jac, names = _jacobian(robot, candidates)
    report = analyze(jac, names)
    keep = [names.index(n) for n in report.base_set]
    per_pose = jac.reshape(600, 3, -1)[:, :, keep]
    k = 15
    chosen = select_poses_d_optimal(per_pose, k, generator=generator)
    assert len(set(chosen.tolist())) == k

    def logdet(idx):
        j = per_pose[idx].reshape(-1, len(keep))
        j = j / per_pose.reshape(-1, len(keep)).norm(dim=0)
        return float(torch.logdet(j.T @ j))

    random_scores = [logdet(torch.randperm(600, generator=generator)[:k]) for _ in range(20)]
    assert logdet(chosen) > max(random_scores)


def test_selected_poses_calibrate_better_than_random_ones(generator):
    """On the twin, k D-optimal poses give a lower held-out error than k random poses."""
    import statistics

    from torchcal.identify.calibrate import calibrate
    from torchcal.identify.pose_selection import select_poses_for_robot
    from torchcal.sim.twin import Twin, TwinConfig

    twin = Twin.create(TwinConfig(seed=11))
    candidates = twin.robot.sample_joints(1500, generator, margin=0.08)
    test_q = twin.robot.sample_joints(400, generator, margin=0.08)
    truth = twin.true_positions(test_q)
    k = 30

    def held_out_rms(q):
        data = Measurements(q=q, position=twin.measure(q, generator))
        result = calibrate(twin.robot, data)
        return float((result.model.tcp_position(test_q, result.x) - truth).norm(dim=-1).pow(2).mean().sqrt())

    chosen = select_poses_for_robot(twin.robot, candidates, k, generator=generator)
    selected = statistics.median(held_out_rms(candidates[chosen]) for _ in range(3))
    random = statistics.median(held_out_rms(candidates[torch.randperm(1500, generator=generator)[:k]]) for _ in range(5))
    assert selected < random
