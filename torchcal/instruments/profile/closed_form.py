"""Closed-form extrinsics of a flange-mounted profile sensor from an unknown plane target.

Model (see :mod:`torchcal.instruments.profile.model`): a point ``(u, w)`` of scan ``j`` lies on its
placement's plane ``n . x = c`` (``base`` frame), so with the flange pose ``(R_j, p_j)``

    n . R_j (u r1 + w r3 + t) + n . p_j = c.                                  (1)

**Rotation from pure translations.** Scans of one placement taken at one flange orientation
``R_g`` (pure translations) share ``m_g = R_g^T n``, the plane normal in the ``flange`` frame.
(1) becomes linear and homogeneous in six numbers per group:

    a_g u + b_g w + n . p_j + (m_g . t - c) = 0,   a_g = m_g . r1,  b_g = m_g . r3.   (2)

Every point gives one row ``[u, w, p_j^T, 1]``; the right singular vector of the smallest
singular value (columns scaled) gives ``(a_g, b_g, n, m_g . t - c)`` up to one factor, fixed by
``|n| = 1``. This needs the flange positions ``p_j`` of the group to span 3-D (three
non-coplanar translations, four scans): the translations measure ``n . p_j`` only. Each group
then gives ``m_g = R_g^T n`` and two linear equations on the columns of ``R``:
``m_g . r1 = a_g``, ``m_g . r3 = b_g``. With ``G >= 3`` groups whose normals ``m_g`` are not
coplanar (three plane orientations seen from the flange: placements, or flange orientations of
one placement), ``r1 = M^+ a`` and ``r3 = M^+ b`` (pseudo-inverse, ``M = [m_g^T]``).
``R = polar([r1, r3 x r1, r3])`` (SVD projection onto SO(3)); the patent's unit-norm version
(columns normalized, ``r2 = r3 x r1``) is reported beside it.

**Translation from rotations.** With ``R`` and the placement normals ``n_P`` known, (1) is linear
in ``t`` and the offsets ``c_P``: one row per point ``[(R_j^T n_P)^T, -e_P] [t; c] =
-n_P . (R_j R s + p_j)``. ``t`` is determined when, per placement, the normals seen from the
flange differ by rotations about at least two non-parallel axes; with rotations about a single
flange axis ``a`` only, ``m_j . a`` is the same for every scan of a placement and ``t`` along
``a`` is confounded with ``c_P``.

Every degenerate motion set raises a :class:`~torchcal.core.errors.DataError` that says what is
missing and what motion to add.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import DataError
from torchcal.instruments.profile.data import ProfileData
from torchcal.instruments.profile.model import (
    base_points,
    fit_planes,
    rotation_from_columns,
    sensor_points,
    unit_columns,
)
from torchcal.kinematics import transforms as tf

# Translations whose out-of-plane extent is below this share of their in-plane extent are coplanar.
COPLANAR_RATIO = 0.02
# Normals (flange frame) whose third singular value is below this share of the first are coplanar.
NORMALS_RATIO = 0.02
# Column-normalized design matrices with a smaller condition reciprocal are rank deficient.
RANK_RATIO = 1e-6


@dataclass
class MotionGroup:
    """Scans of one placement at one flange orientation (pure translations of each other).

    Attributes:
        plane: placement index.
        scans: scan indices.
        R_base_flange: ``(3, 3)`` flange orientation of the first scan.
        translation_extent_mm: singular values ``(3,)`` of the centred flange positions, mm.
    """

    plane: int
    scans: list[int]
    R_base_flange: torch.Tensor
    translation_extent_mm: list[float] = field(default_factory=list)

    @property
    def non_coplanar(self) -> bool:
        s = self.translation_extent_mm
        return len(self.scans) >= 4 and s[2] > COPLANAR_RATIO * s[0] and s[2] > 1e-3


@dataclass
class ClosedFormResult:
    """Closed-form extrinsics and what they were computed from.

    Attributes:
        R: ``R_flange_sensor`` ``(3, 3)``, SVD-projected onto SO(3).
        R_unit: the patent's unit-norm matrix (columns normalized, ``r2 = r3 x r1``).
        R_least_squares: ``[r1, r3 x r1, r3]`` as least squares gave it (before any projection).
        t: ``t_flange_sensor`` ``(3,)``, m.
        normals / offsets: per placement ``(P, 3)`` and ``(P,)`` (m), fitted to the points with
            ``R, t``.
        groups: the motion groups found.
        rotation_groups: how many groups gave rotation equations.
        normals_singular_values: singular values of the stacked flange-frame normals ``M``.
        translation_condition: reciprocal condition of the column-normalized ``t`` system.
        orthogonality_error: ``|r1 . r3|`` / (``|r1| |r3|``) of the least-squares columns.
    """

    R: torch.Tensor
    R_unit: torch.Tensor
    R_least_squares: torch.Tensor
    t: torch.Tensor
    normals: torch.Tensor
    offsets: torch.Tensor
    groups: list[MotionGroup]
    rotation_groups: int
    normals_singular_values: list[float]
    translation_condition: float
    orthogonality_error: float


def _where(data: ProfileData, scan: int) -> dict:
    return {"path": data.path, "row": data.scan_lines[scan] if data.scan_lines else None}


def group_scans(T_base_flange: torch.Tensor, plane: torch.Tensor, tol_deg: float = 0.1) -> list[MotionGroup]:
    """Group scans of each placement whose flange orientations agree within ``tol_deg``."""
    R = T_base_flange[:, :3, :3]
    groups: list[MotionGroup] = []
    for j in range(R.shape[0]):
        for g in groups:
            if g.plane == int(plane[j]):
                angle = math.degrees(float(tf.rotation_angle(g.R_base_flange.T @ R[j])))
                if angle <= tol_deg:
                    g.scans.append(j)
                    break
        else:
            groups.append(MotionGroup(plane=int(plane[j]), scans=[j], R_base_flange=R[j]))
    for g in groups:
        p = T_base_flange[g.scans, :3, 3]
        s = torch.linalg.svdvals(p - p.mean(0)) * 1e3 if len(g.scans) > 1 else torch.zeros(3, dtype=p.dtype)
        g.translation_extent_mm = [*s.tolist(), 0.0, 0.0, 0.0][:3]
    return groups


def _group_plane(data: ProfileData, T_base_flange: torch.Tensor, group: MotionGroup) -> tuple[torch.Tensor, float, float, float]:
    """Solve (2) for one group: base normal ``n``, ``a = m . r1``, ``b = m . r3``, ``m . t - c``."""
    scans = torch.tensor(group.scans, device=data.uw.device)
    mask = torch.isin(data.point_scan, scans)
    uw = data.uw[mask]
    p = T_base_flange[data.point_scan[mask], :3, 3]
    p_mean = p.mean(0)
    cols = torch.cat([uw, p - p_mean, torch.ones_like(uw[:, :1])], 1)
    scale = cols.pow(2).mean(0).sqrt().clamp_min(1e-12)
    _, s, vh = torch.linalg.svd(cols / scale, full_matrices=False)
    if float(s[-2]) <= RANK_RATIO * float(s[0]):
        raise DataError(
            f"placement {data.plane_labels[group.plane]}: the points of the translated scans do not determine the plane "
            "(the system (u, w, flange position) has more than one solution); scan across the target at several depths",
            **_where(data, group.scans[0]),
        )
    v = vh[-1] / scale
    e = v[2:5]
    lam = 1.0 / float(e.norm())
    n = e * lam
    offset = (float(v[5]) - float(e @ p_mean)) * lam
    return n, float(v[0]) * lam, float(v[1]) * lam, offset


def _rotation(data: ProfileData, T_base_flange: torch.Tensor, groups: list[MotionGroup]):
    usable = [g for g in groups if g.non_coplanar]
    translated = [g for g in groups if len(g.scans) >= 2]
    if not translated:
        raise DataError(
            "no pure translations: no two scans of a placement share the flange orientation. The closed form needs, "
            "at >= 3 plane orientations, a scan plus >= 3 pure translations of the flange that are not coplanar",
            path=data.path,
        )
    if len(usable) < 3:
        bad = [g for g in translated if not g.non_coplanar]
        details = "; ".join(
            f"placement {data.plane_labels[g.plane]} at the orientation of scan '{data.scan_labels[g.scans[0]]}': "
            f"{len(g.scans)} scans, translation extents {', '.join(f'{v:.3g}' for v in g.translation_extent_mm)} mm"
            for g in bad[:4]
        )
        reason = (
            f"fewer than 3 plane orientations: only {len(usable)} plane orientation(s) (placement at a flange "
            "orientation) have >= 3 non-coplanar pure translations; need 3"
            if not bad
            else f"the translations are coplanar or too few (need 4 scans at one flange orientation whose positions "
            f"span 3-D; the third extent must exceed {COPLANAR_RATIO:.0%} of the first) in: {details}. "
            f"Only {len(usable)} plane orientation(s) are usable; need 3 (fewer than 3 plane orientations)"
        )
        raise DataError(f"degenerate motion set: {reason}", **_where(data, (bad or translated)[0].scans[0]))
    rows, a, b = [], [], []
    plane_normals: dict[int, list[torch.Tensor]] = {}
    for g in usable:
        n, ag, bg, _ = _group_plane(data, T_base_flange, g)
        ref = plane_normals.setdefault(g.plane, [])
        if ref and float(n @ ref[0]) < 0:  # one sign per placement
            n, ag, bg = -n, -ag, -bg
        ref.append(n)
        rows.append(g.R_base_flange.T @ n)
        a.append(ag)
        b.append(bg)
    M = torch.stack(rows)
    s = torch.linalg.svdvals(M)
    if len(rows) < 3 or float(s[2]) < NORMALS_RATIO * float(s[0]):
        angle = math.degrees(math.asin(min(1.0, float(s[2]) / max(float(s[0]), 1e-300)))) if len(rows) >= 3 else 0.0
        raise DataError(
            f"degenerate motion set: fewer than 3 plane orientations. The {len(rows)} plane normal(s) seen from the "
            f"flange lie (within {angle:.2g} deg) in one plane, so the sensor rotation about their common normal is "
            "not determined; place the target (or orient the flange) so that three normals differ by >= 15 deg "
            "out of one plane",
            **_where(data, usable[0].scans[0]),
        )
    a_t = torch.tensor(a, dtype=M.dtype, device=M.device)
    b_t = torch.tensor(b, dtype=M.dtype, device=M.device)
    pinv = torch.linalg.pinv(M)
    r1, r3 = pinv @ a_t, pinv @ b_t
    normals = {k: torch.stack(v).mean(0) for k, v in plane_normals.items()}
    normals = {k: v / v.norm() for k, v in normals.items()}
    return r1, r3, normals, len(rows), s.tolist()


def _translation(
    data: ProfileData, T_base_flange: torch.Tensor, R: torch.Tensor, normals: dict[int, torch.Tensor], groups: list[MotionGroup]
):
    planes = sorted(normals)
    column = {k: i for i, k in enumerate(planes)}
    point_plane = data.point_plane()
    mask = torch.isin(point_plane, torch.tensor(planes, device=point_plane.device))
    scan = data.point_scan[mask]
    pp = point_plane[mask]
    n = torch.stack([normals[int(k)] for k in pp.tolist()])
    pose = T_base_flange[scan]
    m = (pose[:, :3, :3].transpose(-1, -2) @ n.unsqueeze(-1)).squeeze(-1)
    s = sensor_points(data.uw[mask]) @ R.T
    y = -(n * ((pose[:, :3, :3] @ s.unsqueeze(-1)).squeeze(-1) + pose[:, :3, 3])).sum(-1)
    onehot = torch.zeros(len(pp), len(planes), dtype=m.dtype, device=m.device)
    onehot[torch.arange(len(pp)), torch.tensor([column[int(k)] for k in pp.tolist()])] = -1.0
    A = torch.cat([m, onehot], 1)
    scale = A.norm(dim=0).clamp_min(1e-300)
    _, sv, vh = torch.linalg.svd(A / scale, full_matrices=False)
    condition = float(sv[-1] / sv[0])
    if condition < RANK_RATIO:
        null = vh[-1] / scale
        axis = null[:3] / null[:3].norm().clamp_min(1e-300)
        rotated = [k for k in planes if sum(g.plane == k for g in groups) > 1]
        hint = (
            "no scan at a rotated flange orientation: add >= 3 rotations of the flange about different axes"
            if not rotated
            else "the flange orientations of each placement differ by rotations about one axis only"
        )
        raise DataError(
            f"degenerate motion set: {hint}. The sensor translation along {[round(float(v), 3) for v in axis]} "
            "(flange frame) is confounded with the plane offsets; rotate the flange about two non-parallel axes",
            path=data.path,
        )
    sol = torch.linalg.lstsq(A / scale, y.unsqueeze(-1)).solution.squeeze(-1) / scale
    return sol[:3], condition


def check_plane_coverage(data: ProfileData, points: torch.Tensor) -> torch.Tensor:
    """Fit every placement's plane to ``points`` (``base``); a placement seen along a single line is an error."""
    point_plane = data.point_plane()
    normals, offsets, spread = fit_planes(points, point_plane, data.n_planes)
    for k in range(data.n_planes):
        s = spread[k]
        if float(s[1]) <= 1e-6 * max(float(s[0]), 1e-300) or float(s[1]) < 1e-9:
            first = int((data.plane == k).nonzero()[0])
            raise DataError(
                f"the points of placement {data.plane_labels[k]} lie on one line (all its scans see the same line of "
                "the target), so its plane is not determined; translate the sensor across the laser line or rotate it",
                **_where(data, first),
            )
    return torch.cat([normals, offsets.unsqueeze(-1)], -1)


