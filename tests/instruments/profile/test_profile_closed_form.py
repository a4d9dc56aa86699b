"""Closed-form extrinsics: exact on noise-free twin scans, and every degenerate motion set explained."""

from __future__ import annotations

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.instruments.profile.closed_form import closed_form, group_scans
from torchcal.instruments.profile.data import load_profile, write_profile_csv
from torchcal.instruments.profile.model import rotation_angle_deg
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A noise-free twin (4 placements; 3 translations, 3 rotations each), read back from its file."""
    twin = ProfileTwin(ProfileTwinConfig(seed=2, points_per_scan=40, noise_w_mm=0.0, n_translations=3, n_rotations=3, n_planes=4))
    path = write_profile_csv(tmp_path_factory.mktemp("profile") / "profile.csv", twin.scan())
    return twin, load_profile(path)


def _kinds(twin):
    return twin.plan.kinds


def test_noise_free_scans_give_the_exact_pose(clean):
    twin, data = clean
    T = twin.robot.flange_pose(data.q)
    result = closed_form(data, T)
    assert rotation_angle_deg(result.R, twin.R_true) < 1e-7
    assert float((result.t - twin.t_true).norm()) < 1e-10
    # least squares already gives orthonormal columns when the data are exact
    assert result.orthogonality_error < 1e-9
    torch.testing.assert_close(result.R_unit, twin.R_true, rtol=0, atol=1e-9)
    align = (result.normals * twin.normals).sum(-1).abs()
    torch.testing.assert_close(align, torch.ones_like(align), rtol=0, atol=1e-12)
    assert result.rotation_groups == 4


def test_groups_are_pure_translations(clean):
    twin, data = clean
    groups = group_scans(twin.robot.flange_pose(data.q), data.plane)
    translated = [g for g in groups if len(g.scans) > 1]
    assert len(translated) == 4 and all(len(g.scans) == 4 and g.non_coplanar for g in translated)
    assert sum(len(g.scans) == 1 for g in groups) == 4 * 3  # each rotation is its own orientation


def test_noisy_closed_form_is_close(generator):
    twin = ProfileTwin(ProfileTwinConfig(seed=5, points_per_scan=200))
    data = twin.scan()
    result = closed_form(data, twin.robot.flange_pose(data.q))
    assert rotation_angle_deg(result.R, twin.R_true) < 0.05
    assert float((result.t - twin.t_true).norm()) * 1e3 < 0.05


def test_coplanar_translations_are_rejected(clean):
    twin, data = clean
    T = twin.robot.flange_pose(data.q).clone()
    kinds = _kinds(twin)
    motions = twin.plan.motions
    for j, kind in enumerate(kinds):
        if kind == "translation" and float(motions[j, 2].abs()) > 0:  # move the depth translation into the others' plane
            ref = j - 3
            T[j, :3, 3] = T[ref + 1, :3, 3] + T[ref + 2, :3, 3] - T[ref, :3, 3]
    with pytest.raises(DataError, match="coplanar") as info:
        closed_form(data, T)
    assert info.value.row == data.scan_lines[0] and "translation extents 15, 15" in str(info.value)


def test_fewer_than_three_plane_orientations(clean):
    twin, data = clean
    sub = data.select_scans(data.plane < 2)
    with pytest.raises(DataError, match="fewer than 3 plane orientations"):
        closed_form(sub, twin.robot.flange_pose(sub.q))


def test_rotations_about_one_axis_only(clean):
    twin, data = clean
    motions = twin.plan.motions
    keep = torch.tensor([k != "rotation" or (float(m[0].abs()) > 0 and float(m[1:].abs().max()) == 0)
                         for k, m in zip(_kinds(twin), motions)])
    sub = data.select_scans(keep)
    with pytest.raises(DataError, match="rotations about one axis only") as info:
        closed_form(sub, twin.robot.flange_pose(sub.q))
    # the unobservable direction is the rotation axis: the sensor x axis in the flange frame
    axis = torch.tensor(eval(str(info.value).split("along ")[1].split(" (flange")[0]), dtype=torch.float64)
    assert abs(float(axis @ twin.R_design[:, 0])) / float(axis.norm()) > 0.99


def test_no_rotations(clean):
    twin, data = clean
    sub = data.select_scans(torch.tensor([k != "rotation" for k in _kinds(twin)]))
    with pytest.raises(DataError, match="no scan at a rotated flange orientation"):
        closed_form(sub, twin.robot.flange_pose(sub.q))


def test_no_translations(clean):
    twin, data = clean
    sub = data.select_scans(torch.tensor([k != "translation" for k in _kinds(twin)]))
    with pytest.raises(DataError, match="no pure translations"):
        closed_form(sub, twin.robot.flange_pose(sub.q))


def test_a_placement_seen_along_one_line(clean):
    twin, data = clean
    first_of_last = int((data.plane == 3).nonzero()[0])
    keep = (data.plane < 3) | (torch.arange(data.n_scans) == first_of_last)
    sub = data.select_scans(keep)
    with pytest.raises(DataError, match="placement 3 lie on one line") as info:
        closed_form(sub, twin.robot.flange_pose(sub.q))
    assert info.value.row == data.scan_lines[first_of_last] and info.value.path == data.path
