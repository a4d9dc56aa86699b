"""What an export measures of its own graphs before it is trusted.

* :func:`float32_budget`: the float32 files run by onnxruntime against the float64 torch graphs
  (compensated TCP and monitor output, mm) on poses uniform within the joint limits;
* :func:`convergence_report`: what the fixed Newton steps reach, by stratum (regular, near a wrist
  singularity, near a position singularity; thresholds :data:`WRIST_SINGULAR_BELOW`,
  :data:`POSITION_SINGULAR_BELOW_M`, :data:`SOLVABLE_ABOVE_M`).

Both go into the export's manifest (:mod:`torchcal.compensate.export`).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.compensate.graphs import (
    GRAPHS,
    compensator_of,
    has_wrench_input,
)
from torchcal.compensate.onnx_checks import ort_feeds, ort_session, unsolved_distance_m
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian

BUDGET_POSES = 10_000
DEFAULT_BUDGET_WRENCH = {"max_force_n": 300.0, "max_torque_nm": 30.0}


def sample_wrenches(n: int, max_force_n: float, max_torque_nm: float, generator: torch.Generator) -> torch.Tensor:
    """Random wrenches ``(n, 6)`` (N, N m): uniform directions, magnitudes uniform up to the maxima."""
    directions = torch.randn(n, 2, 3, generator=generator, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    size = torch.rand(n, 2, 1, generator=generator, dtype=torch.float64) * torch.tensor([[max_force_n], [max_torque_nm]])
    return (directions * size).reshape(n, 6)


def budget_wrenches(stored, n: int, generator: torch.Generator) -> torch.Tensor:
    """Wrenches for the float32 budget: up to the largest force and moment of the stiffness data."""
    loads = (stored.stiffness.metadata.get("training_wrench") if stored.stiffness is not None else None) or DEFAULT_BUDGET_WRENCH
    return sample_wrenches(n, loads["max_force_n"], loads["max_torque_nm"], generator)


def float32_budget(graphs: dict[str, torch.nn.Module], out_dir: Path, stored, n_poses: int = BUDGET_POSES, seed: int = 0) -> dict:
    """Float32 error of the exported files against the float64 torch graphs, measured in mm.

    Poses: ``n_poses`` uniform within the joint limits. Compensator: 3-D distance between the
    calibrated TCP at the float32 ORT command and at the float64 torch command. Monitor: 3-D
    distance of the predicted errors.
    """
    gen = torch.Generator().manual_seed(seed)
    q = stored.robot.sample_joints(n_poses, gen)
    loaded = has_wrench_input(graphs)
    wrench = budget_wrenches(stored, n_poses, gen) if loaded else None
    args = (q, wrench) if loaded else (q,)
    with torch.no_grad():
        qc64 = graphs["compensator"](*args)
        mon64 = graphs["monitor"](*args)
    w32 = wrench.numpy() if wrench is not None else None
    session = ort_session(out_dir / GRAPHS["compensator_f32"][0])
    qc32 = torch.from_numpy(session.run(None, ort_feeds(session, q.float().numpy(), w32))[0]).double()
    session = ort_session(out_dir / GRAPHS["monitor_f32"][0])
    mon32 = torch.from_numpy(session.run(None, ort_feeds(session, q.float().numpy(), w32))[0]).double()
    model = stored.model
    tcp = lambda qq: model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x)  # noqa: E731
    d_cmd = (tcp(qc32)[..., :3, 3] - tcp(qc64)[..., :3, 3]).norm(dim=-1) * 1e3
    d_mon = (mon32 - mon64).norm(dim=-1) * 1e3
    budget = {
        "n_poses": n_poses,
        "sampling": f"uniform within joint limits, seed {seed}",
        "compensator_tcp_mm": {"max": float(d_cmd.max()), "p99": float(d_cmd.quantile(0.99)), "median": float(d_cmd.median())},
        "compensator_joint_rad_max": float((qc32 - qc64).abs().max()),
        "monitor_mm": {"max": float(d_mon.max()), "p99": float(d_mon.quantile(0.99)), "median": float(d_mon.median())},
    }
    if loaded:
        budget["wrench_sampling"] = "uniform directions, magnitudes uniform up to the stiffness data's largest force and moment"
    return budget


WRIST_SINGULAR_BELOW = 0.02
"""Wrist stratum of the convergence report: smallest singular value of the last three joints'
angular Jacobian below this (for a spherical wrist ``|sin q5|``: about 1.1 deg from alignment)."""
POSITION_SINGULAR_BELOW_M = 0.01
"""Position-singular stratum: smallest singular value of the TCP position Jacobian below 10 mm/rad."""
SOLVABLE_ABOVE_M = 0.001
"""Poses whose position Jacobian keeps a singular value above 1 mm/rad must be solved to 1 um."""


def singular_values(robot, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sigma_position, sigma_wrist)`` ``(B,)`` of the nominal robot at ``q``: the smallest singular
    value of the TCP position Jacobian (m/rad) and of the last three joints' angular Jacobian (rad/rad)."""
    model = ErrorModel(robot)
    _, jac = geometric_jacobian(model, q, model.nominal_vector())
    return torch.linalg.svdvals(jac[:, :3, :])[:, -1], torch.linalg.svdvals(jac[:, 3:, -3:])[:, -1]


