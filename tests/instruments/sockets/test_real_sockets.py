"""Socket calibration on the MUKCa recordings, read in place (skipped when the folder is absent)."""

from __future__ import annotations

import json

import pytest

from tests.conftest import REAL_DATA
from torchcal.cli import main

pytestmark = pytest.mark.real
FOLDER = REAL_DATA / "mukca-sockets"


def _fit_one_score_others(tmp_path, robot_id, urdf, train, others, *extra):
    model, out = tmp_path / "m", tmp_path / "e.json"
    data = str(FOLDER / f"sockets_{robot_id}.csv")
    assert main(["fit", "--robot", str(FOLDER / "raw" / "urdf" / urdf), "--end-link", "ball_link", "--data", data,
                 "--out", str(model), f"placements=[{train}]", *extra]) == 0
    assert main(["evaluate", "--model", str(model), "--data", data, "--json", str(out),
                 f"placements=[{','.join(others)}]", *extra]) == 0
    return json.loads(out.read_text())


def test_panda_1_fit_on_front_scored_on_the_other_placements(tmp_path):
    m = _fit_one_score_others(tmp_path, "panda_1", "panda.urdf", "front", ["back-high", "right"])
    assert m["n_rows"] == 120
    # nominal 7.72 / 2.76 mm; measured 0.637 / 0.645 (the source's README: 0.347 on its test data)
    assert m["nominal"]["consistency_mean_mm"] > 7.5
    assert m["consistency_mean_mm"] < 0.7
    assert m["distortion_mean_mm"] < 0.7


def test_kuka_14_fit_on_front_scored_on_the_other_placements(tmp_path):
    m = _fit_one_score_others(tmp_path, "kuka_14", "iiwa14.urdf", "front", ["left_back", "raised_left"])
    # nominal 0.81 mm; measured 0.262 / 0.069
    assert m["consistency_mean_mm"] < 0.3 and m["distortion_mean_mm"] < 0.1


URDFS = {"panda": "panda.urdf", "kuka": "iiwa14.urdf", "dinova": "gen3lite.urdf"}


@pytest.mark.parametrize("path", sorted(FOLDER.glob("sockets_*.csv")), ids=lambda p: p.stem)
def test_every_recording_passes_the_nominal_plausibility_checks(path):
    """The limits' margin is measured on these files (worst: panda_1_with_sensor, 24.3 mm per socket)."""
    import torch

    from torchcal.instruments.sockets.data import load_socket_data
    from torchcal.instruments.sockets.plausibility import check_nominal
    from torchcal.kinematics.robot import load_robot

    urdf = FOLDER / "raw" / "urdf" / URDFS[path.stem.split("_")[1]]
    robot = load_robot(urdf, end_link="ball_link")
    data = load_socket_data(path, robot, check_limits=False)  # the Kinova files pass q6 beyond the URDF's limits
    with torch.no_grad():
        check_nominal(robot.flange_pose(data.q), data, 50.0, robot.name)
    # a robot file that ends before the ball (at the gripper or the flange): the ball offset is fitted, not refused
    end = {"panda": "panda_link8", "kuka": "link_7", "dinova": "gripper_base_link"}[path.stem.split("_")[1]]
    flange_robot = load_robot(urdf, end_link=end)
    with torch.no_grad():
        check_nominal(flange_robot.flange_pose(data.q), data, 50.0, flange_robot.name)


def test_a_kinova_recording_with_another_robot_file_is_refused(tmp_path, capsys):
    """Used to fit with exit 0 (consistency 387 -> 9.3 mm) on the 6-joint twin robot."""
    from torchcal.kinematics.robot import default_robot_path

    data = FOLDER / "sockets_dinova_1.csv"
    assert main(["fit", "--robot", str(default_robot_path()), "--data", str(data), "--out", str(tmp_path / "m"),
                 "check_limits=false"]) == 2
    err = capsys.readouterr().err
    assert "sockets_dinova_1.csv, row 2" in err and "wrong robot file" in err
    assert not (tmp_path / "m").exists()
