"""Profile scans in the wrong unit, and sensor poses the scans do not determine: refused, never written."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from torchcal.cli import main
from torchcal.core.errors import DataError
from torchcal.instruments.profile.data import ProfileData, load_profile
from torchcal.instruments.profile.refine import MAX_SIGMA_ROTATION_DEG, refine
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig


@pytest.fixture(scope="module")
def profile_case(tmp_path_factory):
    """A simulated profile case on disk: robot.yaml and profile.csv (deg, mm)."""
    folder = tmp_path_factory.mktemp("pcase")
    assert main(["simulate", "instrument=profile", "--out", str(folder), "seed=8", "points_per_scan=60"]) == 0
    return folder


def _scaled(source: Path, target: Path, factor: float) -> Path:
    """``source`` with ``u, w`` multiplied by ``factor``."""
    rows = list(csv.reader(source.open()))
    index = [rows[0].index(c) for c in ("u", "w")]
    out = [rows[0]] + [[repr(float(v) * factor) if j in index else v for j, v in enumerate(r)] for r in rows[1:]]
    target.write_text("\n".join(",".join(r) for r in out) + "\n")
    return target


def _fit_error(capsys, case: Path, data: Path, out: Path) -> str:
    capsys.readouterr()
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(data), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not (out / "sensor.json").exists()
    return err


def test_u_w_in_metres_are_refused_naming_the_unit(tmp_path, profile_case, capsys):
    data = _scaled(profile_case / "profile.csv", tmp_path / "pm.csv", 1e-3)
    err = _fit_error(capsys, profile_case, data, tmp_path / "pm")
    assert "pm.csv" in err and "column 'u'" in err and "u, w look like metres; set length_unit=m" in err
    # read as metres the same file is accepted
    back = load_profile(data, length_unit="m")
    torch.testing.assert_close(back.uw, load_profile(profile_case / "profile.csv").uw, atol=1e-12, rtol=0)


def test_the_widest_scan_is_what_counts(tmp_path):
    # one scan a mm wide is enough to accept the file: a short line clipped by the target is real
    header = "scan,q1,q2,q3,q4,q5,q6,u,w\n"
    q = "10,-60,80,0,45,90"
    narrow = "".join(f"{s},{q},{u},{0.1 + u}\n" for s in (0, 1) for u in (0.0, 0.0002))
    path = tmp_path / "narrow.csv"
    path.write_text(header + narrow)
    with pytest.raises(DataError, match=r"widest scan \('0'\) spans only 0.000283 mm") as info:
        load_profile(path)
    assert (info.value.row, info.value.column) == (2, "u")
    path.write_text(header + narrow + f"2,{q},-0.6,100.1\n2,{q},0.6,100.2\n")
    assert load_profile(path).n_scans == 3


def test_a_rotation_the_scans_do_not_determine_is_refused_naming_it(tmp_path, profile_case, capsys):
    # u, w shrunk 30 times pass the unit check (scans ~1.5 mm wide) but leave the rotation at tens of degrees
    data = _scaled(profile_case / "profile.csv", tmp_path / "p30.csv", 1.0 / 30.0)
    err = _fit_error(capsys, profile_case, data, tmp_path / "p30")
    assert "p30.csv" in err and "determine the sensor rotation only to rot_" in err
    assert f"more than {MAX_SIGMA_ROTATION_DEG:g} deg" in err and "length_unit" in err


def test_refine_refuses_loose_rotations_but_keeps_good_ones():
    twin = ProfileTwin(ProfileTwinConfig(seed=1, points_per_scan=60))
    data = twin.scan()
    T = twin.robot.flange_pose(data.q)
    good = refine(data, T, twin.R_true, twin.t_true, twin.normals, twin.offsets)
    assert max(good.sigma_rotation_deg) < 0.01
    shrunk = ProfileData(**{**data.__dict__, "uw": data.uw / 30.0})
    with pytest.raises(DataError, match=r"rotation only to rot_\w \+-\d") as info:
        refine(shrunk, T, twin.R_true, twin.t_true, twin.normals, twin.offsets)
    assert "1 sigma" in str(info.value)