def wrist_singular_samples(robot, n: int, generator: torch.Generator, degrees: float = 1.0, margin: float = 0.0) -> torch.Tensor:
    """``(n, N)`` joints uniform within the limits (``margin`` rad inside) but the second-to-last
    joint within ``+-degrees`` of zero: the wrist singularity of 6-R wrists and of 7-joint arms."""
    q = robot.sample_joints(n, generator, margin=margin)
    limits = robot.joint_limits.to(torch.float64)
    wrist = (torch.rand(n, generator=generator, dtype=torch.float64) * 2 - 1) * math.radians(degrees)
    q[:, -2] = wrist.clamp(limits[-2, 0], limits[-2, 1])
    return q


def _stratum(miss_mm: torch.Tensor, turn: torch.Tensor, joint: torch.Tensor, solvable: torch.Tensor, out_err_mm: torch.Tensor,
             added: torch.Tensor) -> dict:
    """Summary of one stratum: unsolved position (mm), orientation deviation (rad), joint moves (rad),
    and ``added``: how much further (rad) the command turns the tool from the nominal orientation
    than the nominal command does (the price of holding the position where only the wrist can)."""
    n = int(miss_mm.numel())
    if n == 0:
        return {"n_poses": 0}
    return {
        "n_poses": n,
        "unsolved_tcp_mm": {"median": float(miss_mm.median()), "p99": float(miss_mm.quantile(0.99)), "max": float(miss_mm.max())},
        "share_within_1um": float((miss_mm <= 1e-3).double().mean()),
        "n_solvable": int(solvable.sum()),
        "solvable_share_within_1um": float((miss_mm[solvable] <= 1e-3).double().mean()) if bool(solvable.any()) else None,
        "orientation_deviation_rad": {"median": float(turn.median()), "p99": float(turn.quantile(0.99)), "max": float(turn.max())},
        "largest_joint_correction_rad": float(joint.max()),
        "tool_turn_added_rad": {"median": float(added.median()), "p99": float(added.quantile(0.99)), "max": float(added.max())},
        "share_tool_turn_added_above_1_deg": float((added > math.radians(1.0)).double().mean()),
        "residual_output_error": {"position_mm_max": float(out_err_mm.max())},
    }