def closed_form(data: ProfileData, T_base_flange: torch.Tensor, *, orientation_tol_deg: float = 0.1) -> ClosedFormResult:
    """Closed-form ``R_flange_sensor`` and ``t_flange_sensor`` (see the module docstring).

    Args:
        data: validated profile scans (SI).
        T_base_flange: ``(S, 4, 4)`` flange pose of each scan (nominal or calibrated robot).
        orientation_tol_deg: flange orientations closer than this are one orientation (pure
            translations); commanded translations keep it exactly on the nominal model.

    Raises:
        DataError: a degenerate motion set, with what to add.
    """
    T = T_base_flange.to(data.uw)
    groups = group_scans(T, data.plane, orientation_tol_deg)
    r1, r3, normals, used, svals = _rotation(data, T, groups)
    R = rotation_from_columns(r1, r3)
    t, condition = _translation(data, T, R, normals, groups)
    points = base_points(T, data.point_scan, data.uw, R, t)
    planes = check_plane_coverage(data, points)
    return ClosedFormResult(
        R=R,
        R_unit=unit_columns(r1, r3),
        R_least_squares=torch.stack([r1, torch.linalg.cross(r3, r1), r3], -1),
        t=t,
        normals=planes[:, :3],
        offsets=planes[:, 3],
        groups=groups,
        rotation_groups=used,
        normals_singular_values=svals,
        translation_condition=condition,
        orthogonality_error=float((r1 @ r3).abs() / (r1.norm() * r3.norm())),
    )
