"""A start for the refinement when the scans have no pure translations (no closed form).

The extrinsics rotation is searched over the 24 rotations of the cube, each turned about its
z axis by 0, 30 and 60 deg (72 starts, no two more than ~35 deg from the nearest one); from each
start ``t = 0`` and the planes fitted to the resulting points, a short Levenberg-Marquardt run on a
subsample of the points (at most ``points_per_scan`` per scan) is made, and the lowest cost wins.
The full refinement then starts from it. It is a fallback: the closed form with its
degeneracy checks is the method of choice.
"""

from __future__ import annotations

import itertools
import math
import warnings

import torch

from torchcal.core.errors import DataError
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.instruments.profile.data import ProfileData
from torchcal.instruments.profile.model import base_points, fit_planes
from torchcal.instruments.profile.refine import ProfileProblem
from torchcal.kinematics import transforms as tf


def cube_rotations(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The 24 proper rotations mapping the coordinate axes onto themselves, ``(24, 3, 3)``."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = torch.zeros(3, 3, dtype=dtype)
            for i, j in enumerate(perm):
                m[i, j] = signs[i]
            if torch.det(m) > 0:
                out.append(m)
    return torch.stack(out)


def _subsample(data: ProfileData, per_scan: int) -> ProfileData:
    keep = torch.zeros(data.n_points, dtype=torch.bool)
    for s in range(data.n_scans):  # once per scan, to pick evenly spread points
        idx = (data.point_scan == s).nonzero().squeeze(-1)
        step = max(1, math.ceil(len(idx) / per_scan))
        keep[idx[::step]] = True
    return ProfileData(
        q=data.q, plane=data.plane, point_scan=data.point_scan[keep], uw=data.uw[keep],
        scan_labels=data.scan_labels, plane_labels=data.plane_labels, scan_lines=data.scan_lines, path=data.path,
    )


def search_start(
    data: ProfileData, T_base_flange: torch.Tensor, *, points_per_scan: int = 12, iterations: int = 12
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best ``(R, t, normals, offsets)`` over the multi-start set (see the module docstring)."""
    small = _subsample(data, points_per_scan)
    T = T_base_flange.to(data.uw)
    point_plane = small.point_plane()
    starts = [c @ tf.rot_z(torch.tensor(math.radians(a), dtype=torch.float64)) for c in cube_rotations() for a in (0.0, 30.0, 60.0)]
    found = []
    solver = LevenbergMarquardt(max_iterations=iterations)
    for R0 in starts:
        t0 = torch.zeros(3, dtype=torch.float64)
        normals, offsets, _ = fit_planes(base_points(T, small.point_scan, small.uw, R0, t0), point_plane, small.n_planes)
        problem = ProfileProblem(small, T, R0, normals)
        try:
            sol = solver.solve(problem, problem.initial(t0, offsets))
        except torch.linalg.LinAlgError:
            continue
        found.append((sol.cost, problem.unpack(sol.x)))
    if not found:
        raise DataError("no start of the rotation search converged; the scans do not determine the sensor pose", path=data.path)
    found.sort(key=lambda item: item[0])
    best_cost, (R, t, _, _) = found[0]
    # Another minimum as good as the best but elsewhere: these scans cannot tell them apart.
    for cost, (R_other, t_other, _, _) in found[1:]:
        if cost > 2.0 * best_cost + 1e-18:
            break
        if math.degrees(float(tf.rotation_angle(R.T @ R_other))) > 1.0:
            warnings.warn(
                f"{data.path}: the rotation search found two equally good sensor poses "
                f"(t differs by {float((t - t_other).norm()) * 1e3:.1f} mm); pure translations at >= 3 plane "
                "orientations make the solution unique (closed form)",
                stacklevel=2,
            )
            break
    normals, offsets, _ = fit_planes(base_points(T, data.point_scan, data.uw, R, t), data.point_plane(), data.n_planes)
    return R, t, normals, offsets