def convergence_report(graphs: dict[str, torch.nn.Module], stored, n_poses: int = BUDGET_POSES, seed: int = 1) -> dict:
    """What the float64 compensator's commands reach, over the joint range and near singularities.

    Poses: ``n_poses`` uniform within the joint limits, and as many again with the second-to-last
    joint within +-1 deg (the wrist singularity of 6-R wrists and of 7-joint arms; with the
    budget's wrenches for a loaded model). For each command: the position the steps leave
    unsolved, ``|p_nom(q_c) + monitor(q_c) - p_nom(q_t)|`` (mm, through the monitor
    graph, and compared with the compensator's own ``residual`` output), and the orientation
    deviation of the calibrated tool from the nominal target (rad, the ``residual`` output: the
    compensator computes it through the kinematics at ``q_c``), and how much further than the
    nominal command's that deviation is (where the position can be held only by turning the wrist:
    near the wrist singularity, and near the arm's elbow or shoulder singularity, where the TCP
    Jacobian stays regular through the wrist's lever). Strata: all uniform poses; wrist
    singular (:data:`WRIST_SINGULAR_BELOW`); position singular (:data:`POSITION_SINGULAR_BELOW_M`).
    A pose counts as solvable where the position Jacobian's smallest singular value exceeds
    :data:`SOLVABLE_ABOVE_M`.
    """
    gen = torch.Generator().manual_seed(seed)
    robot = stored.robot
    uniform = robot.sample_joints(n_poses, gen)
    q = torch.cat([uniform, wrist_singular_samples(robot, n_poses, gen)])
    graph = compensator_of(graphs)
    wrench = budget_wrenches(stored, len(q), gen) if has_wrench_input(graphs) else None
    with torch.no_grad():
        q_c, residual = graph.solve(q, wrench)
    miss = unsolved_distance_m(graphs, robot, q, q_c, wrench) * 1e3
    turn = residual[:, 1]
    with torch.no_grad():
        added = turn - graph.nominal_residual(q, wrench)[:, 1]
    out_err = (residual[:, 0] * 1e3 - miss).abs()
    joint = (q_c - q).abs().amax(-1)
    sigma_p, sigma_w = singular_values(robot, q)
    solvable = sigma_p > SOLVABLE_ABOVE_M
    parts = {
        "uniform": torch.arange(len(q)) < n_poses,
        "wrist_singular": sigma_w < WRIST_SINGULAR_BELOW,
        "position_singular": sigma_p < POSITION_SINGULAR_BELOW_M,
    }
    strata = {name: _stratum(miss[m], turn[m], joint[m], solvable[m], out_err[m], added[m]) for name, m in parts.items()}
    return {
        "n_poses": n_poses,
        "sampling": (f"uniform within joint limits (seed {seed}), and {n_poses} more with joint {robot.dof - 1} "
                     "within +-1 deg; strata by the nominal robot's singular values"),
        "task": graph.task,
        "iterations": graph.iterations,
        "thresholds": {"wrist_singular_below": WRIST_SINGULAR_BELOW, "position_singular_below_m_per_rad": POSITION_SINGULAR_BELOW_M,
                       "solvable_above_m_per_rad": SOLVABLE_ABOVE_M},
        "strata": strata,
        # the uniform stratum's headline figures, where older readers look for them
        "unsolved_tcp_mm": {**strata["uniform"]["unsolved_tcp_mm"], "p90": float(miss[parts["uniform"]].quantile(0.9))},
        "share_within_1um": strata["uniform"]["share_within_1um"],
        "largest_joint_correction_rad": strata["uniform"]["largest_joint_correction_rad"],
    }


def regular_mask(robot, q: torch.Tensor) -> torch.Tensor:
    """``(n,)`` bool: the poses of ``q`` not near a singularity (outside the convergence report's
    singular strata): near one any compensator's step is large by the geometry, not by the model."""
    sigma_p, sigma_w = singular_values(robot, q.to(torch.float64))
    return (sigma_p >= POSITION_SINGULAR_BELOW_M) & (sigma_w >= WRIST_SINGULAR_BELOW)


def regular_poses(robot, q: torch.Tensor) -> torch.Tensor:
    """``q`` less the poses near a singularity (:func:`regular_mask`)."""
    return q[regular_mask(robot, q)]
